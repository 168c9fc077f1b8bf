"""Replica as NICE-SLAM and SplaTAM ship it: ``results/frameNNNNNN.jpg``, ``results/depthNNNNNN.png``
(uint16, 6553.5 units per metre) and ``traj.txt`` (one camera-to-world 4x4 per line, 16 numbers,
row-major). The intrinsics are not in the folder: give them in ``intrinsics.json`` or with the flags
(NICE-SLAM's and SplaTAM's Replica camera: 1200x680, fx = fy = 600, cx = 599.5, cy = 339.5).
Frames are taken as 1/30 s apart.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import Sequence
from .common import NOMINAL_FPS, ReadOptions, intrinsics_with_defaults, json_keys, numbered, rigid

NAME = "replica"
COLOR = r"frame(\d+)\.(?:jpg|png)"
DEPTH_SCALE = 6553.5
STANDARD = '{"fx": 600, "fy": 600, "cx": 599.5, "cy": 339.5}'


def detect(root: Path) -> bool:
    return (root / "results").is_dir() and ((root / "traj.txt").is_file() or bool(numbered(root / "results", COLOR)))


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    colors = numbered(root / "results", COLOR)
    if not colors:
        raise InputError(root / "results", "no colour frames (frameNNNNNN.jpg)", "give a Replica folder as NICE-SLAM ships it")
    rgb_paths = list(colors.values())
    depth_paths = [p.with_name("depth" + p.name[len("frame"):]).with_suffix(".png") for p in rgb_paths]
    missing = next((p for p in depth_paths if not p.is_file()), None)
    if missing is not None:
        raise InputError(missing, "depth frame missing for its colour frame", "restore it or remove that colour frame")
    given = json_keys(root / "intrinsics.json") | set(options.override.values())
    if not all(k in given for k in ("fx", "fy", "cx", "cy")):
        raise InputError(root / "intrinsics.json", "Replica folders carry no intrinsics and none were given",
                         f"write intrinsics.json with {STANDARD} (NICE-SLAM's Replica camera) or pass --fx --fy --cx --cy")
    intrinsics = intrinsics_with_defaults(root, options.override, rgb_paths[0], {"depth_scale": DEPTH_SCALE})
    return Sequence(root, NAME, intrinsics, np.array(list(colors), dtype=float) / NOMINAL_FPS, rgb_paths, depth_paths,
                    gt_poses=_trajectory(root / "traj.txt", len(rgb_paths)), names=[p.stem for p in rgb_paths])


def _trajectory(path: Path, frames: int) -> np.ndarray | None:
    if not path.is_file():
        return None
    fix = "write one camera-to-world 4x4 matrix per frame, 16 numbers per line, row-major"
    rows = [line.split() for line in path.read_text(errors="replace").splitlines() if line.strip()]
    if len(rows) != frames or any(len(r) != 16 for r in rows):
        raise InputError(path, f"has {len(rows)} lines for {frames} frames (16 numbers each expected)", fix)
    try:
        poses = np.array(rows, dtype=float).reshape(frames, 4, 4)
    except ValueError:
        raise InputError(path, "holds something that is not a number", fix) from None
    return rigid(poses)
