"""Neural network building blocks (importable without the pipeline).

``encoding`` (NeRF positional encoding), ``mlp`` (the paper's delta MLPs), ``pointnet2`` (the PointNet++
geometry encoder giving the 1024-d feature F).
"""
