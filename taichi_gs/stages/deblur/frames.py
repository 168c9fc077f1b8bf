"""Stage 3's frames: stage 2's outputs read back, the training / held-out split, the frames at training
resolution (and, coarse-to-fine, at coarser ones), and the frame trained at each iteration."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ...errors import InputError
from ...geometry import median_depths
from ...io.ply import read_splats
from ...io.sequence import SOURCED, Sequence
from ...io.trajectory import check_frame_times, read_tum
from ...noreference import laplacian_variance, sharpest_holdout
from ...rolling_shutter import DeskewedSequence, readout_skews
from ...splats import Splats
from ..schedule import downsample_depth, scaled_intrinsics
from .config import DeblurConfig
from .model import BlurScene


def split_frames(n_frames: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """(train, test) frame indices: frames 1, 1 + h, 1 + 2h, ... are test views (none if h is 0)."""
    test = list(range(1, n_frames, holdout_every)) if holdout_every > 0 else []
    held_out = set(test)
    train = [i for i in range(n_frames) if i not in held_out]
    if not train:
        raise InputError(None, f"no training frames left with holdout_every={holdout_every}",
                         "use --holdout none or a larger value")
    return train, test


def training_frame(train: list[int], iteration: int, rng: np.random.Generator, seed: int, epochs: bool) -> int:
    """The frame trained at ``iteration``: uniform at random, or (``epochs``) every training view once
    per epoch of len(train) iterations, in an order that depends only on ``seed`` and the epoch."""
    if not epochs:
        return train[int(rng.integers(len(train)))]
    epoch, place = divmod(iteration, len(train))
    return train[int(np.random.default_rng([seed, epoch]).permutation(len(train))[place])]


def choose_split(colors: list[np.ndarray], holdout: str, holdout_every: int) -> tuple[list[int], list[int], list[float]]:
    """(train, test, sharpness): ``holdout`` "every" takes :func:`split_frames`; "sharpest" holds out
    the sharpest frame (``noreference.laplacian_variance``) of each window of ``holdout_every`` frames
    that lies between two training frames (:func:`noreference.sharpest_holdout`)."""
    sharpness = [laplacian_variance(c) for c in colors]
    if holdout == "every":
        return (*split_frames(len(colors), holdout_every), sharpness)
    if holdout != "sharpest":
        raise InputError(None, f"unknown holdout mode {holdout!r}", 'set [deblur] holdout to "every" or "sharpest"')
    if holdout_every == 1 or len(colors) < 2:
        raise InputError(None, f"cannot hold out the sharpest of every {holdout_every} of {len(colors)} frames",
                         "use holdout_every >= 2 (or 0) and at least 2 frames")
    return (*sharpest_holdout(sharpness, holdout_every), sharpness)


def load_stage2(out_dir: Path, frame_times: np.ndarray) -> tuple[np.ndarray, Splats]:
    """Stage-2 poses (N, 4, 4) and splats from OUT/refine/, made for the frames stamped ``frame_times``."""
    poses_path, splats_path = out_dir / "refine" / "trajectory.txt", out_dir / "refine" / "splats.ply"
    for path in (poses_path, splats_path):
        if not path.is_file():
            raise InputError(path, "stage-2 output missing", "run 'taichi-gs refine' first")
    timestamps, poses = read_tum(poses_path)
    check_frame_times(poses_path, timestamps, frame_times, "rerun stage 2 on this sequence")
    splats = read_splats(splats_path)
    if len(splats) == 0:
        raise InputError(splats_path, "no Gaussians", "rerun stage 2")
    return poses, splats


def with_sh_degree(splats: Splats, degree: int) -> Splats:
    """The splats with SH bands up to ``degree`` (higher bands added as zeros or dropped)."""
    m = (degree + 1) ** 2
    sh = np.zeros((len(splats), m, 3), np.float32)
    keep = min(m, splats.sh.shape[1])
    sh[:, :keep] = splats.sh[:, :keep]
    return dataclasses.replace(splats, sh=sh)


def _downsample_color(color: np.ndarray, scale: int) -> np.ndarray:
    """Area average over scale x scale blocks (pixel i covers inputs scale*i .. scale*i + scale - 1)."""
    if scale == 1:
        return color
    h, w = color.shape[0] // scale, color.shape[1] // scale
    return cv2.resize(color[: h * scale, : w * scale], (w, h), interpolation=cv2.INTER_AREA)


def _area_intrinsics(K: np.ndarray, scale: int) -> np.ndarray:
    """Intrinsics of the block-averaged image (block centre at scale*i + (scale - 1)/2)."""
    K = scaled_intrinsics(K, scale)
    K[0, 2] += (scale // 2 - (scale - 1) / 2) / scale
    K[1, 2] += (scale // 2 - (scale - 1) / 2) / scale
    return K


@dataclass
class _Frames:
    """The sequence at training resolution."""

    colors: list[np.ndarray]
    depths: list[np.ndarray]
    median_depth: np.ndarray
    K: np.ndarray
    sourced: np.ndarray | None = None  # H x W bool: pixels the losses use (None: all)


def _load_frames(sequence: Sequence, scale: int, sourced: np.ndarray | None,
                 depth_source: Sequence | DeskewedSequence | None = None) -> _Frames:
    """The frames at 1/``scale`` resolution, depth read from ``depth_source`` (None: ``sequence``); ``sourced``
    (full resolution, or None) is shrunk alike, a pixel kept only if its whole block is sourced."""
    colors = [_downsample_color(sequence.color(i), scale) for i in range(len(sequence))]
    h, w = colors[0].shape[:2]
    depth_source = sequence if depth_source is None else depth_source
    depths = [downsample_depth(depth_source.depth(i), scale)[:h, :w] for i in range(len(sequence))]
    if sourced is not None:
        sourced = _downsample_color(sourced.astype(np.float32), scale) >= SOURCED
    return _Frames(colors, depths, median_depths(depths), _area_intrinsics(sequence.K(), scale), sourced)


def loss_mask(sequence: Sequence, config: DeblurConfig) -> np.ndarray | None:
    """Full-resolution pixels stage 3's photometric losses use: ``Sequence.sourced_pixels`` with
    ``sourced_pixels_only``, else None (all)."""
    if not config.sourced_pixels_only:
        return None
    sourced = sequence.sourced_pixels()
    return None if sourced.all() else sourced


def _scene_extent(poses: np.ndarray, means: np.ndarray) -> float:
    """Radius of the scene: the 90th percentile distance of the Gaussians from the cameras' centroid."""
    centre = poses[:, :3, 3].mean(axis=0)
    return float(max(np.percentile(np.linalg.norm(means - centre, axis=1), 90), 1e-3))


