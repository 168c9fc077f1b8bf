"""Optical flow between colour frames: OpenCV DIS by default, or precomputed files from any network.

A flow is a float32 H x W x 2 array; ``flow[v, u] = (du, dv)`` moves pixel (u, v) of the first
frame to (u + du, v + dv) in the second, in OpenCV's pixel convention.

Precomputed flows (``--flow-dir``): one file per pair k (frame k -> k+1), either Middlebury
``.flo`` or NumPy ``.npy`` (H x W x 2), named by the pair index (``000007.flo``) or by the colour
file stem of frame k (``frame_0007.npy``). Optional backward flows (frame k+1 -> k) carry the suffix
``_backward`` (``000007_backward.flo``); without them the forward-backward check is skipped.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from . import profiling
from .errors import InputError
from .geometry import backproject, project, transform
from .io.atomic import atomic_path

FLOW_SUFFIXES = (".flo", ".npy")
BACKWARD_SUFFIX = "_backward"
DIS_PRESETS = {
    "ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
    "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}


class FlowProvider(Protocol):
    """Source of dense flow between frames i and j of a sequence."""

    def flow(self, i: int, j: int) -> np.ndarray | None:
        """Flow from frame i to frame j (H x W x 2), or None if this provider has none for the pair."""


def to_gray_u8(color: np.ndarray) -> np.ndarray:
    """8-bit grey image of an RGB float image in [0, 1]."""
    gray = cv2.cvtColor(np.ascontiguousarray(color, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    return np.clip(np.round(gray * 255.0), 0, 255).astype(np.uint8)


@profiling.timed("optical flow (DIS)")
def dis_flow(gray_a: np.ndarray, gray_b: np.ndarray, preset: str = "medium", initial: np.ndarray | None = None,
             finest_width_px: int = 0) -> np.ndarray:
    """DIS optical flow (Kroeger et al. 2016) from 8-bit grey image a to b.

    ``initial`` (H x W x 2, finite) seeds the coarsest pyramid level instead of zero flow, so motions
    larger than DIS's coarse-to-fine search range can be followed when a guess of them is known.
    ``finest_width_px``: DIS's finest pyramid level is at least this wide, when the preset's own is
    narrower (see :func:`finest_scale`); 0 keeps the preset's.
    """
    if preset not in DIS_PRESETS:
        raise ValueError(f"unknown DIS preset {preset!r}; use one of {', '.join(DIS_PRESETS)}")
    dis = cv2.DISOpticalFlow_create(DIS_PRESETS[preset])
    dis.setFinestScale(finest_scale(dis.getFinestScale(), gray_a.shape[1], finest_width_px))
    seed = None if initial is None else np.array(initial, dtype=np.float32, order="C")
    return dis.calc(gray_a, gray_b, seed).astype(np.float32)


def finest_scale(preset_scale: int, width: int, finest_width_px: int) -> int:
    """DIS's finest pyramid level (0: full resolution, s: 2^-s of it): the preset's, or a finer one so that the
    level is at least ``finest_width_px`` wide (0: the preset's). [ours] The medium preset stops at half
    resolution; on 320 px wide blurred frames its flow fits the camera's translation about 3.5% short (a 60-frame
    synthetic translation and 7-Scenes at every 3rd frame, x0.5), at full resolution 2% and 0%
    (docs/notebook/benchmarks-2026-11.md, "DIS at full resolution below 640 px")."""
    if finest_width_px <= 0:
        return preset_scale
    finest = 0
    while width / 2 ** (finest + 1) >= finest_width_px:
        finest += 1
    return min(preset_scale, finest)


def rigid_flow(depth: np.ndarray, K: np.ndarray, T: np.ndarray, fill_holes: bool = False) -> np.ndarray:
    """Flow that the camera motion T (camera a -> camera b) induces on the pixels of a depth map of a.

    Pixels without depth are NaN, or with ``fill_holes`` moved as if at the median valid depth (a
    finite seed for :func:`dis_flow`; zero flow where no depth is valid at all).
    """
    valid = depth > 0
    if fill_holes:
        if not valid.any():
            return np.zeros((*depth.shape, 2), np.float32)
        depth = np.where(valid, depth, np.median(depth[valid]))
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):
        moved = project(transform(T, backproject(depth, K)), K)
    flow = np.stack([moved[..., 0] - u, moved[..., 1] - v], axis=-1)
    if fill_holes:
        return np.nan_to_num(flow, nan=0.0, posinf=0.0, neginf=0.0).astype(np.float32)
    flow[~valid] = np.nan
    return flow.astype(np.float32)


class DISFlow:
    """FlowProvider computing DIS flow on 8-bit grey frames, ``gray(i)`` for frame i (the caller caches them;
    stage 1's frame cache does, for every thread)."""

    def __init__(self, gray: Callable[[int], np.ndarray], preset: str = "medium", finest_width_px: int = 0):
        self.gray = gray
        self.preset = preset
        self.finest_width_px = finest_width_px

    def flow(self, i: int, j: int) -> np.ndarray:
        return dis_flow(self.gray(i), self.gray(j), self.preset, finest_width_px=self.finest_width_px)


class FileFlow:
    """FlowProvider reading one precomputed flow file per consecutive pair from a folder."""

    def __init__(self, folder: str | Path, names: list[str]):
        self.folder = Path(folder)
        self.names = names
        if not self.folder.is_dir():
            raise InputError(self.folder, "flow folder not found", "give --flow-dir an existing folder of .flo or .npy files")

    def check(self) -> None:
        """Fail now, naming the first missing file, rather than mid-stage."""
        for k in range(len(self.names) - 1):
            if self._find(k, backward=False) is None:
                raise InputError(self.folder, f"no flow file for pair {k} ({self.names[k]} -> {self.names[k + 1]})",
                                 f"write {k:06d}.flo, {k:06d}.npy, {self.names[k]}.flo or {self.names[k]}.npy")

    def flow(self, i: int, j: int) -> np.ndarray | None:
        if abs(i - j) != 1:
            return None
        path = self._find(min(i, j), backward=j < i)
        return None if path is None else read_flow(path)

    def _find(self, k: int, backward: bool) -> Path | None:
        tag = BACKWARD_SUFFIX if backward else ""
        for stem in (f"{k:06d}", self.names[k]):
            for suffix in FLOW_SUFFIXES:
                path = self.folder / f"{stem}{tag}{suffix}"
                if path.is_file():
                    return path
        return None


def read_flow(path: str | Path) -> np.ndarray:
    """Flow from a Middlebury ``.flo`` or a ``.npy`` (H x W x 2) file, as float32."""
    path = Path(path)
    if path.suffix == ".flo":
        return read_flo(path)
    if path.suffix == ".npy":
        flow = np.load(path, allow_pickle=False)
        if flow.ndim != 3 or flow.shape[2] != 2:
            raise InputError(path, f"flow array has shape {flow.shape}", "save an H x W x 2 array of (du, dv)")
        return flow.astype(np.float32)
    raise InputError(path, f"unknown flow file type {path.suffix!r}", "use .flo or .npy")


def write_flow(path: str | Path, flow: np.ndarray) -> None:
    """Write a flow as ``.flo`` or ``.npy`` (chosen by the suffix), atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        if path.suffix == ".flo":
            if not cv2.writeOpticalFlow(str(tmp), np.ascontiguousarray(flow, dtype=np.float32)):
                raise OSError(f"could not write {path}")
        elif path.suffix == ".npy":
            with open(tmp, "wb") as f:
                np.save(f, flow.astype(np.float32))
        else:
            raise ValueError(f"unknown flow file type {path.suffix!r}; use .flo or .npy")


def read_flo(path: Path) -> np.ndarray:
    """Middlebury ``.flo`` (float32 tag 202021.25, int32 width, int32 height, then u, v interleaved)."""
    flow = cv2.readOpticalFlow(str(path))
    if flow is None or flow.size == 0:
        raise InputError(path, "not a readable Middlebury .flo file (bad tag, or truncated)",
                         "write flows with a standard .flo writer (cv2.writeOpticalFlow) or as .npy")
    return flow.astype(np.float32)


def warp_by_flow(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """Sample ``image`` at p + flow(p) bilinearly; NaN outside the image."""
    h, w = flow.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    map_u, map_v = u + flow[..., 0], v + flow[..., 1]
    return cv2.remap(image.astype(np.float32), map_u, map_v, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))


def finite_flow(flow: np.ndarray) -> np.ndarray:
    """Pixels where both components of an H x W x 2 flow are finite."""
    return np.isfinite(flow[..., 0]) & np.isfinite(flow[..., 1])


def forward_backward_mask(forward: np.ndarray, backward: np.ndarray, alpha: float = 0.01, beta: float = 0.5) -> np.ndarray:
    """Pixels whose forward flow is undone by the backward flow (Sundaram et al. 2010).

    Consistent where |f + b(p + f)|^2 < alpha (|f|^2 + |b(p + f)|^2) + beta and p + f lies inside.
    """
    back = warp_by_flow(backward, forward)
    # the components written out (here and in finite_flow): numpy's reductions over a last axis of length 2
    # are slow on whole frames
    (fu, fv), (bu, bv) = np.moveaxis(forward, -1, 0), np.moveaxis(back, -1, 0)
    round_trip = (fu + bu) ** 2 + (fv + bv) ** 2
    bound = alpha * ((fu**2 + fv**2) + (bu**2 + bv**2)) + beta
    with np.errstate(invalid="ignore"):
        return np.isfinite(round_trip) & (round_trip < bound)
