"""Depth from a second camera moved into the colour camera (depth-colour registration).

Some RGB-D recordings keep the depth camera's own images: 7-Scenes (Kinect v1) ships them that way,
and a user's rig may too. Every stage assumes depth registered to colour (one camera), so such depth
is forward-projected into the colour camera as it is read: each valid depth pixel is back-projected
with the depth camera's intrinsics, moved by ``colour_from_depth`` and splatted to its nearest colour
pixel, the nearest surface winning; colour pixels nothing lands on are 0 (invalid).

intrinsics.json may describe the depth camera (the top-level fx, fy, cx, cy stay the colour camera's)::

    "depth_camera": {"fx": 585, "fy": 585, "cx": 320, "cy": 240,
                     "colour_from_depth": [-0.025, 0, 0]}

``colour_from_depth`` is X_colour = R X_depth + t, given as t (metres, R = I) or as a 4x4 rigid
matrix (rows). The layout's ground truth stays what it is: the colour camera's.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry import backproject, intrinsics_matrix, pose_from_rt, project, transform
from .transforms import FrameTransform, scale_matrix

JSON_KEY = "depth_camera"
EXAMPLE = '"depth_camera": {"fx": 585, "fy": 585, "cx": 320, "cy": 240, "colour_from_depth": [-0.025, 0, 0]}'


@dataclasses.dataclass(frozen=True)
class DepthCamera:
    """The depth camera of an unregistered RGB-D pair: its intrinsics ``K`` (on the depth images' own
    grid) and the rigid ``colour_from_depth`` (4x4: X_colour = R X_depth + t)."""

    K: np.ndarray
    colour_from_depth: np.ndarray

    def moved_to_colour(self, depth_poses: np.ndarray | None) -> np.ndarray | None:
        """Camera-to-world poses of the depth camera (N x 4 x 4) as the colour camera's."""
        if depth_poses is None:
            return None
        return depth_poses @ np.linalg.inv(self.colour_from_depth)


@dataclasses.dataclass(frozen=True)
class RegisterDepth(FrameTransform):
    """Depth forward-projected from ``camera`` into the colour camera ``colour_K`` (width x height);
    see the module docstring. A depth grid coarser than the colour grid is first repeated so that
    every depth pixel covers at most one colour pixel (no cracks between neighbours)."""

    camera: DepthCamera
    colour_K: np.ndarray
    width: int
    height: int

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        K = self.camera.K
        repeat = max(1, math.ceil(max(self.colour_K[0, 0] / K[0, 0], self.colour_K[1, 1] / K[1, 1]) - 1e-9))
        if repeat > 1:
            depth = np.repeat(np.repeat(depth, repeat, axis=0), repeat, axis=1)
            K = scale_matrix(K, repeat, repeat)
        moved = transform(self.camera.colour_from_depth, backproject(depth, K)[depth > 0])
        moved = moved[moved[:, 2] > 1e-6]
        zc = moved[:, 2]
        uc, vc = np.rint(project(moved, self.colour_K)).astype(np.int64).T
        inside = (uc >= 0) & (uc < self.width) & (vc >= 0) & (vc < self.height)
        nearest = np.full(self.width * self.height, np.inf)
        np.minimum.at(nearest, vc[inside] * self.width + uc[inside], zc[inside])
        nearest[np.isinf(nearest)] = 0.0
        return nearest.reshape(self.height, self.width).astype(np.float32)


def intrinsics_entry(json_path: Path, key: str) -> Any:
    """The ``key`` entry of an intrinsics.json, or None without the file or the entry (the file's syntax is
    checked where its intrinsics are read)."""
    try:
        values = json.loads(json_path.read_text())
    except (OSError, ValueError):
        return None
    return values.get(key) if isinstance(values, dict) else None


def depth_camera_in(json_path: Path) -> DepthCamera | None:
    """The ``depth_camera`` entry of an intrinsics.json (None without the file or the entry)."""
    entry = intrinsics_entry(json_path, JSON_KEY)
    if entry is None:
        return None
    fix = f"write {EXAMPLE} (colour_from_depth: a translation in metres, or a 4x4 rigid matrix)"
    if not isinstance(entry, dict) or any(k not in entry for k in ("fx", "fy", "cx", "cy", "colour_from_depth")):
        raise InputError(json_path, f"{JSON_KEY} needs fx, fy, cx, cy and colour_from_depth", fix)
    try:
        fx, fy, cx, cy = (float(entry[k]) for k in ("fx", "fy", "cx", "cy"))
        transform = np.asarray(entry["colour_from_depth"], dtype=float)
    except (TypeError, ValueError):
        raise InputError(json_path, f"{JSON_KEY} values are not numbers", fix) from None
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or min(fx, fy) <= 0:
        raise InputError(json_path, f"{JSON_KEY} fx and fy must be finite and positive, cx and cy finite", fix)
    return DepthCamera(intrinsics_matrix(fx, fy, cx, cy), rigid_transform(transform, json_path, fix))


def rigid_transform(value: np.ndarray, where: Path, fix: str) -> np.ndarray:
    """A 4x4 rigid matrix from a translation (3,) or a 4x4 matrix; an error naming ``where`` otherwise."""
    if value.shape == (3,):
        value = pose_from_rt(np.eye(3), value)
    if value.shape != (4, 4) or not np.all(np.isfinite(value)):
        raise InputError(where, f"{JSON_KEY} colour_from_depth has shape {value.shape}, not (3,) or (4, 4)", fix)
    R = value[:3, :3]
    if not (np.allclose(R.T @ R, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0
            and np.allclose(value[3], [0.0, 0.0, 0.0, 1.0])):
        raise InputError(where, f"{JSON_KEY} colour_from_depth is not a rigid transform", fix)
    return value
