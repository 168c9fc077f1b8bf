"""Stage-1 loss terms on their own, their Jacobians, and the robust solver, on the exact test scene."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_pose_scene import MOTION, exact_flow, pair

from taichi_gs.geometry import invert, se3_exp, se3_log
from taichi_gs.stages.pose.config import PoseConfig
from taichi_gs.stages.pose.icp import reliable_depth_mask
from taichi_gs.stages.pose.losses import (depth_consistency_residuals, flow_residuals, photometric_residuals,
                                          point_to_plane_residuals, warp)
from taichi_gs.stages.pose.pair import add_joint, sample_pair
from taichi_gs.stages.pose.solver import active_terms, linearise, solve


@pytest.fixture(scope="module")
def scene():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    flow = exact_flow(depth_t, K, MOTION)
    mask = reliable_depth_mask(depth_t, 0.1, 10.0, 0.05)
    samples = sample_pair(color_t, depth_t, color_t1, depth_t1, K, flow, None, mask, PoseConfig(max_points=1500))
    return samples


def depth_term(T, samples):
    return depth_consistency_residuals(warp(T, samples), samples, min_baseline=1e-3)


TERMS = {
    "flow": lambda T, s: flow_residuals(warp(T, s), s),
    "photometric": lambda T, s: photometric_residuals(warp(T, s), s),
    "depth_consistency": depth_term,
    "point_to_plane": lambda T, s: point_to_plane_residuals(warp(T, s), s),
}


def mean_abs(term, T, samples) -> float:
    w = warp(T, samples)
    return float(np.mean(term(T, samples).norms()[w.valid]))


def perturbed(delta) -> np.ndarray:
    return se3_exp(np.asarray(delta, dtype=np.float64)) @ MOTION


def test_depth_consistency_is_zero_at_true_pose_and_grows_away(scene):
    at_truth = mean_abs(depth_term, MOTION, scene)
    assert at_truth < 1e-4  # metres; only bilinear depth interpolation error remains
    previous = at_truth
    for size in (0.002, 0.005, 0.01, 0.02):
        away = mean_abs(depth_term, perturbed([size, -size, 0, 0, 0, size]), scene)
        assert away > previous
        previous = away
    assert previous > 50 * at_truth


def test_point_to_plane_is_zero_at_true_pose_and_needs_normals(scene):
    assert mean_abs(TERMS["point_to_plane"], MOTION, scene) < 1e-4  # metres: bilinear depth's error only
    assert scene.target_normals is not None and np.isfinite(scene.target_normals).any()
    config = PoseConfig()
    joint = config.joint_settings(flow_scale_px=0.5, plane_scale=2.0)
    assert joint.plane_weight == config.joint_plane_weight * 0.5 / 2.0 and joint.photometric_weight == 0.0
    assert (joint.flow_floor_px, joint.plane_floor) == (0.5, 2.0)
    assert config.solver_settings(with_all_terms=True).plane_weight == 0.0  # the method's solve has no L_P


def test_every_term_is_smallest_at_the_true_pose(scene):
    for name, term in TERMS.items():
        at_truth = mean_abs(term, MOTION, scene)
        for delta in np.eye(6) * 0.01:
            assert mean_abs(term, perturbed(delta), scene) > at_truth, name


@pytest.mark.parametrize("name, tolerance", [("flow", 1e-4), ("depth_consistency", 2e-2), ("photometric", 0.15)])
def test_jacobian_matches_finite_differences(scene, name, tolerance):
    """Left-perturbation Jacobians against central differences (photometric: image gradients are
    central differences, not the bilinear interpolant's slope, hence the looser tolerance)."""
    term = TERMS[name]
    T = perturbed([0.01, 0.005, -0.008, 0.004, -0.003, 0.006])
    analytic = term(T, scene).jacobian
    eps = 1e-5
    numeric = np.stack(
        [(term(se3_exp(eps * e) @ T, scene).values - term(se3_exp(-eps * e) @ T, scene).values) / (2 * eps) for e in np.eye(6)],
        axis=-1,
    )
    valid = warp(T, scene).valid
    error = np.linalg.norm(analytic[valid] - numeric[valid]) / np.linalg.norm(numeric[valid])
    assert error < tolerance


def test_point_to_plane_jacobian_matches_finite_differences(scene):
    """L_P holds frame t+1's normal at the nearest pixel fixed (as point-to-plane ICP does), so the comparison
    leaves out the points whose nearest pixel changes within the differences' step."""
    term = TERMS["point_to_plane"]
    T = perturbed([0.01, 0.005, -0.008, 0.004, -0.003, 0.006])
    eps = 1e-5
    steps = [se3_exp(sign * eps * e) @ T for e in np.eye(6) for sign in (1, -1)]
    numeric = np.stack([(term(steps[2 * k], scene).values - term(steps[2 * k + 1], scene).values) / (2 * eps)
                        for k in range(6)], axis=-1)
    nearest = [np.round(warp(X, scene).pixels) for X in [T, *steps]]
    same_pixel = np.all([np.all(n == nearest[0], axis=1) for n in nearest[1:]], axis=0)
    keep = warp(T, scene).valid & same_pixel
    assert keep.sum() > 0.95 * warp(T, scene).valid.sum()
    analytic = term(T, scene).jacobian
    error = np.linalg.norm(analytic[keep] - numeric[keep]) / np.linalg.norm(numeric[keep])
    assert error < 1e-4


def test_flow_term_alone_recovers_the_motion_from_exact_flow(scene):
    result = solve(np.eye(4), scene, PoseConfig().solver_settings(with_all_terms=False))
    error = se3_log(result.T @ invert(MOTION))
    assert result.converged
    assert np.linalg.norm(error[:3]) < 1e-6 and np.linalg.norm(error[3:]) < 1e-6


def test_full_loss_recovers_the_motion_despite_flow_outliers(scene):
    """30% of the flow vectors replaced by garbage: the robust sum of norms still finds the motion."""
    rng = np.random.default_rng(1)
    flow = scene.flow.copy()
    bad = rng.random(len(flow)) < 0.3
    flow[bad] = rng.normal(0, 15, (bad.sum(), 2))
    corrupted = type(scene)(**{**scene.__dict__, "flow": flow})
    config = PoseConfig()
    first = solve(np.eye(4), corrupted, config.solver_settings(with_all_terms=False))
    second = solve(first.T, corrupted, config.solver_settings(with_all_terms=True))
    error = se3_log(second.T @ invert(MOTION))
    assert np.linalg.norm(error[:3]) < 1e-3 and np.degrees(np.linalg.norm(error[3:])) < 0.02


def test_joint_solve_corrects_a_biased_flow_with_depth():
    """[ours] The joint candidate (flow terms plus L_P, from the flow solve) on a back wall with a strip of
    floor, its flow noisy (0.5 px) and biased (0.6 px down): depth pins what the bias moved."""
    from test_pose_verify import MOTION as WALL_MOTION, START

    color_t, depth_t, color_t1, depth_t1, K = pair(WALL_MOTION, 160, 120, start=START)
    rng = np.random.default_rng(0)
    flow = exact_flow(depth_t, K, WALL_MOTION) + rng.normal(0, 0.5, depth_t.shape + (2,)) + np.array([0.0, 0.6])
    config = PoseConfig()
    samples = sample_pair(color_t, depth_t, color_t1, depth_t1, K, flow, None,
                          reliable_depth_mask(depth_t, 0.1, 10.0, 0.05), config)
    flow_only = solve(np.eye(4), samples, config.solver_settings(with_all_terms=False))
    flow_solve = solve(flow_only.T, samples, config.solver_settings(with_all_terms=True))
    candidates = {}
    add_joint(candidates, samples, flow_solve.T, config)
    joint = candidates["joint"].transform

    def error_mm(T):
        return 1000 * np.linalg.norm(se3_log(T @ invert(WALL_MOTION))[:3])

    assert error_mm(flow_only.T) > 2.0  # the bias alone: 4.0 mm measured
    assert error_mm(joint) < 0.05 * error_mm(flow_only.T)  # 0.16 mm measured
    assert error_mm(joint) < error_mm(flow_solve.T)  # the method's solve, with its exact photometric term: 0.27


@pytest.mark.parametrize("settings_of, term_count", [
    (lambda c: c.solver_settings(with_all_terms=True), 3),
    (lambda c: c.joint_settings(flow_scale_px=0.5, plane_scale=1.0), 2),
], ids=["flow+photometric+consistency", "joint: flow+plane"])
def test_normal_equations_sum_each_valid_points_weighted_jacobian_products(scene, settings_of, term_count):
    """linearise's IRLS system against a loop over points: H = sum w J^T J, g = sum w J^T r, w = weight /
    max(|r|, floor) / n over the valid points."""
    settings = dataclasses.replace(settings_of(PoseConfig()), min_points=1)
    T = perturbed([0.004, -0.003, 0.002, 0.003, -0.002, 0.001])
    system = linearise(T, scene, settings)
    valid, terms = active_terms(T, scene, settings)
    n = int(valid.sum())
    H, g = np.zeros((6, 6)), np.zeros(6)
    for residuals, weight, floor in terms:
        for k in np.flatnonzero(valid):
            r, J = residuals.values[k], residuals.jacobian[k]
            w = weight / max(float(np.linalg.norm(r)), floor) / n
            H += w * J.T @ J
            g += w * J.T @ r
    assert len(terms) == term_count and n > 500
    np.testing.assert_allclose(system.hessian, H, rtol=1e-9, atol=1e-12 * np.abs(H).max())
    np.testing.assert_allclose(system.gradient, g, rtol=1e-9, atol=1e-12 * np.abs(g).max())
