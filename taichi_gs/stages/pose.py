"""Stage 1: local pose. Relative poses frame t -> t+1 from optical flow, colour and depth, refined by
point-to-plane ICP, chained into camera-to-world poses; all frames fused into one coloured cloud.

Outputs in OUT/pose/: ``trajectory.txt`` (TUM, camera-to-world, first frame = identity),
``points.ply`` (voxel-downsampled coloured cloud), ``pairs.json`` (per-pair diagnostics and a
summary), and ``pairs/NNNNNN.json`` (per-pair cache, so a rerun skips finished pairs; with a rolling shutter
``pairs_as_read/`` caches the pairs of the frames as read, and ``pairs/`` those of the de-skewed frames); the
pipeline adds ``config.toml``.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from .. import profiling
from ..errors import InputError
from ..flow import (DISFlow, FileFlow, FlowProvider, dis_flow, finite_flow, forward_backward_mask, rigid_flow,
                    to_gray_u8)
from ..geometry import backproject, invert, se3_log
from ..icp import (ICPLevels, align, capped_voxel_down_sample, depth_cloud, open3d, prepare_icp,
                   reliable_depth_mask, rgbd_odometry)
from ..io.atomic import write_text
from ..io import jsonout
from ..io.ply import write_point_cloud
from ..io.trajectory import write_tum
from ..machine import available_cores
from ..pose_graph import Edge, optimise, rechoose
from ..rolling_shutter import DeskewedSequence, deskewing_motions, readout_motions, stage_readout_ms
from ..pose_verify import (FlowCheck, FrameView, Verification, VerifySettings, depth_normals, flow_disagreement,
                           frame_view, verify)
from .pose_losses import PairSamples, flow_residuals, image_gradient, warp
from .declaration import StageContext, StageDeclaration, StageInputs, StageRun
from .pose_solver import SolverSettings, solve, typical_residuals

if TYPE_CHECKING:
    import open3d as o3d

    from ..io.sequence import Sequence

# What a degenerate pair may raise; anything else is a bug or bad input and ends the run.
NUMERICAL_FAILURES = (np.linalg.LinAlgError, ArithmeticError)

# Estimate kinds recorded per pair.
FROM_RGBD, FROM_ICP, FROM_FLOW, FROM_CONSTANT_VELOCITY = "rgbd", "icp", "flow", "constant-velocity"
FROM_JOINT = "joint"
# ICP starts closer than this (every entry of the 4 x 4 transform) give one RGB-D odometry run: ICP from the
# flow solve and ICP from the prior ended within 1e-9 of each other in 2862 of 3926 stored pairs
SAME_START_ATOL = 1e-9
# Names of a pair's candidates (see _candidates): what started what.
CANDIDATE_NAMES = ("rgbd-icp", "rgbd-icp-prior", "rgbd-flow", "icp", "icp-prior", "joint", "flow", "constant-velocity")


@dataclass(frozen=True)
class PoseConfig:
    """Every number of stage 1. Units: pixels, grey values in [0, 1], metres, degrees."""

    # Optical flow
    flow_dir: str = ""  # precomputed flows (see taichi_gs.flow); empty: OpenCV DIS
    flow_preset: str = "medium"  # DIS preset: ultrafast | fast | medium
    # [ours] DIS's finest pyramid level is at least this wide (0: the preset's own; see taichi_gs.flow.finest_scale)
    flow_finest_width_px: int = 320
    seeded_retry: bool = True  # weak pair: redo it with DIS seeded by the prior's flow, then by rejected ICP's
    fb_alpha: float = 0.01  # forward-backward check: |f + b|^2 < alpha (|f|^2 + |b|^2) + beta
    fb_beta: float = 0.5  # px^2
    # Pixels used by the solver
    max_points: int = 4000
    min_points: int = 150  # fewer valid pixels: the pair is weak and falls back
    min_depth_m: float = 0.1
    max_depth_m: float = 10.0
    depth_edge_ratio: float = 0.05  # drop pixels whose 3x3 depth spread exceeds this fraction of depth
    seed: int = 0
    # Loss L_F + l_I L_I + l_C L_C (phase 1: flow only; phase 2: all three)
    photometric_weight: float = 75.0
    depth_consistency_weight: float = 25.0
    flow_floor_px: float = 0.05  # IRLS: residuals below the floor are weighted as if at the floor
    photometric_floor: float = 0.002
    depth_floor_m: float = 0.0005
    min_baseline_m: float = 0.001  # shorter baselines leave L_C undefined; it is then skipped
    # Levenberg-Marquardt, per phase
    max_iterations: int = 50
    step_tolerance: float = 1e-7
    cost_tolerance: float = 1e-6
    initial_damping: float = 1e-4
    max_flow_residual_px: float = 8.0  # median flow residual above it flags the pair weak (estimate kept)
    # Point-to-plane ICP from the flow estimate
    use_icp: bool = True
    icp_voxel_m: float = 0.01  # finest ICP voxel; coarser levels are multiples of it
    icp_scales: tuple = (4.0, 2.0, 1.0)
    icp_iterations: tuple = (30, 20, 15)
    icp_distance_factor: float = 2.0  # correspondence distance = factor x voxel
    icp_normal_radius_factor: float = 3.0
    icp_normal_max_nn: int = 30
    icp_max_points: int = 20000  # finest level's cap: voxels grow until the source has no more points
    icp_min_fitness: float = 0.3  # below: keep the flow estimate, flag the pair
    icp_max_jump_m: float = 0.05  # ICP moving farther from the flow estimate: keep the flow estimate
    icp_max_jump_deg: float = 2.0
    # [ours] optional last step: Open3D dense RGB-D odometry (hybrid term) from the ICP estimate,
    # kept unless it fails or jumps farther than the ICP guards allow
    rgbd_refine: bool = True
    rgbd_iterations: tuple = (20, 10, 5)  # per pyramid level, coarse to fine
    rgbd_depth_diff_max_m: float = 0.07
    # [ours] verified candidates: every candidate pose of a pair (flow solve, ICP from it, ICP from the
    # constant-velocity prior, RGB-D odometry from each ICP result, the prior itself) is scored by
    # taichi_gs.pose_verify on both frames' depth and colour; the lowest score wins and sets "weak".
    # false: the method's path (flow solve, then ICP behind the fitness and jump guards).
    verify: bool = True
    # [ours] one more candidate, the joint solve: the flow term L_F plus a point-to-plane term L_P on frame
    # t+1's depth, in units of its noise (verify_depth_sigma_m + verify_depth_sigma_quadratic z^2), for
    # joint_iterations steps from the flow solve. Each term is measured in its own typical residual there (the
    # median; also its IRLS floor) and L_P weighs joint_plane_weight times L_F: depth pins the motion across
    # the surfaces it sees, the flow the motion along them, where ICP slides, and where depth is noisy or
    # far (its residuals large) the flow keeps more say
    joint_solve: bool = True
    joint_plane_weight: float = 16.0
    joint_iterations: int = 10
    joint_normal_smooth_px: float = 2.0
    icp_from_prior: bool = True  # also run ICP from the constant-velocity prior (a second candidate)
    verify_max_score: float = 0.5  # winner's score above it flags the pair weak
    # near-ties (within this fraction of the lowest score) go to the first candidate in this order
    verify_margin: float = 0.02
    verify_preference: tuple = ("rgbd-icp", "rgbd-icp-prior", "icp", "icp-prior", "flow", "joint", "constant-velocity")
    verify_min_overlap: float = 0.2  # winner's overlap below it flags the pair weak
    # [ours] add this x the candidate's disagreement with the pair's measured optical flow (0..1, capped at
    # verify_flow_scale_px per pixel, at 320 px width) to its score, for pairs and graph edges alike: on plain
    # walls depth and colour residuals cannot see a candidate slide along the wall, the flow can. 0: off
    verify_flow_weight: float = 0.05
    verify_flow_scale_px: float = 4.0
    verify_grid_points: int = 3000
    verify_depth_sigma_m: float = 0.003
    verify_depth_sigma_quadratic: float = 0.0025
    verify_photo_sigma: float = 0.04
    verify_photo_weight: float = 1.0
    # [ours] robust pose graph (taichi_gs.pose_graph) over the pairs (i, i+1), extra edges (i, i+k) for k in
    # graph_skips and loop closures where the chained cameras come back near an earlier one; each extra
    # edge is RGB-D odometry (and ICP with graph_icp) started from the chained poses, verified like a pair
    # and dropped when weak. false: poses are the chained pairs.
    pose_graph: bool = True
    graph_skips: tuple = (2, 3)
    graph_icp: bool = False
    # [ours] the extra edges also get a joint candidate (joint_solve's settings, from the chained poses, on the
    # edge's flows), so an edge along a plain wall is not only RGB-D odometry, which slides there. On 18
    # synthetic 60-frame sequences ATE sums 53.2 -> 45.7 mm (plain hand-held 9.5 -> 3.5, 4.9 -> 1.7; corridor
    # hand-held 3.4 -> 5.2), on eight real slices within +-0.6 mm but one (+2.0 mm, RPE rotation 0.91 -> 0.53 deg),
    # for about 1.2x stage 1's time (BENCHMARKS, "The joint candidate on the graph's edges, on by default")
    graph_joint: bool = True
    # [ours] RGB-D odometry iterations per pyramid level of the extra edges, which start from the chained
    # poses (the pairs' own odometry keeps rgbd_iterations)
    graph_rgbd_iterations: tuple = (20, 10, 5)
    graph_max_score_ratio: float = 1.5  # extra edges scoring above this x the median pair score are dropped
    graph_weak_weight: float = 0.01  # information scale of weak (i, i+1) pairs, kept to connect the graph
    graph_info_voxel_m: float = 0.02  # clouds of the information matrices (Open3D, point-to-point)
    # [ours] a frame's information cloud keeps at most this many points (0: no cap): its voxel grows by 25% steps
    # as ICP's does; noisy far depth filled 2 cm voxels several layers deep (130k points at 640x480)
    graph_info_max_points: int = 20000
    graph_info_distance_m: float = 0.04
    loop_closures: bool = True
    loop_min_gap: int = 15  # frames between the two ends of a loop edge, at least
    loop_every: int = 5  # look for a loop closure at every this-many-th frame
    loop_max_distance_m: float = 0.3  # chained camera centres closer than this ...
    loop_max_angle_deg: float = 30.0  # ... and viewing directions closer than this
    # [ours] long edges (i, i+k) for k in graph_long_spans, from every graph_long_every-th frame i, where the
    # chained cameras are as close as a loop closure's (loop_max_distance_m, loop_max_angle_deg); verified like
    # the other extra edges but not held to graph_max_score_ratio, whose 1.5x the median pair score admits almost
    # none that long. They bound the drift of long, slowly moving captures: 7-Scenes' 250 frames 35.1 -> 17.2 mm,
    # TUM fr1_rpy 14.2 -> 13.0 mm, at 1.09x the stage's time (BENCHMARKS, "Long edges from every 4th frame").
    # From every frame: four times the edges, 1.31x the time, no better on 7-Scenes. () turns them off.
    graph_long_spans: tuple = (16, 32)
    graph_long_every: int = 4
    # [ours] near-ties in the graph: a pair's candidates that score within verify_margin of its best (its
    # verification cannot tell them apart) and lie more than graph_near_tie_mm from its chosen transform are
    # offered to the graph; once it is solved, each pair's edge takes whichever of them its poses, set by the
    # skip edges, loop closures and long edges, satisfy best, and the graph is solved again
    graph_near_ties: bool = True
    graph_near_tie_mm: float = 2.0
    # [ours] a rolling shutter: the colour and depth cameras read their rows top to bottom over readout_ms
    # milliseconds. The pairs are estimated on the frames as read, each frame's motion over its readout taken
    # from them (rolling_shutter.readout_motions), every frame de-skewed to its middle row's pose
    # (rolling_shutter.DeskewedSequence), and the pairs, the graph and the fused cloud computed again on the
    # de-skewed frames: about 1.4x the stage's time. 0: a global shutter. camera_readout: with readout_ms 0, the
    # readout of a camera the sequence's reading names (rolling_shutter.KNOWN_READOUT_MS; on in the fast preset).
    # Not with precomputed flows (flow_dir), which are the frames' as read
    readout_ms: float = 0.0
    camera_readout: bool = False
    # Fused cloud
    voxel_size_m: float = 0.02  # s: the fused cloud's voxel; stage 2 gives each Gaussian scale s/2
    # [ours] threads (0: one per core this process may run on, at most DEFAULT_MAX_THREADS). The next pairs'
    # prior-free work (flow solve, ICP and RGB-D odometry from it, their verification) runs ahead while a pair
    # finishes, and the graph's edges run side by side. Results do not depend on it; under --profile stage 1
    # runs on one thread.
    threads: int = 0

    def solver_settings(self, with_all_terms: bool) -> SolverSettings:
        return SolverSettings(
            photometric_weight=self.photometric_weight if with_all_terms else 0.0,
            depth_consistency_weight=self.depth_consistency_weight if with_all_terms else 0.0,
            flow_floor_px=self.flow_floor_px, photometric_floor=self.photometric_floor,
            depth_floor_m=self.depth_floor_m, min_baseline_m=self.min_baseline_m, min_points=self.min_points,
            max_iterations=self.max_iterations, step_tolerance=self.step_tolerance,
            cost_tolerance=self.cost_tolerance, initial_damping=self.initial_damping,
        )

    def joint_settings(self, flow_scale_px: float = 1.0, plane_scale: float = 1.0) -> SolverSettings:
        """[ours] The joint solve's terms (L_F + L_P) and step cap, each term in units of its typical residual
        (``flow_scale_px``, ``plane_scale``: see :func:`_add_joint`)."""
        return dataclasses.replace(
            self.solver_settings(with_all_terms=False), max_iterations=self.joint_iterations,
            flow_floor_px=flow_scale_px, plane_floor=plane_scale,
            plane_weight=self.joint_plane_weight * flow_scale_px / plane_scale,
            plane_noise=(self.verify_depth_sigma_m, self.verify_depth_sigma_quadratic))

    def verify_settings(self) -> VerifySettings:
        return VerifySettings(
            grid_points=self.verify_grid_points, depth_sigma_m=self.verify_depth_sigma_m,
            depth_sigma_quadratic=self.verify_depth_sigma_quadratic, photo_sigma=self.verify_photo_sigma,
            photo_weight=self.verify_photo_weight, min_depth_m=self.min_depth_m, max_depth_m=self.max_depth_m,
            depth_edge_ratio=self.depth_edge_ratio,
        )

    def reliable_depth(self, depth: np.ndarray) -> np.ndarray:
        """Mask of ``depth``'s pixels that clouds and ICP may use (:func:`taichi_gs.icp.reliable_depth_mask`)."""
        return reliable_depth_mask(depth, self.min_depth_m, self.max_depth_m, self.depth_edge_ratio)

    def pair_key(self) -> str:
        """Hash of the fields that change a pair's result (not the fused cloud's voxel size nor the graph's)."""
        values = {k: v for k, v in dataclasses.asdict(self).items() if k not in _NOT_PAIR_FIELDS}
        return hashlib.sha1(json.dumps(values, sort_keys=True, default=list).encode()).hexdigest()[:16]