def _phase(sequence: Sequence, sourced: np.ndarray | None, model: BlurScene, cache: dict[int, _Frames],
           scale: int, depth_source: Sequence | DeskewedSequence | None = None) -> tuple[_Frames, BlurScene]:
    """[ours] Coarse-to-fine: the frames at resolution divisor ``scale`` (loaded once, their depth as
    :func:`_load_frames` reads it) and ``model`` moved to that resolution (the same Gaussians, Adam moments and
    densification statistics)."""
    if scale not in cache:
        cache[scale] = _load_frames(sequence, scale, sourced, depth_source)
    frames = cache[scale]
    height, width = frames.colors[0].shape[:2]
    if (model.width, model.height) != (width, height):
        moved = BlurScene(model.splats(), frames.K, width, height, sourced=frames.sourced,
                          warp_margin=model.warp_margin)
        moved.load_state(model.state())
        model = moved
    return frames, model


@dataclass(frozen=True)
class _Shutter:
    """[ours] Each frame's rolling-shutter readout motion (N, 6; zeros: a global shutter) and its median sensor
    depth (N,): where the skew is measured, and where a re-blurred render's rows are warped from a surface-less
    pixel; a skew is taken as at most ``max_skew_px``."""

    motions: np.ndarray
    median_depth: np.ndarray
    max_skew_px: float

    def skew_px(self, focal: float) -> float:
        """The most any frame's first or last row lies from its pose on the image (:func:`readout_px`, pixels at
        focal ``focal``), at most ``max_skew_px``: a pose jump between neighbours must not blow up the anchors'
        margin."""
        skew = float(readout_skews(self.motions, focal, self.median_depth).max())
        return min(skew, self.max_skew_px)
