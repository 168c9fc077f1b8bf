"""bench/mocap_jitter.py: a motion-capture trajectory's per-sample orientation noise is recovered from its
differences under a fast smooth motion, and the RPE rotation floor it predicts is what frames slerped from the
noisy samples read against the smooth truth."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from mocap_jitter import jitter_per_axis_deg, rpe_rotation_floor_deg  # noqa: E402

from taichi_gs.evaluate import rpe  # noqa: E402
from taichi_gs.io.trajectory import interpolate_poses  # noqa: E402

NOISE_DEG = np.array([0.06, 0.03, 0.02])


def _smooth_rotation(t: float) -> np.ndarray:
    """A hand-held-like sweep: up to ~90 deg/s about changing axes."""
    return cv2.Rodrigues(np.array([0.6 * np.sin(2.1 * t), 0.5 * np.sin(1.3 * t + 1.0), 0.3 * np.sin(3.0 * t)]))[0]


def _mocap(rng: np.random.Generator, seconds: float = 30.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """100 Hz sample times, the smooth truth's poses and the noisy samples' poses (N x 4 x 4)."""
    times = np.arange(0.0, seconds, 0.01)
    truth = np.tile(np.eye(4), (len(times), 1, 1))
    noisy = truth.copy()
    for k, t in enumerate(times):
        truth[k, :3, :3] = _smooth_rotation(t)
        noisy[k, :3, :3] = truth[k, :3, :3] @ cv2.Rodrigues(np.radians(NOISE_DEG * rng.standard_normal(3)))[0]
    return times, truth, noisy


def test_the_jitter_of_noisy_samples_is_recovered_under_a_fast_motion():
    times, truth, noisy = _mocap(np.random.default_rng(0))
    for order in (3, 4):
        np.testing.assert_allclose(jitter_per_axis_deg(times, noisy[:, :3, :3], order), NOISE_DEG, rtol=0.12)
    # without noise the differences are the motion's own: far below the noise above
    assert np.all(jitter_per_axis_deg(times, truth[:, :3, :3], 3) < 0.1 * NOISE_DEG)


def test_the_floor_is_the_rpe_rotation_of_exact_poses_against_frames_slerped_from_noisy_samples():
    rng = np.random.default_rng(1)
    times, truth, noisy = _mocap(rng)
    frames = np.arange(0.2, 29.5, 1 / 30) + rng.uniform(0, 0.01)
    exact = np.tile(np.eye(4), (len(frames), 1, 1))
    for k, t in enumerate(frames):
        exact[k, :3, :3] = _smooth_rotation(t)
    reference = interpolate_poses(times, noisy, frames, 0.01)
    measured = rpe(exact, reference)[1]
    assert abs(measured - rpe_rotation_floor_deg(NOISE_DEG)) < 0.1 * rpe_rotation_floor_deg(NOISE_DEG)
