"""Stage 1's estimate of one pair of frames: the method's flow solve and point-to-plane ICP, or [ours] verified
candidates (the flow solve, the joint solve, ICP from the flow solve and from the constant-velocity prior, RGB-D
odometry from each ICP result), scored alike on both frames' depth and colour, of which the lowest score wins."""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .. import profiling
from ..flow import dis_flow, finite_flow, forward_backward_mask, rigid_flow, to_gray_u8
from ..geometry import backproject, invert, se3_log
from ..icp import ICPLevels, align, depth_cloud, prepare_icp, rgbd_odometry
from ..io.jsonout import finite_or_null
from ..pose_verify import FlowCheck, FrameView, Verification, depth_normals, flow_disagreement, frame_view, verify
from .pose_config import PoseConfig
from .pose_losses import PairSamples, flow_residuals, image_gradient, warp
from .pose_solver import solve, typical_residuals

if TYPE_CHECKING:
    import open3d as o3d

# Estimate kinds recorded per pair.
FROM_RGBD, FROM_ICP, FROM_FLOW, FROM_CONSTANT_VELOCITY = "rgbd", "icp", "flow", "constant-velocity"
FROM_JOINT = "joint"
# ICP starts closer than this (every entry of the 4 x 4 transform) give one RGB-D odometry run: ICP from the
# flow solve and ICP from the prior ended within 1e-9 of each other in 2862 of 3926 stored pairs
SAME_START_ATOL = 1e-9


@dataclass
class RelativePose:
    """Transform camera t -> camera t+1 and how it was obtained."""

    transform: np.ndarray
    estimate: str  # rgbd | icp | flow | constant-velocity
    weak: bool = False
    flow_seed: str = "none"  # none | constant-velocity | icp: the motion whose flow seeded DIS
    reason: str = ""
    flow_transform: np.ndarray | None = None
    flow_residual_px: float = float("nan")  # median |F(p_i) - (p_j - p_i)| at the final transform
    points: int = 0
    iterations: tuple[int, int] = (0, 0)
    icp_fitness: float = float("nan")
    icp_inlier_rmse_m: float = float("nan")
    seconds: float = 0.0  # wall time; in run_pose what the pair added to the stage's (its work ahead overlapped)
    score: float = float("nan")  # verification score of the chosen transform (lower is better)
    overlap: float = float("nan")
    candidates: dict = field(default_factory=dict)  # candidate name -> verification (as a dict)
    icp_transform: np.ndarray | None = None  # ICP's own result, also when rejected (not saved)

    def to_dict(self) -> dict:
        return {
            "transform": self.transform.tolist(),
            "estimate": self.estimate, "weak": self.weak, "flow_seed": self.flow_seed, "reason": self.reason,
            "flow_transform": None if self.flow_transform is None else self.flow_transform.tolist(),
            "flow_residual_px": finite_or_null(self.flow_residual_px), "points": self.points,
            "iterations": list(self.iterations), "icp_fitness": finite_or_null(self.icp_fitness),
            "icp_inlier_rmse_m": finite_or_null(self.icp_inlier_rmse_m), "seconds": round(self.seconds, 4),
            "score": finite_or_null(self.score), "overlap": finite_or_null(self.overlap), "candidates": self.candidates,
        }

    @classmethod
    def from_dict(cls, d: dict) -> RelativePose:
        nan = float("nan")
        return cls(
            transform=np.array(d["transform"], dtype=np.float64), estimate=d["estimate"], weak=d["weak"],
            flow_seed=d["flow_seed"], reason=d["reason"],
            flow_transform=None if d["flow_transform"] is None else np.array(d["flow_transform"], dtype=np.float64),
            flow_residual_px=nan if d["flow_residual_px"] is None else d["flow_residual_px"], points=d["points"],
            iterations=tuple(d["iterations"]), icp_fitness=nan if d["icp_fitness"] is None else d["icp_fitness"],
            icp_inlier_rmse_m=nan if d["icp_inlier_rmse_m"] is None else d["icp_inlier_rmse_m"], seconds=d["seconds"],
            score=nan if d.get("score") is None else d["score"], overlap=nan if d.get("overlap") is None else d["overlap"],
            candidates=d.get("candidates", {}),
        )


