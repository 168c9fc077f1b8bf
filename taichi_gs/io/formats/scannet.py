"""ScanNet as its SensReader exports it: ``color/N.jpg`` (1296x968), ``depth/N.png`` (uint16 mm,
640x480), ``pose/N.txt`` (camera-to-world 4x4; rows of -inf mark an invalid pose), and
``intrinsic/intrinsic_color.txt``, ``intrinsic_depth.txt`` (4x4). Frames in numeric order, 1/30 s apart.

Colour is larger than depth and has its own intrinsics; it is resampled onto the depth image's grid
(area shrink, then the exact affine map between the two pixel grids, pixel-centre convention), so
the sequence has the depth camera's size and intrinsics. The flags override those output intrinsics.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import Intrinsics, Sequence, read_image
from ..transforms import ResampleColor
from .common import NOMINAL_FPS, ReadOptions, numbered, pose_files, read_matrix

NAME = "scannet"
COLOR = r"(\d+)\.(?:jpg|png)"
MATRIX_FIX = "export the scene with ScanNet's SensReader (it writes intrinsic/intrinsic_color.txt and intrinsic_depth.txt)"


def detect(root: Path) -> bool:
    return (root / "color").is_dir() and (root / "depth").is_dir() and ((root / "intrinsic").is_dir() or (root / "pose").is_dir())


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    colors = numbered(root / "color", COLOR)
    if not colors:
        raise InputError(root / "color", "no colour frames (N.jpg)", "export the scene with ScanNet's SensReader")
    depth_paths = [root / "depth" / f"{n}.png" for n in colors]
    missing = next((p for p in depth_paths if not p.is_file()), None)
    if missing is not None:
        raise InputError(missing, "depth frame missing for its colour frame", "restore it or remove that colour frame")
    K_color, K_depth = (_matrix(root / "intrinsic" / f"intrinsic_{kind}.txt") for kind in ("color", "depth"))
    height, width = read_image(depth_paths[0]).shape[:2]
    values = {"fx": K_depth[0, 0], "fy": K_depth[1, 1], "cx": K_depth[0, 2], "cy": K_depth[1, 2], "depth_scale": 1000.0,
              **options.override.values()}
    intrinsics = Intrinsics(width=width, height=height, **{k: float(v) for k, v in values.items()})
    gt = pose_files([root / "pose" / f"{n}.txt" for n in colors],
                    "restore it, or remove the pose/ folder to run without ground truth")
    return Sequence(root, NAME, intrinsics, np.array(list(colors), dtype=float) / NOMINAL_FPS, list(colors.values()),
                    depth_paths, gt_poses=gt, names=[f"{n:06d}" for n in colors],
                    transform=ResampleColor(K_color, intrinsics.K(), width, height))


def _matrix(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "intrinsics file missing", MATRIX_FIX)
    K = read_matrix(path, (4, 4), "intrinsics matrix", MATRIX_FIX)[:3, :3]
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(path, "intrinsics matrix has a non-positive or non-finite focal length", MATRIX_FIX)
    return K
