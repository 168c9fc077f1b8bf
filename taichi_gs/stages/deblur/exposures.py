"""Stage 3's exposures: every frame's start and end offsets (se(3) twists in its own frame) from its stage-2
pose, the values they start from, each frame's affine colour transform, and the per-frame Adam of both."""

from __future__ import annotations

import numpy as np

from ...geometry import invert, se3_log, virtual_pose
from ...photometric import IDENTITY, identity_penalty
from ..row_adam import RowAdam
from .config import DeblurConfig


def velocity_twists(poses: np.ndarray, timestamps: np.ndarray | None = None) -> np.ndarray:
    """(N, 6) each frame's velocity twist: the mean of the motions to its neighbours, in its own frame, per frame
    (``timestamps`` None) or per second."""
    n = len(poses)
    velocities = np.zeros((n, 6))
    for i in range(n):
        steps = []
        for j, sign in ((i + 1, 1.0), (i - 1, -1.0)):
            if 0 <= j < n:
                per = 1.0 if timestamps is None else max(sign * (timestamps[j] - timestamps[i]), 1e-9)
                steps.append(sign * se3_log(invert(poses[i]) @ poses[j]) / per)
        velocities[i] = np.mean(steps, axis=0) if steps else 0.0
    return velocities


def initial_offsets(poses: np.ndarray, fraction: float) -> np.ndarray:
    """(N, 2, 6) start/end offsets: -+ half of ``fraction`` of each frame's velocity twist per frame
    (:func:`velocity_twists`), so every exposure starts open."""
    velocity = velocity_twists(poses)
    return np.stack([-0.5 * fraction * velocity, 0.5 * fraction * velocity], axis=1)


def exposure_px(d_start: np.ndarray, d_end: np.ndarray, focal: float, depth: float) -> float:
    """Approximate image travel (pixels) over an exposure for points at ``depth``."""
    delta = np.asarray(d_end) - np.asarray(d_start)
    return float(focal * (np.linalg.norm(delta[:3]) / depth + np.linalg.norm(delta[3:])))


def capped_bend(bend: np.ndarray, d: np.ndarray, share: float, focal: float, depth: float) -> np.ndarray:
    """[ours] ``bend`` (:func:`geometry.exposure_twist`) scaled down, where it moves the image (:func:`exposure_px`
    at ``focal`` and ``depth``) more than ``share`` of the travel of the exposure ``d`` (start, end) does: a
    path's bow stays small against its length."""
    size, limit = exposure_px(np.zeros(6), bend, focal, depth), share * exposure_px(d[0], d[1], focal, depth)
    return bend * (limit / size) if size > limit else bend


def keep_open(d: np.ndarray, fallback: np.ndarray, min_px: float, focal: float, depth: float) -> np.ndarray:
    """Re-open an exposure that closed below ``min_px`` on the image: stretch d_e - d_s about its
    middle (or, if it vanished, take ``fallback``'s direction) to ``min_px``."""
    span = exposure_px(d[0], d[1], focal, depth)
    if span >= min_px:
        return d
    middle = 0.5 * (d[0] + d[1])
    half = 0.5 * (d[1] - d[0]) if span > 1e-3 * min_px else 0.5 * (fallback[1] - fallback[0])
    scale = min_px / max(exposure_px(-half, half, focal, depth), 1e-12)
    return np.stack([middle - scale * half, middle + scale * half])


def shrink_mid(d: np.ndarray, decay: float) -> np.ndarray:
    """Exposure offsets (start, end) whose mid offset (their mean) shrank by the share ``decay``, span unchanged."""
    return d - decay * d.mean(axis=0) if decay > 0 else d


def neighbours_mid_shift(offsets: np.ndarray, train: list[int], frame: int) -> np.ndarray:
    """[ours] The mean mid-exposure correction, (d_s + d_e) / 2, of the nearest training frame before and
    after ``frame`` (those there are; zeros without any): where a held-out frame's fit starts its exposure
    (each correction is in its own frame's coordinates, taken as the held-out frame's: neighbours turn little)."""
    before = [j for j in train if j < frame]
    after = [j for j in train if j > frame]
    nearest = ([max(before)] if before else []) + ([min(after)] if after else [])
    if not nearest:
        return np.zeros(6)
    return np.mean([0.5 * (offsets[j, 0] + offsets[j, 1]) for j in nearest], axis=0)


class DepthMoments:
    """[ours] When each frame's depth was taken, as a pose: the frames' ``velocities`` (N, 6; twists per second,
    :func:`velocity_twists`) and their depth frames' time ``offsets`` (N,; seconds from the colour's timestamp,
    ``Sequence.depth_offsets``)."""

    def __init__(self, velocities: np.ndarray, offsets: np.ndarray):
        self.velocities, self.offsets = velocities, offsets

    def shift(self, frame: int) -> np.ndarray:
        """The twist (6,) from ``frame``'s mid-exposure pose to the pose its depth shows: its velocity times its depth
        offset (zero for depth taken with the colour)."""
        return float(self.offsets[frame]) * self.velocities[frame]


