"""taichi-gs: splat-based 3D reconstruction from motion-blurred RGB-D sequences, in Taichi."""

__version__ = "0.1.0"