# Fields that do not change a pair's own result (excluded from the pair cache's key).
_NOT_PAIR_FIELDS = {"voxel_size_m", "readout_ms", "camera_readout", "pose_graph", "graph_skips", "graph_icp", "graph_joint",
                    "graph_rgbd_iterations", "graph_max_score_ratio", "graph_weak_weight", "graph_info_voxel_m",
                    "graph_info_max_points",
                    "graph_info_distance_m", "loop_closures", "loop_min_gap", "loop_every", "loop_max_distance_m",
                    "loop_max_angle_deg", "graph_long_spans", "graph_long_every", "graph_near_ties",
                    "graph_near_tie_mm", "threads"}

# The method's path alone: flow solve, then point-to-plane ICP behind its guards, pairs chained
# (as a --config file: [pose] verify = false, rgbd_refine = false, icp_from_prior = false, pose_graph = false,
# icp_max_points = 80000, flow_finest_width_px = 0).
METHOD_ONLY = PoseConfig(verify=False, rgbd_refine=False, icp_from_prior=False, pose_graph=False, icp_max_points=80000,
                         flow_finest_width_px=0)

# fast: ICP on at most icp_max_points points per frame, known cameras' rolling shutters; paper: on every point.
PRESETS = {"fast": PoseConfig(camera_readout=True), "paper": PoseConfig(icp_max_points=0)}


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
            "flow_residual_px": _finite_or_none(self.flow_residual_px), "points": self.points,
            "iterations": list(self.iterations), "icp_fitness": _finite_or_none(self.icp_fitness),
            "icp_inlier_rmse_m": _finite_or_none(self.icp_inlier_rmse_m), "seconds": round(self.seconds, 4),
            "score": _finite_or_none(self.score), "overlap": _finite_or_none(self.overlap), "candidates": self.candidates,
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


