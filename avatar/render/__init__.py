"""Renderers: the mesh rasterizer for synthetic data (mesh_raster) and, later, Gaussian backends."""
