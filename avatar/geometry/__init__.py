"""Geometry shared by fitting and training (the low room both import): the cameras' views of a sequence, the
triangles' local frames and rotations, and winding numbers."""