def estimate_relative_pose(
    color_t: np.ndarray,
    depth_t: np.ndarray,
    color_t1: np.ndarray,
    depth_t1: np.ndarray,
    K: np.ndarray,
    flow: np.ndarray | None = None,
    config: PoseConfig = PoseConfig(),
    backward_flow: np.ndarray | None = None,
    prior: np.ndarray | None = None,
    views: tuple[FrameView, FrameView] | None = None,
    ahead: PairStart | None = None,
) -> RelativePose:
    """Transform camera t -> t+1 minimising L_F, then L_F + l_I L_I + l_C L_C, then refined by ICP
    (and, with ``rgbd_refine``, by dense RGB-D odometry).

    With ``verify`` (default) every candidate of the pair is scored by :func:`taichi_gs.pose_verify.verify`
    and the lowest score wins (see :func:`choose`); otherwise ICP replaces the flow estimate unless it
    fits poorly or jumps away. Without ``flow``, forward and backward DIS flows are computed. When that
    estimate is weak, the pair is redone with DIS flows seeded by the flow of a guessed motion
    (``prior``, the constant-velocity guess, if it moves; then a rejected but well-fitting ICP result,
    see :func:`_retry_seeds`); a retry replaces it if it is not weak (with ``verify``: if it scores
    lower). ``prior`` (default identity) itself is returned, flagged weak, when nothing aligns the pair.
    ``views``: the two frames' :func:`taichi_gs.pose_verify.frame_view`, when already computed.
    ``ahead``: the pair's :func:`start_pair` on these flows and views, when it ran ahead (the flows are then
    not needed); the result is the same as without it.
    """
    started = time.perf_counter()
    prior = np.eye(4) if prior is None else prior
    frames = (color_t, depth_t, color_t1, depth_t1, K)
    if not config.verify:
        views = None
    elif views is None:
        settings = config.verify_settings()
        views = (frame_view(color_t, depth_t, K, settings), frame_view(color_t1, depth_t1, K, settings))
    if ahead is None:
        if flow is None:
            flow, backward_flow = dis_flows(to_gray_u8(color_t), to_gray_u8(color_t1), config)
        ahead = start_pair(*frames, flow, backward_flow, config, views)
    first = _finish_pair(ahead, *frames, prior, config, views)
    result = first
    for seed, guess in _retry_seeds(first, prior, config):
        forward, backward = seeded_flows(to_gray_u8(color_t), to_gray_u8(color_t1), depth_t, depth_t1, K, guess,
                                         config)
        retry = _finish_pair(start_pair(*frames, forward, backward, config, views, ahead.samples.target_normals),
                             *frames, prior, config, views)
        better = retry.score < result.score if config.verify else not retry.weak
        if better:
            retry.flow_seed, retry.reason = seed, f"unseeded flow failed: {first.reason}"
            result = retry
        if not result.weak:
            break
    result.seconds = ahead.seconds + time.perf_counter() - started
    return result


def _retry_seeds(first: RelativePose, prior: np.ndarray, config: PoseConfig) -> list[tuple[str, np.ndarray]]:
    """Motions to seed DIS with after a weak first attempt: a moving prior, then an ICP result that fit
    well but was rejected for jumping away from the flow estimate (kept only if the flow it seeds agrees)."""
    if not (first.weak and config.seeded_retry):
        return []
    seeds = [] if np.allclose(prior, np.eye(4)) else [(FROM_CONSTANT_VELOCITY, prior)]
    icp = first.icp_transform
    if icp is not None and np.all(np.isfinite(icp)) and first.icp_fitness >= config.icp_min_fitness:
        seeds.append((FROM_ICP, icp))
    return seeds


def dis_flows(gray_t: np.ndarray, gray_t1: np.ndarray, config: PoseConfig,
              seeds: tuple[np.ndarray | None, np.ndarray | None] = (None, None)) -> tuple[np.ndarray, np.ndarray]:
    """Forward and backward DIS flows with the config's preset and finest level (``seeds``: each one's initial
    flow, or None)."""
    preset, width = config.flow_preset, config.flow_finest_width_px
    return (dis_flow(gray_t, gray_t1, preset, seeds[0], width), dis_flow(gray_t1, gray_t, preset, seeds[1], width))


