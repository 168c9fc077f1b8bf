"""What the readers share: read options, intrinsics with per-format defaults, numbered files."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import Intrinsics, IntrinsicsOverride, _resolve_intrinsics

NOMINAL_FPS = 30.0  # frame rate assumed by layouts without timestamps (7-Scenes, ScanNet, Replica)


@dataclass(frozen=True)
class ReadOptions:
    """Reader inputs beyond the folder: command-line intrinsics, a named camera (TUM: fr1/fr2/fr3),
    TUM's colour/depth association tolerance and depth latency (seconds; None: the named camera's)."""

    override: IntrinsicsOverride = field(default_factory=IntrinsicsOverride)
    camera: str | None = None
    max_time_difference: float = 0.02
    depth_latency: float | None = None


def intrinsics_with_defaults(root: Path, override: IntrinsicsOverride, first_rgb: Path,
                             defaults: dict[str, float]) -> Intrinsics:
    """Intrinsics from, by priority: the flags, ROOT/intrinsics.json, then the format's ``defaults``."""
    in_json = json_keys(root / "intrinsics.json")
    fallback = {k: v for k, v in defaults.items() if k not in in_json}
    return _resolve_intrinsics(root, IntrinsicsOverride(**{**fallback, **override.values()}), first_rgb)


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
        return set()  # _resolve_intrinsics reports the problem
    return set(values) if isinstance(values, dict) else set()


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
