"""Microsoft 7-Scenes as distributed: ``frame-NNNNNN.color.png|jpg``, ``.depth.png`` (uint16 mm;
0 and 65535 invalid) and ``.pose.txt`` (camera-to-world 4x4), either flat in the folder or in one
``seq-NN/`` subfolder. Intrinsics: ``camera-intrinsics.txt`` (3x3) if present, else the dataset's
published fx = fy = 585, cx = 320, cy = 240; intrinsics.json and the flags win over both.
Frames are 1/30 s apart. Without pose files the sequence runs without ground truth.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import Sequence
from ..transforms import DropDepthAbove
from .common import NOMINAL_FPS, ReadOptions, intrinsics_with_defaults, numbered, pose_files, read_matrix

NAME = "7scenes"
COLOR = r"frame-(\d+)\.color\.(?:png|jpg)"
DEFAULTS = {"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0, "depth_scale": 1000.0}
NO_READING = 65535  # depth code for "no reading", besides 0


def _sequence_folders(root: Path) -> list[Path]:
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and re.fullmatch(r"seq-\d+", p.name) and numbered(p, COLOR))


def detect(root: Path) -> bool:
    return bool(numbered(root, COLOR)) or bool(_sequence_folders(root))


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    folder = root
    if not numbered(root, COLOR):
        folders = _sequence_folders(root)
        if len(folders) != 1:
            names = ", ".join(p.name for p in folders) or "none"
            raise InputError(root, f"holds {len(folders)} 7-Scenes sequences ({names}) and no frames of its own",
                             "give one seq-NN folder (sequences are separate recordings)")
        folder = folders[0]
    colors = numbered(folder, COLOR)
    stems = [p.name.split(".color.")[0] for p in colors.values()]
    depth_paths = [folder / f"{s}.depth.png" for s in stems]
    missing = next((p for p in depth_paths if not p.is_file()), None)
    if missing is not None:
        raise InputError(missing, "depth image missing for its colour frame", "restore it or remove that frame's files")
    defaults = dict(DEFAULTS)
    for place in (folder, root):
        if (place / "camera-intrinsics.txt").is_file():
            K = read_matrix(place / "camera-intrinsics.txt", (3, 3), "camera matrix", "write a 3x3 matrix, one row per line")
            defaults.update(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
            break
    rgb_paths = list(colors.values())
    intrinsics = intrinsics_with_defaults(root, options.override, rgb_paths[0], defaults)
    timestamps = np.array(list(colors), dtype=float) / NOMINAL_FPS
    gt = pose_files([folder / f"{s}.pose.txt" for s in stems],
                    "restore it, or remove every .pose.txt file to run without ground truth")
    return Sequence(root, NAME, intrinsics, timestamps, rgb_paths, depth_paths, gt_poses=gt, names=stems,
                    transform=DropDepthAbove((NO_READING - 0.5) / intrinsics.depth_scale))
