"""Blur streaks: how far scene points move on the image over a camera's exposure.

``synth`` sizes and records its blur with them; ``taichi-gs eval`` reports with them the blur that stage 3
learned (``noreference_report``)."""

from __future__ import annotations

import numpy as np

from .geometry import backproject, interpolate, invert, project, transform

SMEAR_SAMPLES = 9  # poses along the exposure at which smear paths are measured
SMEAR_STRIDE_PX = 4  # pixel grid stride of the points whose smear is measured


def point_tracks(depth: np.ndarray, K: np.ndarray, view: np.ndarray, poses, stride: int = 1) -> np.ndarray:
    """Pixel positions (n_poses x n_points x 2) of the valid points of ``depth`` (seen from ``view``)
    in each of ``poses``; points behind any of those cameras are left out."""
    valid = depth[::stride, ::stride] > 0
    world = transform(view, backproject(depth[::stride, ::stride], K)[valid])
    cams = np.stack([transform(invert(pose), world) for pose in poses])
    in_front = np.all(cams[..., 2] > 0.05, axis=0)
    return project(cams[:, in_front], K)


def path_lengths(tracks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per point: total path length and longest single step of a track, in pixels."""
    steps = np.linalg.norm(np.diff(tracks, axis=0), axis=-1)
    return steps.sum(axis=0), steps.max(axis=0, initial=0.0)


def exposure_poses(start: np.ndarray, end: np.ndarray, count: int) -> list[np.ndarray]:
    """``count`` poses interpolated from start to end (the mid pose alone when count is 1)."""
    taus = [0.5] if count == 1 else np.linspace(0.0, 1.0, count)
    return [interpolate(start, end, tau) for tau in taus]


def exposure_smear(
    depth: np.ndarray, K: np.ndarray, mid: np.ndarray, start: np.ndarray, end: np.ndarray
) -> tuple[float, float]:
    """Mean and max length (pixels) of the streaks that points seen at mid-exposure draw."""
    poses = exposure_poses(start, end, SMEAR_SAMPLES)
    lengths, _ = path_lengths(point_tracks(depth, K, mid, poses, SMEAR_STRIDE_PX))
    if lengths.size == 0:
        return 0.0, 0.0
    return float(lengths.mean()), float(lengths.max())
