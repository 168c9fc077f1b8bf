"""bench/realdata.py's depth-to-colour registration: known answers on a plane."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from realdata import register_depth  # noqa: E402


def test_registration_of_a_plane_shifts_by_the_baseline_and_rescales_the_focal():
    h, w, z = 48, 64, 2.0
    K_depth = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    depth = np.full((h, w), z)
    same = register_depth(depth, K_depth, K_depth, np.zeros(3), (w, h))
    assert np.allclose(same, z)
    # colour camera 0.1 m along -x of the depth camera's frame: points move by +0.1 m, 3 px at z = 2
    shifted = register_depth(depth, K_depth, K_depth, np.array([0.1, 0.0, 0.0]), (w, h))
    assert np.allclose(shifted[:, 3:], z) and np.all(shifted[:, :3] == 0)
    # a shorter colour focal length sees the depth image smaller: an empty border, the plane intact
    K_colour = K_depth.copy()
    K_colour[0, 0] = K_colour[1, 1] = 45.0
    small = register_depth(depth, K_depth, K_colour, np.zeros(3), (w, h))
    assert np.all(small[:, :6] == 0) and np.all(small[:, -6:] == 0) and np.allclose(small[10:-10, 10:-10], z)


def test_the_nearest_surface_wins():
    K = np.array([[60.0, 0, 31.5], [0, 60.0, 23.5], [0, 0, 1]])
    depth = np.full((48, 64), 3.0)
    depth[:, 20:24] = 1.0  # a near post
    out = register_depth(depth, K, K, np.array([0.05, 0.0, 0.0]), (64, 48))
    # the post moves 3 px right, the wall 1 px: the post hides the wall where both land
    assert np.allclose(out[:, 23:27], 1.0)
