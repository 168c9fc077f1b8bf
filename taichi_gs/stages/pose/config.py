"""Stage 1's settings: every number of the pose stage, its presets, and the method-only path."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from ...validation import (
    ANY,
    COUNT,
    FRACTION,
    FRAME_GAPS,
    NON_NEGATIVE,
    OPTIONAL_COUNT,
    POSITIVE,
    Rule,
    at_least,
    each,
    one_of,
    setting,
    within,
)
from .flow import DIS_PRESETS
from .icp import reliable_depth_mask
from .solver import SolverSettings
from .verify import VerifySettings

# Names of a pair's candidates (stages/pose/pair.py's _candidates: what started what), and verify_preference's rule.
CANDIDATE_NAMES = ("rgbd-icp", "rgbd-icp-prior", "rgbd-flow", "icp", "icp-prior", "joint", "flow", "constant-velocity")
CANDIDATE_LIST = Rule((lambda v: len(v) > 0 and set(v) <= set(CANDIDATE_NAMES)),
                      "a non-empty list of " + ", ".join(CANDIDATE_NAMES))


@dataclass(frozen=True)
class PoseConfig:
    """Every number of stage 1. Units: pixels, grey values in [0, 1], metres, degrees."""

    RELATIONS: ClassVar[tuple[tuple[str, Callable[[Any], bool]], ...]] = (
        ("min_depth_m must be below max_depth_m", lambda c: c.min_depth_m < c.max_depth_m),
        ("min_points must not exceed max_points", lambda c: c.min_points <= c.max_points),
        ("icp_scales and icp_iterations need one entry per ICP level",
         lambda c: len(c.icp_scales) == len(c.icp_iterations)),
    )

    # Optical flow
    flow_dir: str = setting("", ANY)  # precomputed flows (see taichi_gs.stages.pose.flow); empty: OpenCV DIS
    flow_preset: str = setting("medium", one_of(*DIS_PRESETS))  # DIS preset: ultrafast | fast | medium
    # [ours] DIS's finest pyramid level is at least this wide (0: the preset's own; see taichi_gs.stages.pose.flow.finest_scale)
    flow_finest_width_px: int = setting(320, OPTIONAL_COUNT)
    seeded_retry: bool = True  # weak pair: redo it with DIS seeded by the prior's flow, then by rejected ICP's
    fb_alpha: float = setting(0.01, NON_NEGATIVE)  # forward-backward check: |f + b|^2 < alpha (|f|^2 + |b|^2) + beta
    fb_beta: float = setting(0.5, NON_NEGATIVE)  # px^2
    # Pixels used by the solver
    max_points: int = setting(4000, COUNT)
    min_points: int = setting(150, at_least(6))  # fewer valid pixels: the pair is weak and falls back
    min_depth_m: float = setting(0.1, POSITIVE)
    max_depth_m: float = setting(10.0, POSITIVE)
    # drop pixels whose 3x3 depth spread exceeds this fraction of depth
    depth_edge_ratio: float = setting(0.05, NON_NEGATIVE)
    seed: int = setting(0, ANY)
    # Loss L_F + l_I L_I + l_C L_C (phase 1: flow only; phase 2: all three)
    photometric_weight: float = setting(75.0, NON_NEGATIVE)
    depth_consistency_weight: float = setting(25.0, NON_NEGATIVE)
    flow_floor_px: float = setting(0.05, POSITIVE)  # IRLS: residuals below the floor are weighted as if at the floor
    photometric_floor: float = setting(0.002, POSITIVE)
    depth_floor_m: float = setting(0.0005, POSITIVE)
    min_baseline_m: float = setting(0.001, NON_NEGATIVE)  # shorter baselines leave L_C undefined; it is then skipped
    # Levenberg-Marquardt, per phase
    max_iterations: int = setting(50, COUNT)
    step_tolerance: float = setting(1e-7, POSITIVE)
    cost_tolerance: float = setting(1e-6, POSITIVE)
    initial_damping: float = setting(1e-4, POSITIVE)
    # median flow residual above it flags the pair weak (estimate kept)
    max_flow_residual_px: float = setting(8.0, POSITIVE)
    # Point-to-plane ICP from the flow estimate
    use_icp: bool = True
    icp_voxel_m: float = setting(0.01, POSITIVE)  # finest ICP voxel; coarser levels are multiples of it
    icp_scales: tuple = setting((4.0, 2.0, 1.0), each(POSITIVE))
    icp_iterations: tuple = setting((30, 20, 15), each(COUNT))
    icp_distance_factor: float = setting(2.0, POSITIVE)  # correspondence distance = factor x voxel
    icp_normal_radius_factor: float = setting(3.0, POSITIVE)
    icp_normal_max_nn: int = setting(30, COUNT)
    # finest level's cap: voxels grow until the source has no more points
    icp_max_points: int = setting(20000, OPTIONAL_COUNT)
    icp_min_fitness: float = setting(0.3, FRACTION)  # below: keep the flow estimate, flag the pair
    icp_max_jump_m: float = setting(0.05, POSITIVE)  # ICP moving farther from the flow estimate: keep the flow estimate
    icp_max_jump_deg: float = setting(2.0, POSITIVE)
    # [ours] optional last step: Open3D dense RGB-D odometry (hybrid term) from the ICP estimate,
    # kept unless it fails or jumps farther than the ICP guards allow
    rgbd_refine: bool = True
    rgbd_iterations: tuple = setting((20, 10, 5), each(COUNT))  # per pyramid level, coarse to fine
    rgbd_depth_diff_max_m: float = setting(0.07, POSITIVE)
    # [ours] verified candidates: every candidate pose of a pair (flow solve, ICP from it, ICP from the
    # constant-velocity prior, RGB-D odometry from each ICP result, the prior itself) is scored by
    # taichi_gs.stages.pose.verify on both frames' depth and colour; the lowest score wins and sets "weak".
    # false: the method's path (flow solve, then ICP behind the fitness and jump guards).
    verify: bool = True
    # [ours] one more candidate, the joint solve: the flow term L_F plus a point-to-plane term L_P on frame
    # t+1's depth, in units of its noise (verify_depth_sigma_m + verify_depth_sigma_quadratic z^2), for
    # joint_iterations steps from the flow solve. Each term is measured in its own typical residual there (the
    # median; also its IRLS floor) and L_P weighs joint_plane_weight times L_F: depth pins the motion across
    # the surfaces it sees, the flow the motion along them, where ICP slides, and where depth is noisy or
    # far (its residuals large) the flow keeps more say
    joint_solve: bool = True
    joint_plane_weight: float = setting(16.0, POSITIVE)
    joint_iterations: int = setting(10, COUNT)
    joint_normal_smooth_px: float = setting(2.0, NON_NEGATIVE)
    icp_from_prior: bool = True  # also run ICP from the constant-velocity prior (a second candidate)
    verify_max_score: float = setting(0.5, POSITIVE)  # winner's score above it flags the pair weak
    # near-ties (within this fraction of the lowest score) go to the first candidate in this order
    verify_margin: float = setting(0.02, NON_NEGATIVE)
    verify_preference: tuple = setting(("rgbd-icp", "rgbd-icp-prior", "icp", "icp-prior", "flow", "joint",
                                        "constant-velocity"), CANDIDATE_LIST)
    verify_min_overlap: float = setting(0.2, FRACTION)  # winner's overlap below it flags the pair weak
    # [ours] add this x the candidate's disagreement with the pair's measured optical flow (0..1, capped at
    # verify_flow_scale_px per pixel, at 320 px width) to its score, for pairs and graph edges alike: on plain
    # walls depth and colour residuals cannot see a candidate slide along the wall, the flow can. 0: off
    verify_flow_weight: float = setting(0.05, ANY)
    verify_flow_scale_px: float = setting(4.0, ANY)
    verify_grid_points: int = setting(3000, at_least(10))
    verify_depth_sigma_m: float = setting(0.003, POSITIVE)
    verify_depth_sigma_quadratic: float = setting(0.0025, NON_NEGATIVE)
    verify_photo_sigma: float = setting(0.04, POSITIVE)
    verify_photo_weight: float = setting(1.0, NON_NEGATIVE)
    # [ours] robust pose graph (taichi_gs.stages.pose.graph) over the pairs (i, i+1), extra edges (i, i+k) for k in
    # graph_skips and loop closures where the chained cameras come back near an earlier one; each extra
    # edge is RGB-D odometry (and ICP with graph_icp) started from the chained poses, verified like a pair
    # and dropped when weak. false: poses are the chained pairs.
    pose_graph: bool = setting(True, pair=False)
    graph_skips: tuple = setting((2, 3), FRAME_GAPS, pair=False)
    graph_icp: bool = setting(False, pair=False)
    # [ours] the extra edges also get a joint candidate (joint_solve's settings, from the chained poses, on the
    # edge's flows), so an edge along a plain wall is not only RGB-D odometry, which slides there. On 18
    # synthetic 60-frame sequences ATE sums 53.2 -> 45.7 mm (plain hand-held 9.5 -> 3.5, 4.9 -> 1.7; corridor
    # hand-held 3.4 -> 5.2), on eight real slices within +-0.6 mm but one (+2.0 mm, RPE rotation 0.91 -> 0.53 deg),
    # for about 1.2x stage 1's time (docs/notebook/benchmarks-2026-11.md, "The joint candidate on the graph's edges, on
    # by default")
    graph_joint: bool = setting(True, pair=False)
    # [ours] RGB-D odometry iterations per pyramid level of the extra edges, which start from the chained
    # poses (the pairs' own odometry keeps rgbd_iterations)
    graph_rgbd_iterations: tuple = setting((20, 10, 5), ANY, pair=False)
    # extra edges scoring above this x the median pair score are dropped
    graph_max_score_ratio: float = setting(1.5, ANY, pair=False)
    # information scale of weak (i, i+1) pairs, kept to connect the graph
    graph_weak_weight: float = setting(0.01, NON_NEGATIVE, pair=False)
    # clouds of the information matrices (Open3D, point-to-point)
    graph_info_voxel_m: float = setting(0.02, POSITIVE, pair=False)
    # [ours] a frame's information cloud keeps at most this many points (0: no cap): its voxel grows by 25% steps
    # as ICP's does; noisy far depth filled 2 cm voxels several layers deep (130k points at 640x480)
    graph_info_max_points: int = setting(20000, OPTIONAL_COUNT, pair=False)
    graph_info_distance_m: float = setting(0.04, POSITIVE, pair=False)
    loop_closures: bool = setting(True, pair=False)
    loop_min_gap: int = setting(15, at_least(2), pair=False)  # frames between the two ends of a loop edge, at least
    loop_every: int = setting(5, COUNT, pair=False)  # look for a loop closure at every this-many-th frame
    loop_max_distance_m: float = setting(0.3, POSITIVE, pair=False)  # chained camera centres closer than this ...
    loop_max_angle_deg: float = setting(30.0, within(0, 180), pair=False)  # ... and viewing directions closer than this
    # [ours] long edges (i, i+k) for k in graph_long_spans, from every graph_long_every-th frame i, where the
    # chained cameras are as close as a loop closure's (loop_max_distance_m, loop_max_angle_deg); verified like
    # the other extra edges but not held to graph_max_score_ratio, whose 1.5x the median pair score admits almost
    # none that long. They bound the drift of long, slowly moving captures: 7-Scenes' 250 frames 35.1 -> 17.2 mm,
    # TUM fr1_rpy 14.2 -> 13.0 mm, at 1.09x the stage's time (docs/notebook/benchmarks-2026-11.md, "Long edges from
    # every 4th frame").
    # From every frame: four times the edges, 1.31x the time, no better on 7-Scenes. () turns them off.
    graph_long_spans: tuple = setting((16, 32), FRAME_GAPS, pair=False)
    graph_long_every: int = setting(4, COUNT, pair=False)
    # [ours] near-ties in the graph: a pair's candidates that score within verify_margin of its best (its
    # verification cannot tell them apart) and lie more than graph_near_tie_mm from its chosen transform are
    # offered to the graph; once it is solved, each pair's edge takes whichever of them its poses, set by the
    # skip edges, loop closures and long edges, satisfy best, and the graph is solved again
    graph_near_ties: bool = setting(True, pair=False)
    graph_near_tie_mm: float = setting(2.0, NON_NEGATIVE, pair=False)
    # [ours] a rolling shutter: the colour and depth cameras read their rows top to bottom over readout_ms
    # milliseconds. The pairs are estimated on the frames as read, each frame's motion over its readout taken
    # from them (rolling_shutter.readout_motions), every frame de-skewed to its middle row's pose
    # (rolling_shutter.DeskewedSequence), and the pairs, the graph and the fused cloud computed again on the
    # de-skewed frames: about 1.4x the stage's time. 0: a global shutter. camera_readout: with readout_ms 0, the
    # readout of a camera the sequence's reading names (io.readout.KNOWN_READOUT_MS; on in the fast preset).
    # Not with precomputed flows (flow_dir), which are the frames' as read
    readout_ms: float = setting(0.0, NON_NEGATIVE, pair=False)
    camera_readout: bool = setting(False, pair=False)
    # Fused cloud
    # s: the fused cloud's voxel; stage 2 gives each Gaussian scale s/2
    voxel_size_m: float = setting(0.02, POSITIVE, pair=False)
    # [ours] threads (0: one per core this process may run on, at most DEFAULT_MAX_THREADS). The next pairs'
    # prior-free work (flow solve, ICP and RGB-D odometry from it, their verification) runs ahead while a pair
    # finishes, and the graph's edges run side by side. Results do not depend on it; under --profile stage 1
    # runs on one thread.
    threads: int = setting(0, OPTIONAL_COUNT, pair=False)

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
        (``flow_scale_px``, ``plane_scale``: see :func:`taichi_gs.stages.pose.pair.add_joint`)."""
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
        """Mask of ``depth``'s pixels that clouds and ICP may use (:func:`taichi_gs.stages.pose.icp.reliable_depth_mask`)."""
        return reliable_depth_mask(depth, self.min_depth_m, self.max_depth_m, self.depth_edge_ratio)

    def pair_key(self) -> str:
        """Hash of the fields that change a pair's result (not the fused cloud's voxel size nor the graph's)."""
        values = {k: v for k, v in dataclasses.asdict(self).items() if k not in _NOT_PAIR_FIELDS}
        return hashlib.sha1(json.dumps(values, sort_keys=True, default=list).encode()).hexdigest()[:16]


# Fields that do not change a pair's own result (excluded from the pair cache's key): those declared pair=False.
_NOT_PAIR_FIELDS = {f.name for f in dataclasses.fields(PoseConfig) if not f.metadata.get("pair", True)}

# paper: the method's path alone (flow solve, then point-to-plane ICP on every point behind its guards, pairs
# chained; DIS in place of Unimatch): every addition of ours off. fast: ours, ICP on at most icp_max_points points
# per frame, known cameras' rolling shutters.
PAPER = PoseConfig(verify=False, joint_solve=False, rgbd_refine=False, icp_from_prior=False, seeded_retry=False,
                   pose_graph=False, flow_finest_width_px=0, icp_max_points=0)
PRESETS = {"fast": PoseConfig(camera_readout=True), "paper": PAPER}

# The method's path at a benchmark's cost: ICP capped at 80000 points per frame.
METHOD_ONLY = dataclasses.replace(PAPER, icp_max_points=80000)
