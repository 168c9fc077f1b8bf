"""Robust pose graph: a corrupted edge is outvoted, the true trajectory comes back."""

from __future__ import annotations

import numpy as np

from taichi_gs.evaluate import ate, rpe
from taichi_gs.geometry import invert, se3_exp
from taichi_gs.stages.pose.graph import Edge, optimise, rechoose


def _trajectory(n: int, rng: np.random.Generator) -> np.ndarray:
    poses = [np.eye(4)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ se3_exp(np.concatenate([rng.normal(0, 0.03, 3) + [0, 0, 0.03], rng.normal(0, 0.03, 3)])))
    return np.stack(poses)


def _edges(truth: np.ndarray, skips: tuple[int, ...], rng: np.random.Generator, noise: float) -> list[Edge]:
    info = np.diag([1e4] * 3 + [1e4] * 3)
    edges = []
    for s in range(len(truth)):
        for k in skips:
            t = s + k
            if t < len(truth):
                Z = invert(truth[t]) @ truth[s] @ se3_exp(rng.normal(0, noise, 6))
                edges.append(Edge(s, t, Z, info, "odometry" if k == 1 else "skip"))
    return edges


def _chain(edges: list[Edge], n: int) -> np.ndarray:
    odometry = {e.source: e.transform for e in edges if e.kind == "odometry"}
    poses = [np.eye(4)]
    for s in range(n - 1):
        poses.append(poses[-1] @ invert(odometry[s]))
    return np.stack(poses)


def test_graph_with_one_corrupted_edge_recovers_the_true_trajectory():
    rng = np.random.default_rng(3)
    truth = _trajectory(30, rng)
    edges = _edges(truth, (1, 2, 3), rng, noise=2e-4)
    bad = next(e for e in edges if e.source == 12 and e.kind == "odometry")
    bad.transform = se3_exp(np.array([0.04, -0.03, 0.0, 0.0, 0.03, 0.0])) @ bad.transform  # 5 cm, 1.7 deg slip
    start = _chain(edges, len(truth))
    assert ate(start, truth) > 0.01  # the chained trajectory keeps the slip

    poses = optimise(start, edges)
    assert ate(poses, truth) < 1e-3
    assert rpe(poses, truth)[1] < 0.05
    assert bad.pruned and bad.weight < 0.05
    assert sum(e.pruned for e in edges) == 1


def test_plain_odometry_chain_is_left_unchanged():
    rng = np.random.default_rng(4)
    truth = _trajectory(10, rng)
    edges = _edges(truth, (1,), rng, noise=0.0)
    poses = optimise(_chain(edges, len(truth)), edges)
    assert np.abs(poses - truth).max() < 1e-9
    assert not any(e.pruned for e in edges)


def test_rechoose_takes_the_alternative_the_other_edges_agree_with_and_leaves_a_worse_one():
    rng = np.random.default_rng(3)
    truth = _trajectory(30, rng)
    edges = _edges(truth, (1, 2, 3), rng, noise=2e-4)
    slipped = next(k for k, e in enumerate(edges) if e.source == 12 and e.kind == "odometry")
    sound = next(k for k, e in enumerate(edges) if e.source == 5 and e.kind == "odometry")
    true_12, kept_5 = edges[slipped].transform, edges[sound]
    slip = se3_exp(np.array([0.008, 0.0, 0.0, 0.0, 0.0, 0.0]))  # 8 mm: a near-tie's size, too small to prune
    edges[slipped] = Edge(12, 13, slip @ true_12, edges[slipped].information, "odometry", "rgbd-icp")
    start = _chain(edges, len(truth))
    before = optimise(start, edges)
    alternatives = {slipped: [Edge(12, 13, true_12, edges[slipped].information, "odometry", "joint")],
                    sound: [Edge(5, 6, slip @ kept_5.transform, kept_5.information, "odometry", "flow")]}

    assert rechoose(edges, before, alternatives) == 1
    assert edges[slipped].estimate == "joint" and edges[sound] is kept_5
    after = optimise(start, edges)
    pair_12 = [np.linalg.norm((invert(invert(truth[13]) @ truth[12]) @ invert(p[13]) @ p[12])[:3, 3])
               for p in (before, after)]
    assert pair_12[1] < 0.6 * pair_12[0] and pair_12[1] < 2e-4