def colour_step(adam: RowAdam, M: np.ndarray, grad: np.ndarray, frame: int, config: DeblurConfig) -> np.ndarray:
    """One Adam step of a frame's affine colour transform on its loss gradient plus the identity pull."""
    _, pull = identity_penalty(M, config.lambda_colour_affine)
    return adam.step(frame, M, grad + pull, config.lr_colour_affine)


class Exposures:
    """Every frame's exposure offsets (N, 2, 6) from its pose in ``poses``, starting at ``start``
    (:func:`initial_offsets`), and its colour transform (N, 3, 4; identity unless ``colour_affine``
    trains it), each with a per-frame Adam; [ours] ``bends`` (N, 6; :func:`geometry.exposure_twist`), zero but
    where a held-out fit bowed its exposure (``test_fit_bend``)."""

    def __init__(self, poses: np.ndarray, config: DeblurConfig):
        self.poses = poses
        self.config = config
        self.start = initial_offsets(poses, config.initial_exposure_fraction)
        self.offsets = self.start.copy()
        self.colours = np.repeat(IDENTITY[None], len(poses), axis=0)
        self.bends = np.zeros((len(poses), 6))
        self._exposure_adam = RowAdam(len(poses), (2, 6))
        self._colour_adam = RowAdam(len(poses), (3, 4))

    def colour(self, frame: int) -> np.ndarray | None:
        """``frame``'s colour transform with ``colour_affine``, else None (no transform)."""
        return self.colours[frame] if self.config.colour_affine else None

    def trained_colours(self) -> np.ndarray | None:
        """Every frame's colour transform with ``colour_affine``, else None."""
        return self.colours if self.config.colour_affine else None

    def update(self, frame: int, grad_start: np.ndarray, grad_end: np.ndarray, grad_colour: np.ndarray | None,
               lr: float, focal: float, depth: float) -> None:
        """One Adam step of ``frame``'s exposure at rate ``lr`` (its mid-exposure offset then shrunk by
        ``mid_exposure_decay``, and re-opened to ``min_open_px`` at ``focal`` and the frame's median
        ``depth``), and with ``colour_affine`` one of its colour transform."""
        updated = self._exposure_adam.step(frame, self.offsets[frame], np.stack([grad_start, grad_end]), lr)
        updated = shrink_mid(updated, self.config.mid_exposure_decay)
        self.offsets[frame] = keep_open(updated, self.start[frame], self.config.min_open_px, focal, depth)
        if self.config.colour_affine:
            self.colours[frame] = colour_step(self._colour_adam, self.colours[frame], grad_colour, frame, self.config)

    def start_from_neighbours(self, frame: int, train: list[int]) -> None:
        """[ours] Move held-out ``frame``'s exposure by its training neighbours' mean mid-exposure correction
        (:func:`neighbours_mid_shift`)."""
        self.offsets[frame] = self.offsets[frame] + neighbours_mid_shift(self.offsets, train, frame)

    def mid_pose(self, frame: int) -> np.ndarray:
        """``frame``'s camera-to-world at mid-exposure."""
        return virtual_pose(self.poses[frame], *self.offsets[frame], 0.5, self.bends[frame])

    def mid_poses(self, frames: list[int] | None = None) -> list[np.ndarray]:
        """The mid-exposure poses of ``frames`` (None: every frame)."""
        return [self.mid_pose(f) for f in (range(len(self.poses)) if frames is None else frames)]

    def ends(self) -> np.ndarray:
        """(N, 2, 4, 4) every frame's camera-to-world at the start and the end of its exposure."""
        return np.stack([[virtual_pose(self.poses[i], *self.offsets[i], tau) for tau in (0.0, 1.0)]
                         for i in range(len(self.poses))])

    def state(self) -> dict[str, np.ndarray]:
        """Arrays to checkpoint: the offsets, the colours and both optimisers' moments."""
        return {"offsets": self.offsets, "colours": self.colours, **self._exposure_adam.state("exposure"),
                **self._colour_adam.state("colour")}

    def matches(self, arrays: dict[str, np.ndarray]) -> bool:
        """Whether ``arrays`` (a checkpoint's) hold exposures of as many frames as these."""
        return arrays["offsets"].shape == self.offsets.shape

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore what :meth:`state` saved."""
        self.offsets, self.colours = arrays["offsets"].copy(), arrays["colours"].copy()
        self._exposure_adam.load_state(arrays, "exposure")
        self._colour_adam.load_state(arrays, "colour")
