"""taichi-gs's own layout (written by ``taichi-gs synth`` and ``taichi-gs import``)::

    SEQ/intrinsics.json   {"width", "height", "fx", "fy", "cx", "cy", "depth_scale"}, and "depth_camera" for
                          depth from its own camera, registered as it is read (``io.registration``), and
                          "readout_ms" for a colour camera with a rolling shutter (``io.readout``;
                          ``Sequence.source["readout_ms"]``, what ``camera_readout`` takes)
    SEQ/frames.txt        "timestamp rgb/NAME.png depth/NAME.png" per frame, optionally a 4th column: the moment
                          the depth frame shows, on the colour clock (``Sequence.depth_timestamps``; ``import``
                          writes it where the reading knows it, e.g. TUM's separate depth stream)
    SEQ/groundtruth.txt   optional TUM trajectory (camera-to-world), matched to frames by time
    SEQ/exposure.txt      optional "timestamp" + start and end pose (tx ty tz qx qy qz qw each)
    SEQ/sharp/NAME.png    optional sharp mid-exposure colour, same stem as the rgb file
    SEQ/sourced.png       optional 8-bit mask, 255 where a colour pixel came from camera pixels (what
                          ``import`` writes for frames that had an unsourced border, e.g. undistorted ones)
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...errors import InputError
from ..readout import READOUT_KEY, readout_in
from ..registration import RegisterDepth, depth_camera_in
from ..sequence import Sequence
from ..trajectory import read_tum_rows, tum_rows_to_poses
from .common import (
    ReadOptions,
    check_increasing,
    ground_truth,
    listed_file,
    read_list,
    resolve_intrinsics,
)

NAME = "taichi-gs"


def detect(root: Path) -> bool:
    return (root / "frames.txt").is_file()


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    list_path = root / "frames.txt"
    rows = read_list(list_path, columns=3, optional=1)
    timestamps = np.array([float(r[0]) for r in rows])
    check_increasing(list_path, timestamps)
    rgb_paths = [listed_file(root, r[1], list_path) for r in rows]
    depth_paths = [listed_file(root, r[2], list_path) for r in rows]
    depth_timestamps = depth_times(list_path, rows)
    intrinsics = resolve_intrinsics(root, options.override, rgb_paths[0])
    sharp_dir = root / "sharp"
    sharp_paths = None
    if sharp_dir.is_dir():
        sharp_paths = [sharp_dir / p.name for p in rgb_paths]
        missing = [p for p in sharp_paths if not p.is_file()]
        if missing:
            raise InputError(missing[0], "sharp image missing", "restore it or remove the sharp/ folder")
    sourced = root / "sourced.png"
    depth_camera = depth_camera_in(root / "intrinsics.json")
    sequence = Sequence(
        root, NAME, intrinsics, timestamps, rgb_paths, depth_paths,
        gt_poses=ground_truth(root / "groundtruth.txt", timestamps),
        exposure_poses=read_exposure(root / "exposure.txt", timestamps),
        sharp_paths=sharp_paths, sourced_path=sourced if sourced.is_file() else None,
        transform=None if depth_camera is None else RegisterDepth(depth_camera, intrinsics.K(), intrinsics.width,
                                                                   intrinsics.height),
        depth_timestamps=depth_timestamps,
    )
    readout_ms = readout_in(root / "intrinsics.json")
    if readout_ms is not None:
        sequence.source = {**sequence.source, READOUT_KEY: readout_ms}
    return sequence


def depth_times(list_path: Path, rows: list[list[str]]) -> np.ndarray | None:
    """The depth frames' own timestamps from the frame list's optional 4th column (on every line or on none)."""
    stamps = [r[3] for r in rows if len(r) > 3]
    if not stamps:
        return None
    if len(stamps) != len(rows):
        raise InputError(list_path, f"{len(stamps)} of {len(rows)} lines give a depth timestamp (4th column)",
                         "give it on every line or on none")
    try:
        values = np.array([float(v) for v in stamps])
    except ValueError:
        raise InputError(list_path, "a depth timestamp (4th column) is not a number",
                         "fix or remove the column") from None
    if not np.all(np.isfinite(values)):
        raise InputError(list_path, "a depth timestamp (4th column) is NaN or inf", "fix or remove the column")
    return values


def read_exposure(path: Path, timestamps: np.ndarray) -> np.ndarray | None:
    """(N, 2, 4, 4) exposure start and end poses (camera-to-world) per frame from an exposure.txt (a timestamp and
    two TUM poses per line, one line per frame of ``timestamps``); None without the file."""
    if not path.is_file():
        return None
    rows = read_tum_rows(path, columns=15)
    if len(rows) != len(timestamps) or not np.allclose(rows[:, 0], timestamps, atol=1e-6):
        raise InputError(path, f"has {len(rows)} rows not matching the {len(timestamps)} frames' timestamps",
                         "write one 'timestamp start-pose end-pose' line per frame")
    start = tum_rows_to_poses(rows[:, :8])
    end = tum_rows_to_poses(np.concatenate([rows[:, :1], rows[:, 8:15]], axis=1))
    return np.stack([start, end], axis=1)
