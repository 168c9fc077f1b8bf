"""An RGB-D sequence read lazily, frame by frame, whatever layout it came from (the readers that make one are
``io.formats``, and ``io.load.load_sequence`` opens a folder with them), and the colour and depth image readers.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from .. import profiling
from ..errors import InputError
from ..geometry import intrinsics_matrix
from . import jsonout
from .readout import READOUT_KEY
from .transforms import FrameTransform


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (OpenCV pixel convention) and the depth PNG scale (units per metre)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 5000.0

    def K(self) -> np.ndarray:
        """3x3 intrinsics matrix."""
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    def to_json(self, readout_ms: float = 0.0) -> str:
        """intrinsics.json's text; a rolling shutter's ``readout_ms`` (above 0) as :data:`READOUT_KEY`."""
        values = {**asdict(self), READOUT_KEY: readout_ms} if readout_ms > 0 else asdict(self)
        return jsonout.dumps(values, indent=2) + "\n"


@dataclass(frozen=True)
class IntrinsicsOverride:
    """Values given on the command line; each one set wins over intrinsics.json."""

    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    depth_scale: float | None = None

    def values(self) -> dict[str, float]:
        return {k: v for k, v in asdict(self).items() if v is not None}


SOURCED = 0.999  # share of a pixel that must come from camera pixels for it to count as seen


class Sequence:
    """An RGB-D sequence whose frames are read on demand.

    Attributes: ``root``, ``layout`` (the reader's name, e.g. "tum" or "taichi-gs"), ``intrinsics``,
    ``timestamps`` (N,), ``rgb_paths``, ``depth_paths``, ``names`` (colour file stems), ``gt_poses`` (N x 4 x 4
    camera-to-world, NaN where ground truth does not cover a frame, or None), ``exposure_poses``
    (N x 2 x 4 x 4 start/end, or None), ``depth_timestamps`` (N,) the moment each depth frame shows, on the
    colour clock (None: with its colour frame; see :meth:`depth_offsets`), ``sharp_paths`` (or None),
    ``sourced_path`` (the own layout's ``sourced.png``, or None), ``transform`` (applied to each frame as it is
    read: resampling, undistortion, masking; see ``io.transforms``), ``source`` (how it was read: format, every,
    scale, camera) and ``load_options`` (the arguments of
    :func:`io.load.load_sequence`, recorded in a run's run.json so later commands reopen it the same way).
    """

    def __init__(
        self,
        root: Path,
        layout: str,
        intrinsics: Intrinsics,
        timestamps: np.ndarray,
        rgb_paths: list[Path],
        depth_paths: list[Path],
        gt_poses: np.ndarray | None = None,
        exposure_poses: np.ndarray | None = None,
        sharp_paths: list[Path] | None = None,
        names: list[str] | None = None,
        transform: FrameTransform | None = None,
        sourced_path: Path | None = None,
        depth_timestamps: np.ndarray | None = None,
    ):
        self.root = root
        self.layout = layout
        self.intrinsics = intrinsics
        self.timestamps = timestamps
        self.rgb_paths = rgb_paths
        self.depth_paths = depth_paths
        self.names = names if names is not None else [p.stem for p in rgb_paths]
        self.gt_poses = gt_poses
        self.exposure_poses = exposure_poses
        self.sharp_paths = sharp_paths
        self.transform = transform
        self.sourced_path = sourced_path
        self.depth_timestamps = depth_timestamps
        self.source: dict[str, object] = {"format": layout, "every": 1, "scale": 1.0}
        self.load_options: dict[str, Any] = {}

    def __len__(self) -> int:
        return len(self.rgb_paths)

    def K(self) -> np.ndarray:
        return self.intrinsics.K()

    def depth_offsets(self) -> np.ndarray:
        """(N,) seconds from each colour frame's timestamp to the moment its depth frame shows (0 where the
        reading pairs them in time, or does not say)."""
        if self.depth_timestamps is None:
            return np.zeros(len(self))
        return np.asarray(self.depth_timestamps, dtype=float) - np.asarray(self.timestamps, dtype=float)

    @profiling.timed("input frames (I/O)")
    def color(self, i: int) -> np.ndarray:
        """Blurred colour of frame i, float32 H x W x 3 in [0, 1]."""
        return self._checked_color(self.rgb_paths[i])

    def sharp(self, i: int) -> np.ndarray:
        """Sharp ground-truth colour of frame i (synthetic sequences only)."""
        if self.sharp_paths is None:
            raise InputError(self.root, "sequence has no sharp ground-truth images", "use a sequence made by 'taichi-gs synth'")
        return self._checked_color(self.sharp_paths[i])

    @profiling.timed("input frames (I/O)")
    def depth(self, i: int) -> np.ndarray:
        """Depth of frame i in metres, float32 H x W, 0 where invalid."""
        path = self.depth_paths[i]
        depth = read_depth(path, self.intrinsics.depth_scale)
        if self.transform is not None:
            depth = self.transform.depth(path, depth)
        self._check_size(path, depth.shape[:2], "depth")
        return depth

    def sourced_pixels(self) -> np.ndarray:
        """Boolean H x W: the colour pixels made wholly from camera pixels. False only where a transform
        had no source (e.g. the border of an undistorted frame, which OpenCV fills by replicating the
        edge), or where the own layout's ``sourced.png`` says so. [ours] eval's real-data figures count
        these pixels only, and so do stage 3's photometric losses with ``[deblur] sourced_pixels_only``."""
        h, w = self.intrinsics.height, self.intrinsics.width
        if not self.rgb_paths or (self.transform is None and self.sourced_path is None):
            return np.ones((h, w), bool)
        raw = read_color(self.rgb_paths[0]).shape[:2]
        share = np.ones(raw, np.float32) if self.sourced_path is None else self._stored_sourced(raw)
        if self.transform is not None:
            share = self.transform.sourced(share)
        self._check_size(self.rgb_paths[0], share.shape[:2], "colour")
        return share >= SOURCED

    def _stored_sourced(self, raw: tuple[int, int]) -> np.ndarray:
        """The own layout's ``sourced.png`` as a 0/1 float32 share on the frames' grid."""
        path = self.sourced_path
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if mask is None or mask.ndim != 2:
            raise InputError(path, "unreadable or not a single-channel mask",
                             "restore it (255 where a pixel came from the camera), or delete it to count every pixel")
        if mask.shape != raw:
            raise InputError(path, f"mask is {mask.shape[1]}x{mask.shape[0]}, the colour frames {raw[1]}x{raw[0]}",
                             "give a mask at the colour frames' size, or delete it to count every pixel")
        return (mask >= 128).astype(np.float32)

    def check_all(self) -> None:
        """Read every frame once, so corrupt files fail now rather than mid-stage."""
        for i in range(len(self)):
            self.color(i)
            self.depth(i)

    def _checked_color(self, path: Path) -> np.ndarray:
        color = read_color(path)
        if self.transform is not None:
            color = self.transform.color(path, color)
        self._check_size(path, color.shape[:2], "colour")
        return color

    def _check_size(self, path: Path, shape: tuple[int, int], what: str) -> None:
        h, w = shape
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise InputError(
                path,
                f"{what} image is {w}x{h} but the intrinsics say {self.intrinsics.width}x{self.intrinsics.height}",
                "give colour and depth at the same resolution as intrinsics.json (align depth to colour first)",
            )


def read_color(path: Path) -> np.ndarray:
    """Colour image as float32 H x W x 3 RGB in [0, 1] (8- or 16-bit, grey, RGB or RGBA)."""
    image = read_image(path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(image.dtype)
    if scale is None:
        raise InputError(path, f"colour image has unsupported type {image.dtype}", "save colour as 8- or 16-bit PNG or JPEG")
    return image.astype(np.float32) / np.float32(scale)


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """Depth in metres from a 16-bit PNG (value / depth_scale), or a float ``.npy`` or 32-bit float
    TIFF in metres (NaN or inf in a float TIFF count as invalid, 0)."""
    if path.suffix == ".npy":
        depth = _load_npy(path)
    else:
        raw = read_image(path)
        if raw.ndim == 2 and raw.dtype in (np.float32, np.float64):
            depth = np.nan_to_num(raw.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        elif raw.dtype != np.uint16 or raw.ndim != 2:
            kind = f"{raw.dtype}, {raw.shape[2] if raw.ndim == 3 else 1} channel(s)"
            raise InputError(path, f"depth must be a 16-bit single-channel PNG, got {kind}",
                             "save depth as uint16 PNG (value = metres x depth_scale)")
        else:
            depth = raw.astype(np.float32) / np.float32(depth_scale)
    if not np.all(np.isfinite(depth)):
        raise InputError(path, "depth contains NaN or inf", "write 0 for invalid depth")
    if np.any(depth < 0):
        raise InputError(path, "depth contains negative values", "write 0 for invalid depth")
    return depth


def _load_npy(path: Path) -> np.ndarray:
    try:
        depth = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise InputError(path, f"cannot read depth array ({err})", "write depth as a float32 .npy in metres") from None
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise InputError(path, f"depth array has shape {depth.shape} and type {depth.dtype}",
                         "write an H x W float array in metres")
    return depth.astype(np.float32)


def read_image(path: Path) -> np.ndarray:
    """An image file as stored (OpenCV's channels and type); a one-line error when missing or unreadable."""
    if not path.is_file():
        raise InputError(path, "image file not found", "restore the file or remove its line from the frame list")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputError(path, "image is unreadable or corrupt", "re-export the image as PNG or JPEG")
    return image
