"""Reading RGB-D sequences and writing trajectories, point clouds and splat PLY files."""
