"""[ours] Stage 1's pose graph: the pairs' edges, skip edges, loop closures and long edges (each verified like a
pair), solved by :mod:`taichi_gs.pose_graph`."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Executor

import numpy as np

from .. import profiling
from ..geometry import invert
from ..icp import align, depth_cloud, open3d, rgbd_odometry
from ..io.jsonout import finite_or_null
from ..pose_graph import Edge, optimise, rechoose
from .pose_config import PoseConfig
from .pose_frames import FrameCache
from .pose_pair import (FROM_CONSTANT_VELOCITY, FROM_JOINT, Candidate, RelativePose, add_joint, choose, icp_levels,
                        measured_flow, sample_pair, seeded_flows)


def refine_with_graph(sequence, relatives: list[RelativePose], chained: np.ndarray, config: PoseConfig,
                      frames: FrameCache, pool: Executor,
                      on_frame: Callable[[int], None] | None = None) -> tuple[np.ndarray, list[Edge]]:
    """[ours] Poses from a robust pose graph over the pairs, skip edges, loop closures and long edges, solved
    again once each pair's edge has been re-chosen among its near-tied candidates (see PoseConfig);
    ``frames``: the run's per-frame cache, shared with the pairs; ``pool``: where the edges run (side by
    side on a thread pool, or one after another); ``on_frame(done)`` after each frame's edges."""
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
        check = measured_flow(*flows) if config.verify_flow_weight > 0 else None
        if config.graph_joint:
            samples = sample_pair(color_i, depth_i, color_j, depth_j, K, *flows, config.reliable_depth(depth_i), config,
                                  frames.normals(j))
            add_joint(candidates, samples, init, config, name=f"{FROM_JOINT}-chain")
    chosen = choose(candidates, views, K, config,
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
    every = config.graph_long_every  # at least 1: its rule in pose_config
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


@profiling.timed("pose graph: information matrices")
def _information(frames: FrameCache, i: int, j: int, T: np.ndarray, config: PoseConfig) -> np.ndarray:
    """Open3D's point-to-point information matrix of the edge i -> j, reordered to [translation, rotation]."""
    info = np.asarray(open3d().pipelines.registration.get_information_matrix_from_point_clouds(
        frames.info_cloud(i), frames.info_cloud(j), config.graph_info_distance_m, T))
    order = [3, 4, 5, 0, 1, 2]
    info = info[np.ix_(order, order)]
    return info + 1e-6 * np.trace(info) * np.eye(6) if np.trace(info) > 0 else np.eye(6) * 1e-6


def edge_record(edge: Edge) -> dict:
    """An edge as pairs.json lists it (after the graph: its weight and whether it was pruned)."""
    return {"source": edge.source, "target": edge.target, "kind": edge.kind, "estimate": edge.estimate,
            "score": finite_or_null(edge.score), "weak": edge.weak, "weight": round(edge.weight, 5), "pruned": edge.pruned}
