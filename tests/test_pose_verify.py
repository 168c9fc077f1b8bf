"""Verification score: a pose slid along a plane fits the depth as well as the truth (ICP cannot tell),
but not the colour; the score catches it and the stage keeps the right candidate."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from test_pose_scene import pair

from taichi_gs.geometry import invert, se3_exp, se3_log
from taichi_gs.stages.pose.config import PoseConfig
from taichi_gs.stages.pose.icp import depth_cloud
from taichi_gs.stages.pose.pair import estimate_relative_pose
from taichi_gs.stages.pose.verify import depth_normals, frame_view, verify

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


def _wall_pair(distance_m: float):
    """Two noisy 160x120 views of one plain painted wall (synth's `plain` room) from ``distance_m``, the
    second 3 cm aside and 0.6 deg turned: (colour, depth) of each, K and the true transform A -> B."""
    from taichi_gs.synth import SynthConfig, camera_matrix, render_view

    K = camera_matrix(SynthConfig(width=160, height=120))
    A = np.eye(4)
    A[:3, 3] = [0.3, 0.0, 3.3 - distance_m]  # the plain room of seed 0 has its +z wall at z = 3.31
    B = A @ se3_exp(np.array([0.03, 0.005, 0.0, 0.0, 0.01, 0.0]))
    rng = np.random.default_rng(0)
    frames = []
    for pose in (A, B):
        color, depth = render_view(pose, K, 160, 120, 0, "plain")
        color = np.clip(color + rng.normal(0, 0.003, color.shape), 0, 1).astype(np.float32)
        frames.append((color, depth + rng.normal(0, 1, depth.shape) * 0.0015 * depth ** 2))
    return frames, K, invert(B) @ A


def test_flow_check_catches_a_slide_along_a_plain_wall_that_the_score_misses():
    import dataclasses

    from taichi_gs.stages.pose.flow import rigid_flow
    from taichi_gs.stages.pose.pair import Candidate, choose
    from taichi_gs.stages.pose.verify import FlowCheck, flow_disagreement

    (frame_a, frame_b), K, true = _wall_pair(1.3)
    config = PoseConfig()
    views = tuple(frame_view(c, d, K, config.verify_settings()) for c, d in (frame_a, frame_b))
    slid = se3_exp(np.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.0])) @ true  # 1 cm along the wall: ~1 px
    candidates = {"flow": Candidate(true), "rgbd-icp": Candidate(slid)}
    measured = rigid_flow(views[0].depth, K, true)
    check = FlowCheck(measured, np.all(np.isfinite(measured), axis=-1))
    assert flow_disagreement(true, views[0].depth, K, check, 2.0) < 1e-6
    assert flow_disagreement(slid, views[0].depth, K, check, 2.0) > 0.1
    no_check = dataclasses.replace(config, verify_flow_weight=0.0)
    assert choose(candidates, views, K, no_check, flow_check=check).estimate == "rgbd-icp"  # score alone: blind
    chosen = choose(candidates, views, K, config, flow_check=check)
    assert chosen.estimate == "flow" and chosen.candidates["rgbd-icp"]["flow"] > 0.1


def test_interpolation_noise_is_largest_on_a_pixel_smallest_between_four_and_one_on_average():
    from taichi_gs.stages.pose.verify import interpolation_noise

    pixels = np.array([[3.0, 7.0], [3.5, 7.0], [3.5, 7.5], [10.25, 2.0]])
    expected = np.sqrt((1.0 + np.array([1.0, 0.5, 0.25, 0.625])) / (13.0 / 9.0))
    np.testing.assert_allclose(interpolation_noise(pixels), expected)
    spread = np.random.default_rng(0).uniform(0, 50, (200_000, 2))  # mean variance over positions: unchanged
    assert np.mean(interpolation_noise(spread) ** 2) == pytest.approx(1.0, abs=2e-3)


def test_a_still_camera_scores_no_worse_than_a_half_pixel_slide_along_a_plain_wall():
    """A camera at rest puts every grid point on a pixel of the other frame, where the residual holds two
    whole depth samples' noise; half a pixel aside, bilinear interpolation averages the target's noise down.
    Scored with one noise scale for both, the still camera lost to a wrong motion (a stage-1 pair at the
    turn of synth's plain translation picked a 15 mm-wrong candidate over the right one this way)."""
    from taichi_gs.synth import SynthConfig, camera_matrix, render_view

    K = camera_matrix(SynthConfig(width=160, height=120))
    A = np.eye(4)
    A[:3, 3] = [0.3, 0.0, 3.3 - 1.3]  # 1.3 m from the plain room's +z wall
    rng = np.random.default_rng(0)
    views = []
    for _ in range(2):  # the same pose twice, each with its own depth noise
        color, depth = render_view(A, K, 160, 120, 0, "plain")
        views.append(frame_view(color.astype(np.float32), depth + rng.normal(0, 1, depth.shape) * 0.0015 * depth ** 2, K))
    half_pixel = se3_exp(np.array([0.5 * 1.3 / K[0, 0], 0.0, 0.0, 0.0, 0.0, 0.0]))
    still, slid = verify(np.eye(4), *views, K), verify(half_pixel, *views, K)
    assert still.geometric < 1.05 * slid.geometric, (still.geometric, slid.geometric)  # 1.23x before the fix


def test_graph_edge_gets_a_joint_candidate_on_its_own_flows(monkeypatch):
    """[ours] An extra graph edge from chained poses that slid 2.5 cm along the back wall: its joint candidate
    (flow plus point-to-plane on the edge's flows, from the chain, the default) lands on the true motion; with
    ``graph_joint = false`` there is none."""
    from test_pose import SceneSequence

    from taichi_gs.stages.pose import edges as pose_edges
    from taichi_gs.stages.pose import frames as pose_frames

    sequence = SceneSequence(np.stack([START, START @ invert(MOTION)]))
    K = sequence.intrinsics.K()
    slid_chain = np.stack([START, START @ invert(SLIDE @ MOTION)])
    seen = {}
    original = pose_edges.choose

    def recording(candidates, *args, **kwargs):
        seen.clear()
        seen.update(candidates)
        return original(candidates, *args, **kwargs)

    monkeypatch.setattr(pose_edges, "choose", recording)
    config = PoseConfig()
    frames = pose_frames.FrameCache(sequence, K, config)
    edge = pose_edges._graph_edge(frames, 0, 1, slid_chain, K, config, "skip", np.inf)
    assert _error_mm(seen["chain"].transform) > 20.0
    assert _error_mm(seen["rgbd-chain"].transform) > 1.0  # RGB-D odometry from the chain: 3.2 mm measured
    assert _error_mm(seen["joint-chain"].transform) < 0.5  # 0.14 mm measured
    assert edge is not None and edge.estimate == "joint-chain"

    no_joint = PoseConfig(graph_joint=False)
    assert no_joint.pair_key() == config.pair_key()  # a graph setting: the pairs stay cached
    pose_edges._graph_edge(pose_frames.FrameCache(sequence, K, no_joint), 0, 1, slid_chain, K, no_joint, "skip", np.inf)
    assert "joint-chain" not in seen


def test_depth_normals_are_unit_cross_products_of_central_differences_facing_the_camera():
    """Against a loop over pixels: n = (P[v, u+1] - P[v, u-1]) x (P[v+1, u] - P[v-1, u]), normalised and turned
    towards the camera; NaN on the border and next to a masked pixel."""
    rng = np.random.default_rng(3)
    h, w = 9, 12
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    z = 1.5 + 0.05 * u - 0.03 * v + 0.01 * rng.standard_normal((h, w))
    points = np.stack([(u - 6) / 10 * z, (v - 4) / 10 * z, z], axis=-1)
    mask = rng.random((h, w)) > 0.15
    normals = depth_normals(points, mask)
    for y in range(h):
        for x in range(w):
            inner = 0 < y < h - 1 and 0 < x < w - 1
            if not (inner and mask[y, x] and mask[y, x - 1] and mask[y, x + 1] and mask[y - 1, x] and mask[y + 1, x]):
                assert np.isnan(normals[y, x]).all()
                continue
            n = np.cross(points[y, x + 1] - points[y, x - 1], points[y + 1, x] - points[y - 1, x])
            n /= np.linalg.norm(n)
            n = -n if n @ points[y, x] > 0 else n
            np.testing.assert_allclose(normals[y, x], n, rtol=0, atol=1e-12)
    assert np.isfinite(normals).all(axis=-1).sum() > 20