def seeded_flows(gray_t: np.ndarray, gray_t1: np.ndarray, depth_t: np.ndarray, depth_t1: np.ndarray,
                 K: np.ndarray, guess: np.ndarray, config: PoseConfig) -> tuple[np.ndarray, np.ndarray]:
    """:func:`dis_flows`, each seeded by the rigid flow of ``guess`` (camera t -> t+1)."""
    return dis_flows(gray_t, gray_t1, config, (rigid_flow(depth_t, K, guess, fill_holes=True),
                                               rigid_flow(depth_t1, K, invert(guess), fill_holes=True)))


@dataclass
class Candidate:
    """One candidate transform camera t -> t+1 and, for ICP candidates, ICP's own fit."""

    transform: np.ndarray
    icp_fitness: float = float("nan")
    icp_inlier_rmse_m: float = float("nan")


@dataclass
class PairStart:
    """The part of one attempt at a pair that does not depend on its prior (the pair before it), so that it
    can run ahead while that pair finishes: the flow samples and the flow solve; when verifying, also ICP
    from the flow solve, RGB-D odometry from that, and the verification scores of these candidates."""

    samples: PairSamples
    flow_T: np.ndarray | None
    iterations: tuple[int, int]
    reason: str  # why there is no flow solve, if there is none
    source_mask: np.ndarray
    levels: ICPLevels | None = None  # the ICP pyramid of the two frames (with ``use_icp``, when verifying)
    candidates: dict[str, Candidate] = field(default_factory=dict)
    odometry_runs: list[tuple[np.ndarray, np.ndarray | None]] = field(default_factory=list)  # see _run_once
    scores: dict[str, Verification] = field(default_factory=dict)
    flow_check: FlowCheck | None = None
    seconds: float = 0.0


def start_pair(color_t: np.ndarray, depth_t: np.ndarray, color_t1: np.ndarray, depth_t1: np.ndarray, K: np.ndarray,
               flow: np.ndarray, backward_flow: np.ndarray | None, config: PoseConfig,
               views: tuple[FrameView, FrameView] | None, target_normals: np.ndarray | None = None) -> PairStart:
    """One attempt's prior-free part with the given flows (``views``: the frames' views when verifying, else None;
    ``target_normals``: frame t+1's :func:`joint_normals`, when known)."""
    started = time.perf_counter()
    source_mask = config.reliable_depth(depth_t)
    samples = sample_pair(color_t, depth_t, color_t1, depth_t1, K, flow, backward_flow, source_mask, config,
                          target_normals)
    flow_T, iterations, reason = _flow_solve(samples, config)
    ahead = PairStart(samples, flow_T, iterations, reason, source_mask)
    if views is not None:
        if config.verify_flow_weight > 0:
            ahead.flow_check = measured_flow(flow, backward_flow)
        if config.use_icp:
            target_mask = config.reliable_depth(depth_t1)
            ahead.levels = icp_levels(depth_cloud(depth_t, K, source_mask), depth_cloud(depth_t1, K, target_mask),
                                      config)
        if flow_T is not None:
            ahead.candidates[FROM_FLOW] = Candidate(flow_T)
            if config.joint_solve:
                add_joint(ahead.candidates, samples, flow_T, config)
            if ahead.levels is not None:
                _add_icp(ahead.candidates, FROM_ICP, ahead.levels, flow_T)
        if config.rgbd_refine and FROM_ICP in ahead.candidates:
            _add_odometry(ahead.candidates, FROM_ICP, ahead.odometry_runs, color_t, depth_t, color_t1, depth_t1, K,
                          config)
        ahead.scores = {name: _score(c.transform, views, K, config, ahead.flow_check)
                        for name, c in ahead.candidates.items()}
    ahead.seconds = time.perf_counter() - started
    return ahead


