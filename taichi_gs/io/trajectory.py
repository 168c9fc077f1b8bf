"""TUM trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, camera-to-world; poses interpolated in time."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputError
from ..geometry import pose_from_rt, quat_to_rotmat, rotmat_to_quat
from .atomic import write_text


# [ours] Stamps of a stage's trajectory and of the frames it was made for agree to the 6 decimals it is written
# with; frames are at least 1/100 s apart, so a larger difference means other frames
FRAME_TIME_TOLERANCE_S = 1e-3


def check_frame_times(path: Path, timestamps: np.ndarray, frame_times: np.ndarray, fix: str) -> None:
    """A one-line error naming ``path`` when its ``timestamps`` (one per pose) are not the sequence's
    ``frame_times``: another count, or another frame's stamp (a run folder reopened on other frames)."""
    if len(timestamps) != len(frame_times):
        raise InputError(path, f"{len(timestamps)} poses for {len(frame_times)} frames", fix)
    gap = np.abs(np.asarray(timestamps, dtype=np.float64) - np.asarray(frame_times, dtype=np.float64))
    if np.any(gap > FRAME_TIME_TOLERANCE_S):
        k = int(np.argmax(gap > FRAME_TIME_TOLERANCE_S))  # the first
        raise InputError(path, f"poses are stamped for other frames (pose {k} at {float(timestamps[k]):.6f} s, "
                               f"frame {k} at {float(frame_times[k]):.6f} s)", fix)


def format_tum(timestamps: np.ndarray, poses: np.ndarray, header: str | None = None) -> str:
    """TUM text of camera-to-world poses (N x 4 x 4)."""
    lines = [f"# {header}"] if header else []
    for t, T in zip(timestamps, poses):
        w, x, y, z = rotmat_to_quat(T[:3, :3])
        tx, ty, tz = T[:3, 3]
        lines.append(f"{t:.6f} {tx:.9f} {ty:.9f} {tz:.9f} {x:.9f} {y:.9f} {z:.9f} {w:.9f}")
    return "\n".join(lines) + "\n"


def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray, header: str | None = None) -> None:
    """Write camera-to-world poses (N x 4 x 4) as a TUM trajectory file, atomically."""
    if len(timestamps) != len(poses):
        raise ValueError(f"{len(timestamps)} timestamps but {len(poses)} poses")
    write_text(path, format_tum(timestamps, poses, header))


def read_tum_rows(path: str | Path, columns: int = 8) -> np.ndarray:
    """Numeric rows of a whitespace/comma separated file, skipping '#' comments and blank lines."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "file not found", "give the path of an existing TUM trajectory file")
    rows, numbers = [], []
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) < columns:
            raise InputError(path, f"line {n} has {len(parts)} values, expected {columns}",
                             "use 'timestamp tx ty tz qx qy qz qw' per line")
        try:
            rows.append([float(p) for p in parts[:columns]])
            numbers.append(n)
        except ValueError:
            raise InputError(path, f"line {n} is not numeric", "remove or comment out the line") from None
    if not rows:
        raise InputError(path, "no poses in file", "write one 'timestamp tx ty tz qx qy qz qw' line per pose")
    data = np.asarray(rows)
    if not np.all(np.isfinite(data)):
        raise InputError(path, "NaN or inf in trajectory", "remove the non-finite rows")
    _check_quaternions(path, data, numbers)
    return data


def _check_quaternions(path: Path, data: np.ndarray, numbers: list[int]) -> None:
    """Every pose's quaternion (columns 4-7, and 11-14 in 15-column exposure rows) must have a
    usable norm: a zero quaternion is no rotation at all and would turn into NaN poses."""
    for first in range(4, data.shape[1] - 3, 7):
        norms = np.linalg.norm(data[:, first:first + 4], axis=1)
        bad = np.flatnonzero(norms < 1e-6)
        if bad.size:
            lines = ", ".join(str(numbers[i]) for i in bad[:5]) + (" ..." if bad.size > 5 else "")
            raise InputError(path, f"{bad.size} pose(s) with a zero quaternion (line {lines})",
                             "write unit quaternions 'qx qy qz qw', or delete those lines")


def tum_rows_to_poses(rows: np.ndarray) -> np.ndarray:
    """Camera-to-world 4x4 poses from TUM rows (``tx ty tz qx qy qz qw`` in columns 1..7)."""
    return np.stack(
        [pose_from_rt(quat_to_rotmat([r[7], r[4], r[5], r[6]]), r[1:4]) for r in rows]
    )


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N x 4 x 4) of a TUM trajectory file."""
    rows = read_tum_rows(path)
    return rows[:, 0], tum_rows_to_poses(rows)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray, tolerance: float) -> np.ndarray:
    """Poses at query times: linear in position, slerp in rotation; NaN beyond ``tolerance`` outside."""
    out = np.full((len(query), 4, 4), np.nan)
    for k, t in enumerate(query):
        j = int(np.searchsorted(times, t))
        if j < len(times) and abs(times[j] - t) < 1e-9:
            out[k] = poses[j]
        elif 0 < j < len(times):
            a = (t - times[j - 1]) / (times[j] - times[j - 1])
            out[k] = _blend(poses[j - 1], poses[j], a)
        elif j == 0 and times[0] - t <= tolerance:
            out[k] = poses[0]
        elif j == len(times) and t - times[-1] <= tolerance:
            out[k] = poses[-1]
    return out


def _blend(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    q0, q1 = rotmat_to_quat(T0[:3, :3]), rotmat_to_quat(T1[:3, :3])
    if np.dot(q0, q1) < 0:
        q1 = -q1
    dot = np.clip(np.dot(q0, q1), -1.0, 1.0)
    theta = np.arccos(dot)
    if theta < 1e-8:
        q = q0
    else:
        q = (np.sin((1 - a) * theta) * q0 + np.sin(a * theta) * q1) / np.sin(theta)
    return pose_from_rt(quat_to_rotmat(q), (1 - a) * T0[:3, 3] + a * T1[:3, 3])
