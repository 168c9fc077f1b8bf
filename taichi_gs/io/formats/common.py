"""What the readers share: read options, frame lists, intrinsics (intrinsics.json, the flags, per-format
defaults), ground truth matched to the frames, numbered files."""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import Intrinsics, IntrinsicsOverride, read_image
from ..trajectory import interpolate_poses, read_tum_rows, tum_rows_to_poses

NOMINAL_FPS = 30.0  # frame rate assumed by layouts without timestamps (7-Scenes, ScanNet, Replica)
MAX_TIME_DIFFERENCE = 0.02  # seconds, TUM associate.py's default


@dataclass(frozen=True)
class ReadOptions:
    """Reader inputs beyond the folder: command-line intrinsics, a named camera (TUM: fr1/fr2/fr3),
    TUM's colour/depth association tolerance and depth latency (seconds; None: the named camera's)."""

    override: IntrinsicsOverride = field(default_factory=IntrinsicsOverride)
    camera: str | None = None
    max_time_difference: float = MAX_TIME_DIFFERENCE
    depth_latency: float | None = None


def read_text(path: Path) -> str:
    """A list file's text (UTF-8), or a one-line error."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise InputError(path, f"not UTF-8 text (byte {err.start})", "save the list as plain UTF-8 text") from None
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror})", "check the file's permissions") from None


def read_list(path: Path, columns: int, optional: int = 0) -> list[list[str]]:
    """The rows of a frame list ("timestamp file ..." per line; blank lines and # comments skipped), each cut to
    ``columns`` fields and up to ``optional`` more; an error naming the line when one is short or its timestamp
    is not a number."""
    rows = []
    for n, line in enumerate(read_text(path).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < columns:
            raise InputError(path, f"line {n} has {len(parts)} fields, expected {columns}",
                             "write 'timestamp file' per line (frames.txt: 'timestamp rgb depth')")
        try:
            stamp = float(parts[0])
        except ValueError:
            raise InputError(path, f"line {n}: timestamp {parts[0]!r} is not a number", "fix the timestamp") from None
        if not math.isfinite(stamp):
            raise InputError(path, f"line {n}: timestamp is NaN or inf", "fix the timestamp")
        rows.append(parts[:columns + optional])
    if not rows:
        raise InputError(path, "lists no frames", "add one line per frame")
    return rows


def check_increasing(path: Path, timestamps: np.ndarray) -> None:
    """An error naming the list ``path`` where its ``timestamps`` do not increase."""
    bad = np.flatnonzero(np.diff(timestamps) <= 0)
    if bad.size:
        k = int(bad[0])
        raise InputError(path, f"timestamps not increasing at entry {k + 2} ({timestamps[k]:.6f} then {timestamps[k + 1]:.6f})",
                         "sort the list by time and remove duplicate frames")


def listed_file(root: Path, name: str, list_path: Path) -> Path:
    """ROOT/``name``, a file the list ``list_path`` names; an error when it is missing."""
    path = root / name
    if not path.is_file():
        raise InputError(path, f"listed in {list_path.name} but missing",
                         f"restore the frame or remove its line from {list_path.name}")
    return path


def resolve_intrinsics(root: Path, override: IntrinsicsOverride, first_rgb: Path) -> Intrinsics:
    """Intrinsics from the flags (``override``) over ROOT/intrinsics.json; width and height (and their check) from
    the first colour frame, depth_scale 5000 unless given."""
    json_path = root / "intrinsics.json"
    values: dict[str, float] = {}
    if json_path.is_file():
        try:
            values = json.loads(read_text(json_path))
        except json.JSONDecodeError as err:
            raise InputError(json_path, f"not valid JSON ({err.msg} at line {err.lineno})", "fix the JSON syntax") from None
        if not isinstance(values, dict):
            raise InputError(json_path, "must hold a JSON object", 'write {"width", "height", "fx", "fy", "cx", "cy", "depth_scale"}')
    values = {**values, **override.values()}
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise InputError(json_path, f"intrinsics {', '.join(missing)} not given",
                         "write intrinsics.json beside the data or pass --fx --fy --cx --cy")
    height, width = read_image(first_rgb).shape[:2]
    values.setdefault("width", width)
    values.setdefault("height", height)
    values.setdefault("depth_scale", 5000.0)
    try:
        intrinsics = Intrinsics(
            width=int(values["width"]), height=int(values["height"]),
            fx=float(values["fx"]), fy=float(values["fy"]), cx=float(values["cx"]), cy=float(values["cy"]),
            depth_scale=float(values["depth_scale"]),
        )
    except (TypeError, ValueError) as err:
        raise InputError(json_path, f"intrinsics are not numbers ({err})", "write plain numbers") from None
    numbers = [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.depth_scale]
    if not all(math.isfinite(v) for v in numbers) or min(intrinsics.fx, intrinsics.fy, intrinsics.depth_scale) <= 0:
        raise InputError(json_path, "fx, fy and depth_scale must be finite and positive, cx and cy finite",
                         "fix intrinsics.json or the --fx/--fy/--cx/--cy/--depth-scale flags")
    if (intrinsics.width, intrinsics.height) != (width, height):
        raise InputError(first_rgb, f"image is {width}x{height} but intrinsics say {intrinsics.width}x{intrinsics.height}",
                         "fix width/height in intrinsics.json")
    return intrinsics


def intrinsics_with_defaults(root: Path, override: IntrinsicsOverride, first_rgb: Path,
                             defaults: dict[str, float]) -> Intrinsics:
    """Intrinsics from, by priority: the flags, ROOT/intrinsics.json, then the format's ``defaults``."""
    in_json = json_keys(root / "intrinsics.json")
    fallback = {k: v for k, v in defaults.items() if k not in in_json}
    return resolve_intrinsics(root, IntrinsicsOverride(**{**fallback, **override.values()}), first_rgb)


def check_published_size(first_rgb: Path, intrinsics: Intrinsics, camera: str, size: tuple[int, int], fix: str) -> None:
    """Refuse frames of another size than ``size`` (width, height), the one the published ``camera`` is for: its
    numbers would be read as this size's camera."""
    width, height = intrinsics.width, intrinsics.height
    if (width, height) != size:
        raise InputError(first_rgb, f"frames are {width}x{height}, but {camera} is published for {size[0]}x{size[1]} "
                         "frames", fix)


def json_keys(path: Path) -> set[str]:
    """The keys an intrinsics.json sets (empty if absent or unreadable: the full read reports that)."""
    if not path.is_file():
        return set()
    try:
        values = json.loads(path.read_text())
    except (ValueError, OSError):
        return set()  # resolve_intrinsics reports the problem
    return set(values) if isinstance(values, dict) else set()


def ground_truth(path: Path, timestamps: np.ndarray) -> np.ndarray | None:
    """Ground-truth poses of a TUM trajectory file interpolated to the frame times (NaN where not covered); None
    without the file."""
    if not path.is_file():
        return None
    rows = read_tum_rows(path)
    order = np.argsort(rows[:, 0])
    rows = rows[order]
    return interpolate_poses(rows[:, 0], tum_rows_to_poses(rows), timestamps, MAX_TIME_DIFFERENCE)


def numbered(folder: Path, pattern: str) -> dict[int, Path]:
    """Files of ``folder`` whose name matches ``pattern`` (a regex with one integer group), by number."""
    regex = re.compile(pattern)
    found: dict[int, Path] = {}
    if folder.is_dir():
        for path in folder.iterdir():
            match = regex.fullmatch(path.name)
            if match:
                found[int(match.group(1))] = path
    return dict(sorted(found.items()))


def read_matrix(path: Path, shape: tuple[int, int], what: str, fix: str) -> np.ndarray:
    """A whitespace- or comma-separated matrix of the given shape."""
    try:
        values = np.array(path.read_text().replace(",", " ").split(), dtype=float)
    except (OSError, ValueError, UnicodeDecodeError):
        raise InputError(path, f"{what} is unreadable or not numbers", fix) from None
    if values.size != shape[0] * shape[1]:
        raise InputError(path, f"{what} has {values.size} numbers, expected {shape[0]}x{shape[1]}", fix)
    return values.reshape(shape)


def pose_files(paths: list[Path], fix: str) -> np.ndarray | None:
    """Camera-to-world 4x4 poses from one text file per frame: None when no frame has one; an error
    naming the first missing file when only some do; rows of -inf or NaN (ScanNet) give NaN."""
    present = [p for p in paths if p.is_file()]
    if not present:
        return None
    if len(present) < len(paths):
        missing = next(p for p in paths if not p.is_file())
        raise InputError(missing, f"pose file missing ({len(paths) - len(present)} of {len(paths)} frames have none)", fix)
    return rigid(np.stack([read_matrix(p, (4, 4), "pose", fix) for p in present]))


def rigid(poses: np.ndarray) -> np.ndarray:
    """4x4 poses with each rotation block replaced by the nearest rotation (datasets store rounded,
    slightly non-orthonormal matrices: 7-Scenes' determinants are off by ~1e-4, which alone reads as
    ~1 degree of rotation error); poses with a non-finite entry become all NaN."""
    poses = np.array(poses, dtype=float)
    finite = np.all(np.isfinite(poses.reshape(len(poses), -1)), axis=1)
    poses[~finite] = np.nan
    if finite.any():
        U, _, Vt = np.linalg.svd(poses[finite, :3, :3])
        flip = np.where(np.linalg.det(U @ Vt) < 0, -1.0, 1.0)
        U[:, :, 2] *= flip[:, None]
        rotations = U @ Vt
        block = poses[finite]
        block[:, :3, :3] = rotations
        block[:, 3] = [0.0, 0.0, 0.0, 1.0]
        poses[finite] = block
    return poses