def _finish_pair(ahead: PairStart, color_t: np.ndarray, depth_t: np.ndarray, color_t1: np.ndarray, depth_t1: np.ndarray,
                 K: np.ndarray, prior: np.ndarray, config: PoseConfig,
                 views: tuple[FrameView, FrameView] | None) -> RelativePose:
    """The rest of the attempt, which needs the prior: the prior's candidates and the verification of every
    candidate (``views`` given), or else the method's ICP and odometry behind its guards."""
    started = time.perf_counter()
    flow_T, samples = ahead.flow_T, ahead.samples
    if views is None and flow_T is None:
        return fallback_pose(prior, ahead.reason, started)
    if views is None:
        result = RelativePose(flow_T, FROM_FLOW, flow_transform=flow_T, points=len(samples.points),
                              iterations=ahead.iterations)
        if config.use_icp:
            _refine_with_icp(result, depth_t, depth_t1, K, ahead.source_mask, config)
        if config.rgbd_refine and result.estimate == FROM_ICP:
            _refine_with_rgbd(result, color_t, depth_t, color_t1, depth_t1, K, config)
    else:
        candidates = _candidates(ahead, color_t, depth_t, color_t1, depth_t1, K, prior, config)
        result = choose(candidates, views, K, config, flow_check=ahead.flow_check, known=ahead.scores)
        result.flow_transform, result.points, result.iterations = flow_T, len(samples.points), ahead.iterations
        if flow_T is None:
            result.reason = "; ".join(filter(None, [ahead.reason, result.reason]))
    final = warp(result.transform, samples)
    if final.valid.sum() > 0:
        result.flow_residual_px = float(np.median(flow_residuals(final, samples).norms()[final.valid]))
    if views is None and not result.weak and not result.flow_residual_px <= config.max_flow_residual_px:
        result.weak, result.reason = True, f"median flow residual {result.flow_residual_px:.2f} px"
    return result


@profiling.timed("flow solve (se(3))")
def _flow_solve(samples: PairSamples, config: PoseConfig) -> tuple[np.ndarray | None, tuple[int, int], str]:
    """The method's two solver phases from identity: (transform or None, iterations, why not)."""
    if len(samples.points) < config.min_points:
        return None, (0, 0), f"only {len(samples.points)} pixels with reliable depth and consistent flow"
    flow_only = solve(np.eye(4), samples, config.solver_settings(with_all_terms=False))
    if not np.isfinite(flow_only.cost):
        return None, (flow_only.iterations, 0), f"flow solve left {flow_only.valid_points} valid pixels"
    full = solve(flow_only.T, samples, config.solver_settings(with_all_terms=True))
    flow_T = full.T if np.isfinite(full.cost) else flow_only.T
    if not np.all(np.isfinite(flow_T)):
        return None, (flow_only.iterations, full.iterations), "solver diverged (non-finite pose)"
    return flow_T, (flow_only.iterations, full.iterations), ""


def _candidates(ahead: PairStart, color_t: np.ndarray, depth_t: np.ndarray, color_t1: np.ndarray,
                depth_t1: np.ndarray, K: np.ndarray, prior: np.ndarray, config: PoseConfig) -> dict[str, Candidate]:
    """[ours] Every candidate of a pair: the flow solve, the joint solve from it (``joint_solve``), the prior,
    ICP from the flow solve and the prior (``icp_from_prior``), and RGB-D odometry from each ICP result
    (``rgbd_refine``); ``ahead`` holds those that did not need the prior. Names say what started what; they are
    listed in that order (prior, flow, joint, ICP, odometry)."""
    found = {FROM_CONSTANT_VELOCITY: Candidate(np.array(prior, dtype=np.float64)), **ahead.candidates}
    runs = list(ahead.odometry_runs)
    if ahead.levels is not None and (config.icp_from_prior or ahead.flow_T is None):
        _add_icp(found, f"{FROM_ICP}-prior", ahead.levels, found[FROM_CONSTANT_VELOCITY].transform)
    starts = [n for n in found if n.startswith(FROM_ICP)] or [n for n in (FROM_FLOW,) if n in found]
    if config.rgbd_refine:
        for name in starts:
            if f"{FROM_RGBD}-{name}" not in found:
                _add_odometry(found, name, runs, color_t, depth_t, color_t1, depth_t1, K, config)
    order = [FROM_CONSTANT_VELOCITY, FROM_FLOW, FROM_JOINT, FROM_ICP, f"{FROM_ICP}-prior"]
    order += [f"{FROM_RGBD}-{n}" for n in starts]
    return {name: found[name] for name in order if name in found}


