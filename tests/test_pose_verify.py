"""Verification score: a pose slid along a plane fits the depth as well as the truth (ICP cannot tell),
but not the colour; the score catches it and the stage keeps the right candidate."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from test_pose_scene import pair

from taichi_gs.geometry import invert, se3_exp, se3_log
from taichi_gs.icp import depth_cloud
from taichi_gs.pose_verify import frame_view, verify
from taichi_gs.stages.pose import PoseConfig, estimate_relative_pose

START = se3_exp(np.array([0.1, 0.55, 1.5, 0.0, 0.0, 0.0]))  # facing the back wall 1.5 m away: a strip of floor
MOTION = se3_exp(np.array([0.01, 0.005, 0.0, 0.0, 0.008, 0.0]))
SLIDE = se3_exp(np.array([0.025, 0.0, 0.0, 0.0, 0.0, 0.0]))  # 2.5 cm along the wall


def _error_mm(T: np.ndarray) -> float:
    return 1000 * float(np.linalg.norm(se3_log(T @ invert(MOTION))[:3]))


def test_slid_planar_pose_fits_depth_like_the_truth_but_is_caught_by_the_score():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION, 160, 120, start=START)
    slid = SLIDE @ MOTION
    source, target = depth_cloud(depth_t, K, depth_t > 0), depth_cloud(depth_t1, K, depth_t1 > 0)
    fits = [o3d.pipelines.registration.evaluate_registration(source, target, 0.02, T) for T in (MOTION, slid)]
    assert min(f.fitness for f in fits) > 0.9  # ICP's own measures cannot tell the two apart
    assert abs(fits[0].inlier_rmse - fits[1].inlier_rmse) < 1e-3

    views = (frame_view(color_t, depth_t, K), frame_view(color_t1, depth_t1, K))
    true_score, slid_score = verify(MOTION, *views, K), verify(slid, *views, K)
    assert slid_score.geometric < 0.01  # depth agrees with the slide too ...
    assert slid_score.score > 0.05 and slid_score.score > 20 * true_score.score  # ... colour does not
    assert verify(se3_exp(np.array([0.0, 0.0, 0.02, 0.0, 0.0, 0.0])) @ MOTION, *views, K).geometric > 0.1  # off-plane: depth


def test_stage_keeps_the_verified_candidate_when_the_prior_has_slid():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION, 160, 120, start=START)
    slid = SLIDE @ MOTION
    result = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K, config=PoseConfig(), prior=slid)
    assert not result.weak, result.reason
    assert _error_mm(result.transform) < 3.0  # 0.1 mm measured
    scores = {name: c["score"] for name, c in result.candidates.items()}
    assert scores["constant-velocity"] > 20 * result.score
    assert result.estimate != "constant-velocity"


def test_pair_without_overlap_is_weak_and_keeps_the_prior():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    prior = se3_exp(np.array([0.01, 0, 0, 0, 0, 0]))
    result = estimate_relative_pose(color_t, np.zeros_like(depth_t), color_t1, depth_t1, K, config=PoseConfig(), prior=prior)
    assert result.weak and result.estimate == "constant-velocity"
    np.testing.assert_array_equal(result.transform, prior)