@dataclass
class PoseResult:
    """Camera-to-world poses (N x 4 x 4), per-pair records (as in pairs.json) and the files written."""

    poses: np.ndarray
    pairs: list[dict]
    paths: dict[str, Path] = field(default_factory=dict)
    edges: list[dict] = field(default_factory=list)  # pose-graph edges (empty without the graph)
    graph_seconds: float = 0.0  # extra edges and optimisation
    rolling_shutter: dict | None = None  # readout_ms and skew_px of de-skewed frames (None: as read)
    pairs_as_read_seconds: float = 0.0  # with a rolling shutter: the pairs of the frames as read, all together

    def summary(self) -> str:
        weak = sum(1 for p in self.pairs if p["weak"])
        fallback = sum(1 for p in self.pairs if p["estimate"] == FROM_CONSTANT_VELOCITY)
        text = f"{len(self.pairs)} pairs, {weak} weak ({fallback} replaced by constant velocity)"
        if self.edges:
            loops = sum(e["kind"] == "loop" for e in self.edges)
            pruned = sum(e["pruned"] for e in self.edges)
            rechosen = sum(e["kind"] == "odometry" and e["estimate"] != self.pairs[e["source"]]["estimate"]
                           for e in self.edges)
            text += f"; pose graph: {len(self.edges)} edges ({loops} loop closures), {pruned} pruned"
            text += f", {rechosen} pairs re-chosen among near-ties" if rechosen else ""
        if self.rolling_shutter:
            text += (f"; frames de-skewed for a rolling shutter of {self.rolling_shutter['readout_ms']:g} ms (rows up "
                     f"to {self.rolling_shutter['skew_px']:.1f} px from their frame's pose)")
        return text


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
    and the lowest score wins (see :func:`_choose`); otherwise ICP replaces the flow estimate unless it
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
            ahead.flow_check = _flow_check(flow, backward_flow)
        if config.use_icp:
            target_mask = config.reliable_depth(depth_t1)
            ahead.levels = icp_levels(depth_cloud(depth_t, K, source_mask), depth_cloud(depth_t1, K, target_mask),
                                      config)
        if flow_T is not None:
            ahead.candidates[FROM_FLOW] = Candidate(flow_T)
            if config.joint_solve:
                _add_joint(ahead.candidates, samples, flow_T, config)
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
        return _fallback(prior, ahead.reason, started)
    if views is None:
        result = RelativePose(flow_T, FROM_FLOW, flow_transform=flow_T, points=len(samples.points),
                              iterations=ahead.iterations)
        if config.use_icp:
            _refine_with_icp(result, depth_t, depth_t1, K, ahead.source_mask, config)
        if config.rgbd_refine and result.estimate == FROM_ICP:
            _refine_with_rgbd(result, color_t, depth_t, color_t1, depth_t1, K, config)
    else:
        candidates = _candidates(ahead, color_t, depth_t, color_t1, depth_t1, K, prior, config)
        result = _choose(candidates, views, K, config, flow_check=ahead.flow_check, known=ahead.scores)
        result.flow_transform, result.points, result.iterations = flow_T, len(samples.points), ahead.iterations
        if flow_T is None:
            result.reason = "; ".join(filter(None, [ahead.reason, result.reason]))
    final = warp(result.transform, samples)
    if final.valid.sum() > 0:
        result.flow_residual_px = float(np.median(flow_residuals(final, samples).norms()[final.valid]))
    if views is None and not result.weak and not result.flow_residual_px <= config.max_flow_residual_px:
        result.weak, result.reason = True, f"median flow residual {result.flow_residual_px:.2f} px"
    return result


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