@profiling.timed("joint solve (se(3))")
def add_joint(candidates: dict[str, Candidate], samples: PairSamples, start: np.ndarray, config: PoseConfig,
               name: str = FROM_JOINT) -> None:
    """[ours] The joint solve (``PoseConfig.joint_settings``: flow plus point-to-plane) from ``start`` as the
    candidate ``name``, if it stays finite. Each term's scale is its median residual at ``start`` (at least
    the method's flow floor and a tenth of the depth noise)."""
    scales = typical_residuals(start, samples, config.joint_settings())
    if len(scales) != 2 or not np.all(np.isfinite(scales)):
        return  # no normals, or no point where both terms are defined
    flow_scale, plane_scale = scales
    settings = config.joint_settings(max(flow_scale, config.flow_floor_px), max(plane_scale, 0.1))
    joint = solve(start, samples, settings)
    if np.isfinite(joint.cost) and np.all(np.isfinite(joint.T)):
        candidates[name] = Candidate(joint.T)


def _add_icp(candidates: dict[str, Candidate], name: str, levels: ICPLevels, init: np.ndarray) -> None:
    """Point-to-plane ICP from ``init`` as the candidate ``name``, if it stays finite."""
    icp = align(levels, init)
    if np.all(np.isfinite(icp.transform)):
        candidates[name] = Candidate(icp.transform, icp.fitness, icp.inlier_rmse)


def _add_odometry(candidates: dict[str, Candidate], name: str, runs: list[tuple[np.ndarray, np.ndarray | None]],
                  color_t: np.ndarray, depth_t: np.ndarray, color_t1: np.ndarray, depth_t1: np.ndarray,
                  K: np.ndarray, config: PoseConfig) -> None:
    """RGB-D odometry from the candidate ``name`` as ``rgbd-<name>``, if it succeeds (see :func:`_run_once`)."""
    odometry = functools.partial(rgbd_odometry, color_t, depth_t, color_t1, depth_t1, K,
                                 iterations=tuple(config.rgbd_iterations), depth_diff_max=config.rgbd_depth_diff_max_m,
                                 depth_range=(config.min_depth_m, config.max_depth_m))
    refined = _run_once(runs, candidates[name].transform, odometry)
    if refined is not None and np.all(np.isfinite(refined)):
        candidates[f"{FROM_RGBD}-{name}"] = Candidate(refined)


def _run_once(runs: list[tuple[np.ndarray, np.ndarray | None]], start: np.ndarray,
              run: Callable[[np.ndarray], np.ndarray | None]) -> np.ndarray | None:
    """``run(start)``, or the result of an earlier run in ``runs`` from a start within ``SAME_START_ATOL``
    of it (ICP from the flow solve and ICP from the prior converge to one transform in most pairs)."""
    for earlier, result in runs:
        if np.abs(earlier - start).max() <= SAME_START_ATOL:
            return result
    result = run(start)
    runs.append((start, result))
    return result


def measured_flow(forward: np.ndarray, backward: np.ndarray | None) -> FlowCheck:
    """The measured flow, trusted where finite and (given the backward flow) forward-backward consistent."""
    trusted = finite_flow(forward)
    if backward is not None:
        trusted &= forward_backward_mask(forward, backward)
    return FlowCheck(forward, trusted)


