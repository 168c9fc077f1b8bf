"""What stages 2 and 3 share: learning-rate decay and the reduced training resolution."""

from __future__ import annotations

import numpy as np


def exp_decay(start: float, end: float, fraction: float) -> float:
    """Log-linear interpolation from ``start`` (fraction 0) to ``end`` (fraction 1), as 3DGS decays rates."""
    return float(np.exp(np.log(start) * (1.0 - fraction) + np.log(end) * fraction))


def downsample_depth(depth: np.ndarray, scale: int) -> np.ndarray:
    """Nearest-neighbour subsampling at pixel centres (keeps depth sharp, no mixing at edges)."""
    if scale == 1:
        return depth
    return np.ascontiguousarray(depth[scale // 2::scale, scale // 2::scale])


def scaled_intrinsics(K: np.ndarray, scale: int) -> np.ndarray:
    """Intrinsics of the image subsampled at pixels scale*i + scale//2 (OpenCV convention)."""
    K = K.copy()
    K[0, 0] /= scale
    K[1, 1] /= scale
    K[0, 2] = (K[0, 2] - scale // 2) / scale
    K[1, 2] = (K[1, 2] - scale // 2) / scale
    return K


def training_scale(iteration: int, iterations: int, base_scale: int, coarse_scale: int, coarse_fraction: float) -> int:
    """[ours] Coarse-to-fine: the resolution divisor at ``iteration``. The first ``coarse_fraction``
    of the ``iterations`` is split evenly into levels ``coarse_scale``, ``coarse_scale // 2``, ... down
    to 2 (times ``base_scale``); the rest trains at ``base_scale`` (the end is always at the base
    resolution, so Gaussians too small for the coarse pixels are corrected)."""
    coarse = int(round(coarse_fraction * iterations))
    if coarse_scale <= 1 or iteration >= coarse:
        return base_scale
    levels = [coarse_scale]
    while levels[-1] // 2 >= 2:
        levels.append(levels[-1] // 2)
    return base_scale * levels[min(iteration * len(levels) // coarse, len(levels) - 1)]


def views_for_span(span_px: float, max_step_px: float, k_min: int, k_max: int) -> int:
    """[ours] The 1 px rule per exposure: the fewest virtual views whose neighbours lie at most
    ``max_step_px`` apart on an exposure ``span_px`` long (ceil(span / step) + 1), within [k_min, k_max]."""
    wanted = int(np.ceil(max(span_px, 0.0) / max_step_px)) + 1
    return int(min(max(wanted, k_min), k_max))


def window_converged(values: list[float], window: int, rel_tol: float) -> bool:
    """[ours] True when the mean of the last ``window`` values differs from the mean of the
    ``window`` before by at most ``rel_tol`` of the latter (False until 2 windows are there)."""
    if window < 1 or len(values) < 2 * window:
        return False
    last = float(np.mean(values[-window:]))
    before = float(np.mean(values[-2 * window:-window]))
    return abs(last - before) <= rel_tol * max(abs(before), 1e-12)


class ConvergenceWatch:
    """[ours] Stops a schedule that has converged: at every ``window``-th iteration (not within two
    windows after ``quiet_after`` marks, e.g. an opacity reset), the mean loss of the last window
    must differ from the window before by at most ``rel_tol`` of it, and no camera may have moved
    more than ``pose_m`` metres or ``pose_deg`` degrees since the previous check."""

    def __init__(self, window: int, rel_tol: float, pose_m: float, pose_deg: float) -> None:
        self.window, self.rel_tol, self.pose_m, self.pose_deg = window, rel_tol, pose_m, pose_deg
        self.losses: list[float] = []
        self.poses: np.ndarray | None = None
        self.quiet_until = 0
        self.last_move = (float("inf"), float("inf"))

    def disturbed(self, iteration: int) -> None:
        """The schedule changed the scene at ``iteration`` (a reset): no decision for two windows."""
        self.quiet_until = iteration + 2 * self.window

    def update(self, iteration: int, loss: float, poses: np.ndarray) -> bool:
        """Record iteration ``iteration``'s loss (1-based count of iterations done); True to stop."""
        self.losses.append(float(loss))
        if self.window < 1 or iteration % self.window:
            return False
        previous, self.poses = self.poses, poses.copy()
        if previous is None:
            return False
        moved = np.linalg.norm(poses[:, :3, 3] - previous[:, :3, 3], axis=1).max()
        relative = np.einsum("nji,njk->nik", previous[:, :3, :3], poses[:, :3, :3])
        cos = np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
        turned = float(np.degrees(np.arccos(cos)).max())
        self.last_move = (float(moved), turned)
        return (iteration >= self.quiet_until and moved <= self.pose_m and turned <= self.pose_deg
                and window_converged(self.losses, self.window, self.rel_tol))
