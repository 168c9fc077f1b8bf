"""Depth-colour registration (io.registration) against a scene whose depth is known in closed form:
a wall at z = WALL with a box face at z = BOX in front of it, seen by a depth camera and by a colour
camera with another focal length, 10 cm to its side."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from taichi_gs.errors import InputError
from taichi_gs.geometry import pose_from_rt
from taichi_gs.io.load import load_sequence
from taichi_gs.io.registration import DepthCamera, RegisterDepth

WALL, BOX = 2.5, 1.2
BOX_HALF = (0.3, 0.2)  # metres, in x and y
DEPTH_K = np.array([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]])  # 80 x 60
COLOUR_K = np.array([[63.0, 0.0, 40.0], [0.0, 63.0, 30.0], [0.0, 0.0, 1.0]])  # 80 x 60, another centre
COLOUR_FROM_DEPTH = pose_from_rt(np.eye(3), np.array([-0.1, 0.0, 0.0]))


def scene_depth(K: np.ndarray, centre_x: float, width: int = 80, height: int = 60) -> np.ndarray:
    """Depth (z) of the wall-and-box scene from a camera at (centre_x, 0, 0) looking down +z."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    on_box = (np.abs(centre_x + x * BOX) < BOX_HALF[0]) & (np.abs(y * BOX) < BOX_HALF[1])
    return np.where(on_box, BOX, WALL).astype(np.float32)


def test_registered_depth_is_what_the_colour_camera_sees():
    """The colour camera sits at x = +0.1 (X_colour = X_depth - 0.1): its registered depth matches the
    scene's depth from there except on a few pixels at the box's edges (nearest-pixel splatting); where
    the depth camera saw nothing (the wall behind the box, beyond its field of view) it is 0, not a
    guess. The depth image as it is does not match."""
    depth = scene_depth(DEPTH_K, 0.0)
    expected = scene_depth(COLOUR_K, 0.1)
    registered = RegisterDepth(DepthCamera(DEPTH_K, COLOUR_FROM_DEPTH), COLOUR_K, 80, 60).depth(Path("d.png"), depth)
    valid = registered > 0
    assert (np.abs(registered - expected) < 1e-4)[valid].mean() > 0.98
    assert valid[expected == BOX].mean() > 0.97 and valid.mean() > 0.75
    assert np.all(expected[~valid] == WALL)
    box = (depth == BOX) | (expected == BOX)  # pixels where either camera sees the box
    assert (np.abs(registered - expected) < 1e-4)[box & valid].mean() > 0.95
    assert (np.abs(depth - expected) < 1e-4)[box].mean() < 0.7


def test_a_coarser_depth_grid_leaves_no_cracks():
    """Depth at half the colour grid's resolution covers as much of the colour grid as full-resolution
    depth does (each depth pixel is repeated before splatting, so no cracks) and matches the scene there."""
    K_half = np.array([[35.0, 0.0, 19.5], [0.0, 35.0, 14.5], [0.0, 0.0, 1.0]])
    camera = DepthCamera(K_half, COLOUR_FROM_DEPTH)
    registered = RegisterDepth(camera, COLOUR_K, 80, 60).depth(Path("d.png"), scene_depth(K_half, 0.0, 40, 30))
    full = RegisterDepth(DepthCamera(DEPTH_K, COLOUR_FROM_DEPTH), COLOUR_K, 80, 60).depth(
        Path("d.png"), scene_depth(DEPTH_K, 0.0))
    assert (registered > 0).mean() > 0.97 * (full > 0).mean()
    assert (np.abs(registered - scene_depth(COLOUR_K, 0.1)) < 1e-4)[registered > 0].mean() > 0.95


def test_depth_camera_in_intrinsics_json_registers_the_own_layout(tmp_path):
    """intrinsics.json's depth_camera makes the own layout register its depth as it reads it."""
    folder = _own_layout(tmp_path / "seq", {"fx": 70.0, "fy": 70.0, "cx": 39.5, "cy": 29.5,
                                            "colour_from_depth": [-0.1, 0.0, 0.0]})
    seq = load_sequence(folder)
    expected = RegisterDepth(DepthCamera(DEPTH_K, COLOUR_FROM_DEPTH), COLOUR_K, 80, 60).depth(
        Path("d.png"), scene_depth(DEPTH_K, 0.0))
    assert np.allclose(seq.depth(0), expected, atol=1e-3)
    matrix = np.eye(4)
    matrix[0, 3] = -0.1
    same = load_sequence(_own_layout(tmp_path / "matrix", {"fx": 70.0, "fy": 70.0, "cx": 39.5, "cy": 29.5,
                                                           "colour_from_depth": matrix.tolist()}))
    assert np.array_equal(same.depth(0), seq.depth(0))


@pytest.mark.parametrize("entry, message", [
    ({"fx": 70.0, "fy": 70.0, "cx": 39.5, "colour_from_depth": [0, 0, 0]}, "needs fx, fy, cx, cy"),
    ({"fx": 70.0, "fy": 70.0, "cx": 39.5, "cy": 29.5, "colour_from_depth": [0, 0]}, "not \\(3,\\) or \\(4, 4\\)"),
    ({"fx": 70.0, "fy": 70.0, "cx": 39.5, "cy": 29.5, "colour_from_depth": (2 * np.eye(4)).tolist()},
     "not a rigid transform"),
    ({"fx": -70.0, "fy": 70.0, "cx": 39.5, "cy": 29.5, "colour_from_depth": [0, 0, 0]}, "finite and positive"),
    ({"fx": "a", "fy": 70.0, "cx": 39.5, "cy": 29.5, "colour_from_depth": [0, 0, 0]}, "not numbers"),
])
def test_a_bad_depth_camera_entry_names_intrinsics_json(tmp_path, entry, message):
    folder = _own_layout(tmp_path / "seq", entry)
    with pytest.raises(InputError, match=message) as caught:
        load_sequence(folder)
    assert caught.value.path == folder / "intrinsics.json"


def test_depth_camera_poses_move_to_the_colour_camera():
    """A depth camera at the world origin, colour camera 0.1 m along its x axis (turned 90 deg about z):
    the colour camera's centre is the depth camera's x axis times 0.1."""
    R = cv2.Rodrigues(np.array([0.0, 0.0, np.pi / 2]))[0]
    depth_pose = np.eye(4)
    depth_pose[:3, :3] = R
    moved = DepthCamera(DEPTH_K, COLOUR_FROM_DEPTH).moved_to_colour(depth_pose[None])[0]
    assert np.allclose(moved[:3, 3], 0.1 * R[:, 0]) and np.allclose(moved[:3, :3], R)


def _own_layout(folder: Path, depth_camera: dict) -> Path:
    """Two frames of the scene in taichi-gs's layout: colour from COLOUR_K (flat grey: only depth matters
    here), depth from the depth camera in uint16 mm, intrinsics.json with ``depth_camera``."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    lines = []
    for i in range(2):
        cv2.imwrite(str(folder / f"rgb/{i}.png"), np.full((60, 80, 3), 128, np.uint8))
        cv2.imwrite(str(folder / f"depth/{i}.png"), np.round(scene_depth(DEPTH_K, 0.0) * 1000).astype(np.uint16))
        lines.append(f"{i / 30:.6f} rgb/{i}.png depth/{i}.png")
    (folder / "frames.txt").write_text("\n".join(lines) + "\n")
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 63.0, "fy": 63.0, "cx": 40.0, "cy": 30.0,
                                                        "depth_scale": 1000.0, "depth_camera": depth_camera}))
    return folder