def _score(transform: np.ndarray, views: tuple[FrameView, FrameView], K: np.ndarray, config: PoseConfig,
           flow_check: FlowCheck | None) -> Verification:
    """A candidate's verification; with ``flow_check`` its score also carries the candidate's disagreement
    with the measured flow (``verify_flow_weight``)."""
    found = verify(transform, *views, K, config.verify_settings())
    if flow_check is None:
        return found
    width = views[0].depth.shape[1]
    scale, stride = config.verify_flow_scale_px * width / 320.0, max(1, width // 160)
    cost = flow_disagreement(transform, views[0].depth, K, flow_check, scale, stride)
    return dataclasses.replace(found, score=found.score + config.verify_flow_weight * cost, flow=cost)


def choose(candidates: dict[str, Candidate], views: tuple[FrameView, FrameView], K: np.ndarray,
            config: PoseConfig, preference: tuple[str, ...] | None = None,
            flow_check: FlowCheck | None = None, known: dict[str, Verification] | None = None) -> RelativePose:
    """The candidate with the lowest verification score (near-ties, within ``verify_margin`` of it, go to
    the earliest in ``verify_preference``); weak if its score or overlap is poor. With ``flow_check`` each
    score also carries the candidate's disagreement with the measured flow (``verify_flow_weight``).
    ``known``: scores already computed (the same way) for some of the candidates."""
    known = known or {}
    scores = {name: known[name] if name in known else _score(c.transform, views, K, config, flow_check)
              for name, c in candidates.items()}
    name = min(scores, key=lambda n: scores[n].score)
    if np.isfinite(scores[name].score):
        tie = scores[name].score * (1.0 + config.verify_margin)
        preference = config.verify_preference if preference is None else preference
        name = next((n for n in preference if n in scores and scores[n].score <= tie), name)
    elif FROM_CONSTANT_VELOCITY in scores:
        name = FROM_CONSTANT_VELOCITY
    best, chosen = scores[name], candidates[name]
    icp = candidates.get(FROM_ICP) or candidates.get(f"{FROM_ICP}-prior")
    result = RelativePose(chosen.transform, name, score=best.score, overlap=best.overlap,
                          candidates={n: {**v.to_dict(), "transform": candidates[n].transform.tolist()}
                                      for n, v in scores.items()})
    if icp is not None:
        result.icp_fitness, result.icp_inlier_rmse_m, result.icp_transform = icp.icp_fitness, icp.icp_inlier_rmse_m, icp.transform
    if not best.score <= config.verify_max_score:
        result.weak, result.reason = True, f"best verification score {best.score:.3f} > {config.verify_max_score}"
    elif best.overlap < config.verify_min_overlap:
        result.weak, result.reason = True, f"overlap {best.overlap:.2f} < {config.verify_min_overlap}"
    return result


def icp_levels(source: o3d.geometry.PointCloud, target: o3d.geometry.PointCloud, config: PoseConfig) -> ICPLevels:
    """The config's ICP pyramid of the two clouds (``icp.prepare_icp`` with stage 1's ICP settings), shared by
    every start that is aligned on them."""
    return prepare_icp(
        source, target, voxel_sizes=tuple(s * config.icp_voxel_m for s in config.icp_scales),
        iterations=tuple(config.icp_iterations), distance_factor=config.icp_distance_factor,
        normal_radius_factor=config.icp_normal_radius_factor, normal_max_nn=config.icp_normal_max_nn,
        max_points=config.icp_max_points,
    )


@profiling.timed("flow samples")
def sample_pair(
    color_t: np.ndarray, depth_t: np.ndarray, color_t1: np.ndarray, depth_t1: np.ndarray, K: np.ndarray,
    flow: np.ndarray, backward_flow: np.ndarray | None, source_mask: np.ndarray, config: PoseConfig,
    target_normals: np.ndarray | None = None,
) -> PairSamples:
    """Up to ``max_points`` random source pixels with reliable depth and forward-backward consistent flow;
    ``target_normals``: frame t+1's :func:`joint_normals`, when known (else computed here)."""
    usable = source_mask & finite_flow(flow)
    if backward_flow is not None:
        usable &= forward_backward_mask(flow, backward_flow, config.fb_alpha, config.fb_beta)
    index = np.flatnonzero(usable)
    if len(index) > config.max_points:
        index = np.sort(np.random.default_rng(config.seed).choice(index, config.max_points, replace=False))
    v, u = np.divmod(index, depth_t.shape[1])
    z = depth_t.reshape(-1)[index].astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    gray_t = cv2.cvtColor(np.ascontiguousarray(color_t, dtype=np.float32), cv2.COLOR_RGB2GRAY)
    gray_t1 = cv2.cvtColor(np.ascontiguousarray(color_t1, dtype=np.float32), cv2.COLOR_RGB2GRAY).astype(np.float64)
    return PairSamples(
        points=points, pixels=np.stack([u, v], axis=-1).astype(np.float64),
        flow=flow.reshape(-1, 2)[index].astype(np.float64), intensity=gray_t.reshape(-1)[index].astype(np.float64),
        K=np.asarray(K, dtype=np.float64), target_gray=gray_t1, target_gradient=image_gradient(gray_t1),
        target_depth=depth_t1.astype(np.float64),
        target_normals=target_normals if target_normals is not None else joint_normals(depth_t1, K, config),
    )


@profiling.timed("depth normals")
def joint_normals(depth: np.ndarray, K: np.ndarray, config: PoseConfig) -> np.ndarray | None:
    """Unit normals of a frame's reliable depth (NaN where undefined) for the joint solve's point-to-plane term,
    None without a joint solve (``verify`` and ``joint_solve``): central differences of the depth smoothed over
    the reliable pixels (Gaussian, ``joint_normal_smooth_px`` at 320 px width), as ICP fits its normals to a
    neighbourhood rather than to single noisy samples."""
    if not (config.verify and config.joint_solve):
        return None
    mask = config.reliable_depth(depth)
    depth = np.where(mask, depth, 0.0).astype(np.float64)
    sigma = config.joint_normal_smooth_px * depth.shape[1] / 320.0
    if sigma > 0:
        weight = cv2.GaussianBlur(mask.astype(np.float64), (0, 0), sigma)
        depth = np.where(mask, cv2.GaussianBlur(depth, (0, 0), sigma) / np.maximum(weight, 1e-12), 0.0)
    return depth_normals(backproject(depth, K), mask)


def _refine_with_icp(result: RelativePose, depth_t: np.ndarray, depth_t1: np.ndarray, K: np.ndarray,
                     source_mask: np.ndarray, config: PoseConfig) -> None:
    """Replace the flow estimate by point-to-plane ICP unless ICP fits poorly or jumps away from it."""
    target_mask = config.reliable_depth(depth_t1)
    icp = align(icp_levels(depth_cloud(depth_t, K, source_mask), depth_cloud(depth_t1, K, target_mask), config),
                result.transform)
    result.icp_fitness, result.icp_inlier_rmse_m, result.icp_transform = icp.fitness, icp.inlier_rmse, icp.transform
    jump = se3_log(icp.transform @ invert(result.transform))
    jump_m, jump_deg = float(np.linalg.norm(jump[:3])), float(np.degrees(np.linalg.norm(jump[3:])))
    if not np.all(np.isfinite(icp.transform)) or icp.fitness < config.icp_min_fitness:
        result.weak, result.reason = True, f"ICP fitness {icp.fitness:.2f} < {config.icp_min_fitness}; kept the flow estimate"
    elif jump_m > config.icp_max_jump_m or jump_deg > config.icp_max_jump_deg:
        result.weak = True
        result.reason = f"ICP moved {jump_m:.3f} m / {jump_deg:.2f} deg from the flow estimate; kept the flow estimate"
    else:
        result.transform, result.estimate = icp.transform, FROM_ICP


def _refine_with_rgbd(result: RelativePose, color_t: np.ndarray, depth_t: np.ndarray, color_t1: np.ndarray,
                      depth_t1: np.ndarray, K: np.ndarray, config: PoseConfig) -> None:
    """Replace the ICP estimate by dense RGB-D odometry started from it, unless that fails or jumps away."""
    refined = rgbd_odometry(color_t, depth_t, color_t1, depth_t1, K, result.transform, tuple(config.rgbd_iterations),
                            config.rgbd_depth_diff_max_m, (config.min_depth_m, config.max_depth_m))
    if refined is None or not np.all(np.isfinite(refined)):
        return
    jump = se3_log(refined @ invert(result.transform))
    if np.linalg.norm(jump[:3]) <= config.icp_max_jump_m and np.degrees(np.linalg.norm(jump[3:])) <= config.icp_max_jump_deg:
        result.transform, result.estimate = refined, FROM_RGBD


def fallback_pose(prior: np.ndarray, reason: str, start: float) -> RelativePose:
    """``prior`` as a weak constant-velocity pair, with why and the seconds since ``start``."""
    return RelativePose(np.array(prior, dtype=np.float64), FROM_CONSTANT_VELOCITY, weak=True, reason=reason,
                        seconds=time.perf_counter() - start)