def _add_joint(candidates: dict[str, Candidate], samples: PairSamples, start: np.ndarray, config: PoseConfig,
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


def _flow_check(forward: np.ndarray, backward: np.ndarray | None) -> FlowCheck:
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


def _choose(candidates: dict[str, Candidate], views: tuple[FrameView, FrameView], K: np.ndarray,
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


def _fallback(prior: np.ndarray, reason: str, start: float) -> RelativePose:
    return RelativePose(np.array(prior, dtype=np.float64), FROM_CONSTANT_VELOCITY, weak=True, reason=reason,
                        seconds=time.perf_counter() - start)


def _finite_or_none(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def chain_poses(relatives: list[np.ndarray]) -> np.ndarray:
    """Camera-to-world poses from transforms camera t -> t+1; the first camera is the world frame."""
    poses = [np.eye(4)]
    for T in relatives:
        poses.append(poses[-1] @ invert(T))
    return np.stack(poses)


def fuse_points(sequence, poses: np.ndarray, config: PoseConfig,
                on_frame: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World points and colours of all frames' reliable depth, voxel-downsampled to ``voxel_size_m``;
    ``on_frame(done)`` after each frame."""
    K = sequence.intrinsics.K()
    fused = open3d().geometry.PointCloud()
    for i, pose in enumerate(poses):
        depth = sequence.depth(i)
        mask = config.reliable_depth(depth)
        cloud = depth_cloud(depth, K, mask, sequence.color(i)).transform(pose)
        fused += cloud.voxel_down_sample(config.voxel_size_m)
        fused = fused.voxel_down_sample(config.voxel_size_m)
        if on_frame is not None:
            on_frame(i + 1)
    return np.asarray(fused.points), np.asarray(fused.colors)


def flow_provider(sequence, config: PoseConfig, frames: FrameCache) -> FlowProvider:
    """Precomputed flows when ``flow_dir`` is set (checked now), else DIS on ``frames``' grey frames."""
    if config.flow_dir:
        provider = FileFlow(config.flow_dir, list(sequence.names))
        provider.check()
        return provider
    return DISFlow(frames.gray, config.flow_preset, config.flow_finest_width_px)


class FrameCache:
    """A sequence's frames and what pairs and the pose graph derive from them (grey frames for optical flow,
    verification views, information clouds, the joint solve's normals), each read or computed once while among
    the ``keep`` frames used last: pairs and graph edges visit frames in windows. Safe to share between threads."""

    def __init__(self, sequence, K: np.ndarray, config: PoseConfig, keep: int = 16):
        settings = config.verify_settings()
        self.color = _Recent(lambda i: _read_only(sequence.color(i)), keep)
        self.depth = _Recent(lambda i: _read_only(sequence.depth(i)), keep)
        self.gray = _Recent(lambda i: _read_only(to_gray_u8(self.color(i))), keep)
        self.view = _Recent(lambda i: frame_view(self.color(i), self.depth(i), K, settings), keep)
        self.info_cloud = _Recent(lambda i: _information_cloud(self.depth(i), K, config), keep)
        self.normals = _Recent(lambda i: joint_normals(self.depth(i), K, config), keep)


class _Recent:
    """``compute(key)`` for the ``keep`` keys used last, each computed once even when several threads ask for
    it at the same time (the later ones wait for the first)."""

    def __init__(self, compute: Callable[[int], Any], keep: int):
        self.compute, self.keep = compute, keep
        self.results: OrderedDict[int, Future] = OrderedDict()
        self.lock = threading.Lock()

    def __call__(self, key: int) -> Any:
        with self.lock:
            result = self.results.get(key)
            mine = result is None
            if mine:
                result = self.results[key] = Future()
            self.results.move_to_end(key)
            while len(self.results) > self.keep:
                self.results.popitem(last=False)
        if mine:
            try:
                result.set_result(self.compute(key))
            except BaseException as error:
                result.set_exception(error)
                with self.lock:
                    if self.results.get(key) is result:
                        del self.results[key]  # not cached: the next call tries again
        return result.result()


def _read_only(image: np.ndarray) -> np.ndarray:
    """A read-only view of ``image`` (the sequence's own array keeps its flags): a cached frame is shared
    by every pair and edge that uses it."""
    view = image.view()
    view.flags.writeable = False
    return view


def _information_cloud(depth: np.ndarray, K: np.ndarray, config: PoseConfig) -> o3d.geometry.PointCloud:
    """A frame's reliable depth as a cloud at the information matrices' voxel size (grown to keep at most
    ``graph_info_max_points`` points)."""
    cloud = depth_cloud(depth, K, config.reliable_depth(depth))
    return capped_voxel_down_sample(cloud, config.graph_info_voxel_m, config.graph_info_max_points)[0]


def run_pose(sequence, out_dir: Path, config: PoseConfig = PoseConfig(),
             progress: Callable[[int, int, str], None] | None = None) -> PoseResult:
    """Stage 1 over a whole sequence, resuming from cached pairs; writes OUT/pose/ (see module doc).
    ``progress(done, total, step)`` counts the pairs (first "pairs as read" with a rolling shutter), then the
    pose graph's frames, then the frames fused into the cloud (``step``: "pairs", "graph", "fused cloud")."""
    n = len(sequence)
    if n < 2:
        raise InputError(getattr(sequence, "root", None), f"sequence has {n} frame(s)", "give at least two frames")
    pose_dir = Path(out_dir) / "pose"
    K = sequence.intrinsics.K()
    key = config.pair_key()
    readout_ms = pose_readout_ms(sequence, config)
    steps = progress_steps(n, config, readout_ms)

    def progress_of(kind: str, offset: int) -> Callable[[int], None]:
        return (lambda done: progress(offset + done, steps, kind)) if progress is not None else (lambda done: None)

    shutter: dict | None = None
    as_read_seconds = 0.0
    with _workers(stage_threads(config)) as pool:
        if readout_ms > 0:  # [ours] the pairs as read give each frame's motion over its readout; de-skew, redo
            as_read = _pair_estimates(sequence, FrameCache(sequence, K, config), pose_dir / "pairs_as_read", key,
                                      config, pool, progress_of("pairs as read", 0))
            motions, skew_px = deskewing_motions(sequence, readout_motions(
                chain_poses([r.transform for r in as_read]), sequence.timestamps, readout_ms / 1000.0))
            sequence = DeskewedSequence(sequence, motions)
            key = _deskewed_pair_key(key, readout_ms, motions)
            shutter = {"readout_ms": readout_ms, "skew_px": round(skew_px, 3)}
            as_read_seconds = sum(r.seconds for r in as_read)
        frames = FrameCache(sequence, K, config)
        offset = n - 1 if readout_ms > 0 else 0
        relatives = _pair_estimates(sequence, frames, pose_dir / "pairs", key, config, pool,
                                    progress_of("pairs", offset))
        poses = chain_poses([r.transform for r in relatives])
        pairs = [_pair_record(k, sequence.names, r) for k, r in enumerate(relatives)]
        edges: list[Edge] = []
        graph_start = time.perf_counter()
        if config.pose_graph:
            poses, edges = refine_with_graph(sequence, relatives, poses, config, frames, pool,
                                             on_frame=progress_of("graph", offset + n - 1))
    result = PoseResult(poses, pairs, edges=[_edge_record(e) for e in edges],
                        graph_seconds=time.perf_counter() - graph_start, rolling_shutter=shutter,
                        pairs_as_read_seconds=as_read_seconds)
    paths = {"trajectory": pose_dir / "trajectory.txt", "points": pose_dir / "points.ply", "pairs": pose_dir / "pairs.json"}
    write_tum(paths["trajectory"], np.asarray(sequence.timestamps), poses, header="taichi-gs stage 1, camera-to-world")
    record = {"summary": result.summary(), "pairs": pairs, "edges": result.edges}
    if shutter is not None:
        record["rolling_shutter"] = shutter
    write_text(paths["pairs"], jsonout.dumps(record, indent=1) + "\n")
    points, colors = fuse_points(sequence, poses, config, on_frame=progress_of("fused cloud", steps - n))
    write_point_cloud(paths["points"], points, colors)
    result.paths = paths
    return result


def _pair_estimates(sequence, frames: FrameCache, pair_dir: Path, key: str, config: PoseConfig, pool: Executor,
                    on_pair: Callable[[int], None]) -> list[RelativePose]:
    """Every pair (k, k+1) of ``frames``, each read from ``pair_dir`` when cached there under ``key``, else
    estimated (the workers start the next pairs while this thread finishes one) and cached."""
    pair_dir.mkdir(parents=True, exist_ok=True)
    K = sequence.intrinsics.K()
    cached = [_load_pair(pair_dir / f"{k:06d}.json", key) for k in range(len(sequence) - 1)]
    threads = stage_threads(config)
    started = _run_ahead(pool, [k for k, r in enumerate(cached) if r is None],
                         functools.partial(_start_pair_of, frames, flow_provider(sequence, config, frames), K, config),
                         ahead=2 * threads if threads > 1 else 0)
    relatives: list[RelativePose] = []
    last = time.perf_counter()
    for k, relative in enumerate(cached):
        if relative is None:
            prior = relatives[-1].transform if relatives else np.eye(4)
            relative = _estimate_pair(frames, k, K, config, prior, next(started))
            relative.seconds = time.perf_counter() - last  # the wall time it added, its work ahead overlapped
            write_text(pair_dir / f"{k:06d}.json", jsonout.dumps({"config_key": key, **relative.to_dict()}) + "\n")
        relatives.append(relative)
        on_pair(k + 1)
        last = time.perf_counter()
    return relatives


def pose_readout_ms(sequence, config: PoseConfig) -> float:
    """Stage 1's rolling-shutter readout (ms) for ``sequence`` (:func:`rolling_shutter.stage_readout_ms`); 0 with
    precomputed flows (``flow_dir``), which are the frames' as read, and an input error if a readout is asked
    for with them."""
    if config.flow_dir:
        if config.readout_ms > 0:
            raise InputError(Path(config.flow_dir), "precomputed flows are of the frames as read, and a rolling "
                             "shutter's readout de-skews the frames", "give --readout-ms 0, or leave out --flow-dir")
        return 0.0
    return stage_readout_ms(config.readout_ms, config.camera_readout, getattr(sequence, "source", {}))


def _deskewed_pair_key(key: str, readout_ms: float, motions: np.ndarray) -> str:
    """The cache key of pairs on de-skewed frames: the pairs' own ``key``, the readout and its motions."""
    text = json.dumps({"key": key, "readout_ms": readout_ms, "motions": np.round(motions, 9).tolist()})
    return hashlib.sha1(text.encode()).hexdigest()[:16]


def refine_with_graph(sequence, relatives: list[RelativePose], chained: np.ndarray, config: PoseConfig,
                      frames: FrameCache, pool: Executor | None = None,
                      on_frame: Callable[[int], None] | None = None) -> tuple[np.ndarray, list[Edge]]:
    """[ours] Poses from a robust pose graph over the pairs, skip edges, loop closures and long edges, solved
    again once each pair's edge has been re-chosen among its near-tied candidates (see PoseConfig);
    ``frames``: the run's per-frame cache, shared with the pairs; ``pool``: where the edges run (side by
    side on a thread pool; default: one after another); ``on_frame(done)`` after each frame's edges."""
    K = sequence.intrinsics.K()
    n = len(sequence)
    scores = [r.score for r in relatives if np.isfinite(r.score)]
    max_score = config.graph_max_score_ratio * float(np.median(scores)) if scores else config.verify_max_score
    skips, longs = [int(k) for k in config.graph_skips], [int(k) for k in config.graph_long_spans]
    close = set(_long_candidates(chained, config))

    def frame_edges(i: int) -> tuple[Edge, list[Edge | None], list[Edge | None], list[Edge]]:
        r = relatives[i]
        odometry = _pair_edge(frames, i, r.transform, r.estimate, r.score, r.weak, config)
        skip = [_graph_edge(frames, i, i + k, chained, K, config, "skip", max_score) if i + k < n else None
                for k in skips]
        long = [_graph_edge(frames, i, i + k, chained, K, config, "long", float("inf")) if (i, i + k) in close else None
                for k in longs]
        ties = _near_tie_edges(i, r, frames, config) if config.graph_near_ties else []
        return odometry, skip, long, ties

    def loop_edge(pair: tuple[int, int]) -> Edge | None:
        return _graph_edge(frames, *pair, chained, K, config, "loop", max_score)

    # one pass from the last frame down, so that the frame cache's window slides once and starts on the frames
    # the pairs left in it (frame by frame and gap by gap, each frame's view was made three times); the edges
    # are listed as before: odometry, then each gap's skip edges, by frame
    pool = pool or _Inline()
    by_frame = []
    for found in pool.map(frame_edges, reversed(range(n - 1))):
        by_frame.append(found)
        if on_frame is not None:
            on_frame(len(by_frame))
    by_frame.reverse()
    edges = [odometry for odometry, _, _, _ in by_frame]
    for g in range(len(skips)):
        edges += [skip[g] for _, skip, _, _ in by_frame if skip[g] is not None]
    if config.loop_closures:
        edges += [e for e in pool.map(loop_edge, _loop_candidates(chained, config)) if e is not None]
    for g in range(len(longs)):  # each frame's long edges ran with its other edges (the progress counts them)
        edges += [long[g] for _, _, long, _ in by_frame if long[g] is not None]
    poses = optimise(chained, edges)
    near_ties = {k: ties for k, (_, _, _, ties) in enumerate(by_frame) if ties}  # edges[k]: pair k's edge
    if rechoose(edges, poses, near_ties):
        poses = optimise(chained, edges)
    return poses, edges


def _pair_edge(frames: FrameCache, i: int, transform: np.ndarray, estimate: str, score: float, weak: bool,
               config: PoseConfig) -> Edge:
    """The graph's edge camera i -> camera i + 1 for a pair's transform; a weak pair's information is scaled by
    ``graph_weak_weight`` (kept only to connect the graph)."""
    info = _information(frames, i, i + 1, transform, config) * (config.graph_weak_weight if weak else 1.0)
    return Edge(i, i + 1, transform, info, "odometry", estimate, score, weak)


def _near_tie_edges(i: int, relative: RelativePose, frames: FrameCache, config: PoseConfig) -> list[Edge]:
    """[ours] Pair i's other candidates that scored within ``verify_margin`` of its best (the constant-velocity
    guess aside) and lie more than ``graph_near_tie_mm`` from its chosen transform and from each other, as edges
    like the pair's own (``graph_near_ties``; :func:`taichi_gs.pose_graph.rechoose` picks among them)."""
    scores = {name: c["score"] for name, c in relative.candidates.items()
              if c.get("score") is not None and "transform" in c}
    if not scores:
        return []
    tie = min(scores.values()) * (1.0 + config.verify_margin)
    kept, found = [relative.transform], []
    for name, score in scores.items():
        if name == FROM_CONSTANT_VELOCITY or score > tie:
            continue
        transform = np.asarray(relative.candidates[name]["transform"], dtype=np.float64)
        if min(np.linalg.norm(transform[:3, 3] - other[:3, 3]) for other in kept) <= config.graph_near_tie_mm / 1000.0:
            continue
        kept.append(transform)
        found.append(_pair_edge(frames, i, transform, name, score, relative.weak, config))
    return found


def _graph_edge(frames: FrameCache, i: int, j: int, poses: np.ndarray, K: np.ndarray, config: PoseConfig,
                kind: str, max_score: float) -> Edge | None:
    """A verified edge camera i -> camera j started from the current poses, or None when it is weak, scores
    above ``max_score`` or is no better than the poses it started from."""
    init = invert(poses[j]) @ poses[i]
    color_i, depth_i, color_j, depth_j = frames.color(i), frames.depth(i), frames.color(j), frames.depth(j)
    candidates = {"chain": Candidate(init)}
    if config.graph_icp:
        mask_i = config.reliable_depth(depth_i)
        mask_j = config.reliable_depth(depth_j)
        icp = align(icp_levels(depth_cloud(depth_i, K, mask_i), depth_cloud(depth_j, K, mask_j), config), init)
        if np.all(np.isfinite(icp.transform)):
            candidates["icp-chain"] = Candidate(icp.transform, icp.fitness, icp.inlier_rmse)
    for name in list(candidates):
        refined = rgbd_odometry(color_i, depth_i, color_j, depth_j, K, candidates[name].transform,
                                tuple(config.graph_rgbd_iterations), config.rgbd_depth_diff_max_m,
                                (config.min_depth_m, config.max_depth_m))
        if refined is not None and np.all(np.isfinite(refined)):
            candidates[f"rgbd-{name}"] = Candidate(refined)
    views = (frames.view(i), frames.view(j))
    check = None
    if config.verify_flow_weight > 0 or config.graph_joint:
        flows = seeded_flows(frames.gray(i), frames.gray(j), depth_i, depth_j, K, init, config)
        check = _flow_check(*flows) if config.verify_flow_weight > 0 else None
        if config.graph_joint:
            samples = sample_pair(color_i, depth_i, color_j, depth_j, K, *flows, config.reliable_depth(depth_i), config,
                                  frames.normals(j))
            _add_joint(candidates, samples, init, config, name=f"{FROM_JOINT}-chain")
    chosen = _choose(candidates, views, K, config,
                     ("rgbd-icp-chain", "rgbd-chain", "icp-chain", f"{FROM_JOINT}-chain", "chain"), flow_check=check)
    if chosen.weak or chosen.estimate == "chain" or not chosen.score <= max_score:
        return None
    return Edge(i, j, chosen.transform, _information(frames, i, j, chosen.transform, config), kind,
                chosen.estimate, chosen.score)


def _close(a: np.ndarray, b: np.ndarray, config: PoseConfig) -> np.ndarray:
    """Whether cameras ``a`` and ``b`` (4 x 4 poses, or stacks of them that broadcast) are as close as a loop
    closure's: centres within loop_max_distance_m and viewing directions within loop_max_angle_deg."""
    distance = np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)
    cos = np.clip(np.sum(a[..., :3, 2] * b[..., :3, 2], axis=-1), -1.0, 1.0)
    return (distance <= config.loop_max_distance_m) & (np.degrees(np.arccos(cos)) <= config.loop_max_angle_deg)


def _long_candidates(poses: np.ndarray, config: PoseConfig) -> list[tuple[int, int]]:
    """(i, i + k) for every span k in graph_long_spans and every graph_long_every-th frame i whose chained
    cameras are close (:func:`_close`)."""
    every = config.graph_long_every  # at least 1: validation.FIELD_RULES
    return [(int(i), int(i) + k) for k in config.graph_long_spans if k < len(poses)
            for i in np.flatnonzero(_close(poses[:len(poses) - k:every], poses[k::every], config)) * every]


def _loop_candidates(poses: np.ndarray, config: PoseConfig) -> list[tuple[int, int]]:
    """(i, j) pairs, j - i >= loop_min_gap, whose chained cameras are close in position and direction:
    for every loop_every-th frame j, the nearest such earlier frame i (the last of equally near ones)."""
    pairs = []
    for j in range(config.loop_min_gap, len(poses), max(config.loop_every, 1)):
        earlier = poses[:j - config.loop_min_gap + 1]
        distance = np.where(_close(earlier, poses[j], config),
                            np.linalg.norm(earlier[:, :3, 3] - poses[j, :3, 3], axis=1), np.inf)
        if np.isfinite(distance).any():
            pairs.append((int(np.flatnonzero(distance == distance.min())[-1]), j))
    return pairs


def _information(frames: FrameCache, i: int, j: int, T: np.ndarray, config: PoseConfig) -> np.ndarray:
    """Open3D's point-to-point information matrix of the edge i -> j, reordered to [translation, rotation]."""
    info = np.asarray(open3d().pipelines.registration.get_information_matrix_from_point_clouds(
        frames.info_cloud(i), frames.info_cloud(j), config.graph_info_distance_m, T))
    order = [3, 4, 5, 0, 1, 2]
    info = info[np.ix_(order, order)]
    return info + 1e-6 * np.trace(info) * np.eye(6) if np.trace(info) > 0 else np.eye(6) * 1e-6


def _edge_record(edge: Edge) -> dict:
    return {"source": edge.source, "target": edge.target, "kind": edge.kind, "estimate": edge.estimate,
            "score": _finite_or_none(edge.score), "weak": edge.weak, "weight": round(edge.weight, 5), "pruned": edge.pruned}


def _start_pair_of(frames: FrameCache, provider: FlowProvider, K: np.ndarray, config: PoseConfig, k: int) -> PairStart:
    """Pair k's :func:`start_pair` on the provider's flows (run ahead, on a worker thread when there are several)."""
    views = (frames.view(k), frames.view(k + 1)) if config.verify else None
    return start_pair(frames.color(k), frames.depth(k), frames.color(k + 1), frames.depth(k + 1), K,
                      provider.flow(k, k + 1), provider.flow(k + 1, k), config, views, frames.normals(k + 1))


def _estimate_pair(frames: FrameCache, k: int, K: np.ndarray, config: PoseConfig, prior: np.ndarray,
                   started: Future) -> RelativePose:
    """Pair k from its started part (a future of :func:`_start_pair_of`); numerical trouble (a singular
    system, an overflow) makes it a weak constant-velocity pair, recorded with its reason. Input and
    programming errors are not caught: they end the run."""
    start = time.perf_counter()
    try:
        return estimate_relative_pose(frames.color(k), frames.depth(k), frames.color(k + 1), frames.depth(k + 1),
                                      K, config=config, prior=prior, ahead=started.result(),
                                      views=(frames.view(k), frames.view(k + 1)) if config.verify else None)
    except NUMERICAL_FAILURES as err:  # one degenerate pair must not end the run; the reason is recorded
        return _fallback(prior, f"{type(err).__name__}: {err}", start)


# The most threads stage 1 takes by default: the pairs finish one after another on one thread, which bounds what
# more workers can start ahead, and each Open3D call runs its own threads (measured on 2 cores only)
DEFAULT_MAX_THREADS = 4


def stage_threads(config: PoseConfig) -> int:
    """Threads stage 1 runs on: ``config.threads``, 0 meaning one per available core up to
    :data:`DEFAULT_MAX_THREADS`; one under --profile, whose sections are timed on one thread (the results are
    the same)."""
    if profiling.installed():
        return 1
    return config.threads or min(available_cores(), DEFAULT_MAX_THREADS)


class _Inline(Executor):
    """An executor that runs each task in the caller's thread when it is submitted."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as error:  # re-raised by future.result(), where a pool would raise it
            future.set_exception(error)
        return future


@contextmanager
def _workers(threads: int) -> Iterator[Executor]:
    """A pool of ``threads`` worker threads, or the caller's thread alone for one; waiting tasks are cancelled
    on the way out."""
    pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="pose") if threads > 1 else _Inline()
    try:
        yield pool
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_ahead(pool: Executor, keys: list[int], task: Callable[[int], PairStart], ahead: int) -> Iterator[Future]:
    """Futures of ``task(key)`` in the order of ``keys``; when one is taken, the tasks of the next ``ahead``
    keys are submitted too, so that the pool runs ahead of the caller by that many keys at most."""
    futures: dict[int, Future] = {}
    for i, key in enumerate(keys):
        for upcoming in keys[i:i + ahead + 1]:
            if upcoming not in futures:
                futures[upcoming] = pool.submit(task, upcoming)
        yield futures.pop(key)


def _load_pair(path: Path, key: str) -> RelativePose | None:
    """A cached pair computed with the same settings, or None."""
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        return RelativePose.from_dict(data) if data.get("config_key") == key else None
    except (ValueError, KeyError, TypeError):
        return None


def _pair_record(k: int, names: list[str], r: RelativePose) -> dict:
    record = {"index": k, "source": names[k], "target": names[k + 1]}
    record.update({key: value for key, value in r.to_dict().items() if key != "flow_transform"})
    return record


def progress_steps(frames: int, config: PoseConfig, readout_ms: float = 0.0) -> int:
    """Stage 1's progress steps: the pairs (twice with a rolling shutter's ``readout_ms``), the pose graph's
    frames (with ``pose_graph``), the fused frames."""
    return (frames - 1) * ((2 if config.pose_graph else 1) + (1 if readout_ms > 0 else 0)) + frames


MAX_PAIR_WARNINGS = 5  # weak pairs named one by one on the console; pairs.json lists them all


def weak_pair_warnings(sequence: Sequence, pairs: list[dict], config: PoseConfig) -> list[str]:
    """One line per frame of a weak pair whose depth has fewer usable pixels than a pair needs (naming its depth
    file), then one per other weak pair (at most :data:`MAX_PAIR_WARNINGS`, and a count of the rest)."""
    weak = [p for p in pairs if p.get("weak")]
    frames = sorted({p["index"] for p in weak} | {p["index"] + 1 for p in weak})
    depthless = {}
    for i in frames:
        usable = int(np.count_nonzero(config.reliable_depth(sequence.depth(i))))
        if usable < config.min_points:
            depthless[i] = usable
    lines = [f"{sequence.depth_paths[i]}: {usable} pixels of usable depth ({config.min_depth_m:g}-"
             f"{config.max_depth_m:g} m), fewer than a pair needs ({config.min_points}); frame {sequence.names[i]}'s "
             f"pose comes from its neighbours; check the depth file" for i, usable in depthless.items()]
    others = [p for p in weak if p["index"] not in depthless and p["index"] + 1 not in depthless]
    for p in others[:MAX_PAIR_WARNINGS]:
        held = ("the constant-velocity guess" if p["estimate"] == FROM_CONSTANT_VELOCITY
                else f"the {p['estimate']} estimate")
        fate = (f"its edge ({held}) is weighted down in the pose graph" if config.pose_graph
                else f"the trajectory keeps {held}")
        lines.append(f"weak pair {p['source']} -> {p['target']} ({p['reason'] or 'no reason recorded'}); {fate}")
    if len(others) > MAX_PAIR_WARNINGS:
        lines.append(f"{len(others) - MAX_PAIR_WARNINGS} more weak pairs: see pose/pairs.json")
    return lines


def _run_stage(context: StageContext) -> StageRun:
    pairs = len(context.sequence) - 1
    steps = progress_steps(len(context.sequence), context.config, pose_readout_ms(context.sequence, context.config))
    with context.progress(STAGE.title, steps) as update:
        result = run_pose(context.sequence, context.out, context.config,
                          progress=lambda done, total, kind: update(done, total, step=kind))
    weak = sum(1 for p in result.pairs if p.get("weak"))
    shutter = result.rolling_shutter
    deskewed = (f"; frames de-skewed for a rolling shutter of {shutter['readout_ms']:g} ms (rows up to "
                f"{shutter['skew_px']:.1f} px from their frame's pose)") if shutter else ""
    return StageRun(f"{pairs} pairs, {weak} weak{deskewed}",
                    weak_pair_warnings(context.sequence, result.pairs, context.config))


def _stage_inputs(out: Path, config: PoseConfig, poses: Path | None, points: Path | None) -> StageInputs:
    return StageInputs(folders=[Path(config.flow_dir)] if config.flow_dir else [])


STAGE = StageDeclaration(
    name="pose", title="stage 1: pose", config_type=PoseConfig, presets=PRESETS,
    outputs=("trajectory.txt", "points.ply", "pairs.json"), run=_run_stage, inputs=_stage_inputs,
)
