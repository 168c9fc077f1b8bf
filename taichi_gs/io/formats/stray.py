"""Phone captures in Stray Scanner's layout: ``rgb/NNNNNN.jpg|png`` (colour frames, extracted from
``rgb.mp4``), ``depth/NNNNNN.png`` (uint16 mm) or ``.npy`` / 32-bit float ``.tif`` (metres), smaller than
colour, ``confidence/NNNNNN.png`` (0, 1, 2: depth below ``MIN_CONFIDENCE`` is dropped),
``camera_matrix.csv`` (3x3, for the colour image) and ``odometry.csv`` (header, then ``timestamp,
frame, x, y, z, qx, qy, qz, qw`` per frame: ARKit camera-to-world, camera looking down -z, y up).

Colour is resampled onto the depth grid (intrinsics scaled with the pixel-centre convention), so the
sequence has the depth size. Record3D's EXR+JPG export reads the same way once converted (see README).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import Intrinsics, Sequence, read_depth, read_image
from ..transforms import MaskDepth, ResampleColor, scale_matrix, then
from ..trajectory import tum_rows_to_poses
from .common import ReadOptions, numbered, read_matrix

NAME = "stray"
MIN_CONFIDENCE = 2  # ARKit: 0 low, 1 medium, 2 high
FPS = 60.0  # Stray Scanner's frame rate, for frames without odometry timestamps
ARKIT_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def detect(root: Path) -> bool:
    return (root / "depth").is_dir() and any((root / n).exists() for n in ("confidence", "odometry.csv", "camera_matrix.csv"))


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    colors = numbered(root / "rgb", r"(\d+)\.(?:jpg|png)")
    if not colors:
        raise InputError(root / "rgb", "no colour frames", "extract them from the video first: "
                         "mkdir rgb && ffmpeg -i rgb.mp4 -start_number 0 rgb/%06d.png")
    depths = numbered(root / "depth", r"(\d+)\.(?:png|npy|tif|tiff)")
    missing = next((n for n in colors if n not in depths), None)
    if missing is not None:
        raise InputError(root / "depth" / f"{missing:06d}.png", "depth frame missing for its colour frame",
                         "restore it or remove that colour frame")
    rgb_paths, depth_paths = list(colors.values()), [depths[n] for n in colors]
    matrix_path = root / "camera_matrix.csv"
    if not matrix_path.is_file():
        raise InputError(matrix_path, "camera matrix missing", "write the colour camera's 3x3 intrinsics, one row per line")
    K_color = read_matrix(matrix_path, (3, 3), "camera matrix", "write a 3x3 matrix, one row per line")
    color_h, color_w = read_image(rgb_paths[0]).shape[:2]
    depth_scale = options.override.depth_scale or 1000.0
    height, width = read_depth(depth_paths[0], depth_scale).shape
    K = scale_matrix(K_color, width / color_w, height / color_h)
    values = {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "depth_scale": depth_scale, **options.override.values()}
    intrinsics = Intrinsics(width=width, height=height, **{k: float(v) for k, v in values.items()})
    transform = ResampleColor(K_color, intrinsics.K(), width, height)
    if (root / "confidence").is_dir():
        confidence = {depths[n]: root / "confidence" / f"{depths[n].stem}.png" for n in colors}
        absent = next((p for p in confidence.values() if not p.is_file()), None)
        if absent is not None:
            raise InputError(absent, "confidence map missing", "restore it, or remove the confidence/ folder to use all depth")
        transform = then(transform, MaskDepth(confidence, MIN_CONFIDENCE))
    timestamps, gt = _odometry(root / "odometry.csv", list(colors))
    return Sequence(root, NAME, intrinsics, timestamps, rgb_paths, depth_paths, gt_poses=gt,
                    names=[f"{n:06d}" for n in colors], transform=transform)


def _odometry(path: Path, frames: list[int]) -> tuple[np.ndarray, np.ndarray | None]:
    if not path.is_file():
        return np.array(frames, dtype=float) / FPS, None
    fix = "write a header line, then 'timestamp, frame, x, y, z, qx, qy, qz, qw' per frame"
    try:
        rows = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError:
        raise InputError(path, "is not a table of numbers under one header line", fix) from None
    if rows.shape[1] != 9:
        raise InputError(path, f"has {rows.shape[1]} columns", fix)
    by_frame = {int(round(r[1])): r for r in rows}
    missing = next((n for n in frames if n not in by_frame), None)
    if missing is not None:
        raise InputError(path, f"has no row for frame {missing}", fix)
    picked = np.array([by_frame[n] for n in frames])
    tum = np.concatenate([picked[:, :1], picked[:, 2:9]], axis=1)  # timestamp x y z qx qy qz qw
    return picked[:, 0], tum_rows_to_poses(tum) @ ARKIT_TO_OPENCV
