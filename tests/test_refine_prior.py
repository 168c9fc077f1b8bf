"""Stage 2's pose prior: its gradient matches finite differences and it pulls a pose back to stage 1's."""

from __future__ import annotations

import dataclasses

import numpy as np

from taichi_gs.geometry import invert, se3_exp, se3_log
from taichi_gs.stages.refine.run import PRESETS, _adam_pose_step, _pose_prior_gradient
from taichi_gs.stages.row_adam import RowAdam

CONFIG = dataclasses.replace(PRESETS["fast"], pose_prior_weight=0.003, pose_prior_sigma_m=0.003, pose_prior_sigma_deg=0.1)


def _prior_loss(pose: np.ndarray, initial: np.ndarray) -> float:
    e = se3_log(invert(initial) @ pose)
    sigma = np.array([CONFIG.pose_prior_sigma_m] * 3 + [np.radians(CONFIG.pose_prior_sigma_deg)] * 3)
    return 0.5 * CONFIG.pose_prior_weight * float(np.sum((e / sigma) ** 2))


def test_prior_gradient_matches_finite_differences():
    initial = se3_exp(np.array([0.3, -0.1, 0.2, 0.1, 0.2, -0.05]))
    pose = initial @ se3_exp(np.array([0.002, -0.001, 0.003, 0.0004, -0.0008, 0.0006]))
    analytic = _pose_prior_gradient(pose, initial, CONFIG)
    h = 1e-7
    numeric = np.array([(_prior_loss(pose @ se3_exp(h * np.eye(6)[i]), initial)
                         - _prior_loss(pose @ se3_exp(-h * np.eye(6)[i]), initial)) / (2 * h) for i in range(6)])
    np.testing.assert_allclose(analytic, numeric, rtol=5e-3, atol=1e-6 * np.abs(numeric).max())
    assert _pose_prior_gradient(pose, initial, PRESETS["fast"]) is None  # off by default (the method)


def test_prior_alone_pulls_the_pose_back_to_stage_one():
    initial = se3_exp(np.array([0.3, -0.1, 0.2, 0.1, 0.2, -0.05]))
    pose = initial @ se3_exp(np.array([0.01, -0.005, 0.008, 0.002, -0.003, 0.001]))
    adam = RowAdam(1, (6,), eps=1e-12)
    lr = np.array([1e-3] * 3 + [5e-4] * 3)
    start = np.linalg.norm(se3_log(invert(initial) @ pose))
    for _ in range(200):
        prior = _pose_prior_gradient(pose, initial, CONFIG)
        pose = _adam_pose_step(pose, np.zeros(6), adam, 0, lr, prior)
    assert np.linalg.norm(se3_log(invert(initial) @ pose)) < 0.1 * start
