"""[ours] Robust pose-graph optimisation: camera poses from many relative-pose edges, a few of them wrong.

Nodes are camera-to-world poses X_i; an edge (s, t, Z, Lambda) says that Z, the transform camera s ->
camera t, equals inv(X_t) X_s, with information matrix Lambda (6 x 6, twist order [translation,
rotation], expressed in camera t: the frame of Open3D's ``get_information_matrix_from_point_clouds``).
The error of an edge is ``e = log(inv(X_t) X_s inv(Z))``, a left perturbation in camera t.

Solved by Gauss-Newton on all poses at once (dense normal equations; the first pose is fixed to pin
the gauge), first by plain least squares, then by iteratively reweighted least squares with the
Cauchy loss on each edge's Mahalanobis length ``chi = sqrt(e^T Lambda e)``. The Cauchy scale is
``robust_scale`` times the median chi of the cycle-closing (non-odometry) edges (never below
``min_chi``), so the loss needs no
calibrated noise level: an edge that disagrees with the rest far more than the typical edge does
is outvoted (its weight ends near 0) and reported as pruned.

[ours] :func:`rechoose` swaps an edge for an alternative measurement of the same two nodes that the
optimised poses satisfy better (stage 1: a pair's near-tied candidates, which its own score could not
tell apart), before the graph is solved again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import profiling
from .geometry import adjoint, invert, se3_exp, se3_log


@dataclass
class Edge:
    """A relative-pose constraint between nodes ``source`` and ``target``."""

    source: int
    target: int
    transform: np.ndarray  # camera source -> camera target
    information: np.ndarray  # 6 x 6, [translation, rotation], in the target camera
    kind: str = "odometry"  # odometry | skip | loop | long
    estimate: str = ""  # how the transform was obtained (recorded, not used)
    score: float = float("nan")  # its verification score (recorded, not used)
    weak: bool = False
    weight: float = 1.0  # final robust weight (set by optimise)
    pruned: bool = False  # final weight below the prune threshold (set by optimise)


@dataclass(frozen=True)
class GraphSettings:
    least_squares_iterations: int = 10
    robust_iterations: int = 30
    robust_scale: float = 3.0  # Cauchy scale = this x median chi
    min_chi: float = 1e-6
    prune_weight: float = 0.25  # final Cauchy weight below it: the edge is reported as pruned
    step_tolerance: float = 1e-9


def edge_error(edge: Edge, poses: np.ndarray) -> np.ndarray:
    """e = log(inv(X_t) X_s inv(Z)), 6-vector [translation, rotation]."""
    return se3_log(invert(poses[edge.target]) @ poses[edge.source] @ invert(edge.transform))


@profiling.timed("pose graph: optimisation")
def optimise(poses: np.ndarray, edges: list[Edge], settings: GraphSettings = GraphSettings()) -> np.ndarray:
    """Camera-to-world poses (N x 4 x 4) that best satisfy the edges, starting from ``poses``; node 0 stays.

    Sets each edge's final ``weight`` and ``pruned``."""
    poses = np.array(poses, dtype=np.float64)
    n = len(poses)
    if n < 2 or not edges:
        return poses
    weights = np.ones(len(edges))
    total = settings.least_squares_iterations + settings.robust_iterations
    for iteration in range(total):
        robust = iteration >= settings.least_squares_iterations
        errors = [edge_error(e, poses) for e in edges]
        if robust:
            weights = _cauchy_weights(edges, errors, settings)
        step = _gauss_newton_step(poses, edges, errors, weights)
        for i in range(1, n):
            poses[i] = poses[i] @ se3_exp(step[6 * (i - 1): 6 * i])
        if np.max(np.abs(step)) < settings.step_tolerance and (robust or settings.robust_iterations == 0):
            break
    errors = [edge_error(e, poses) for e in edges]
    weights = _cauchy_weights(edges, errors, settings)
    for edge, w in zip(edges, weights):
        edge.weight, edge.pruned = float(w), bool(w < settings.prune_weight)
    return poses


def rechoose(edges: list[Edge], poses: np.ndarray, alternatives: dict[int, list[Edge]]) -> int:
    """[ours] Replace ``edges[k]``, for each k in ``alternatives``, with whichever of itself and
    ``alternatives[k]`` the poses satisfy best (smallest Mahalanobis length of the edge error; a tie keeps
    the edge). Returns how many edges were replaced."""
    replaced = 0
    for k, options in alternatives.items():
        chi = [_mahalanobis(edge_error(edge, poses), edge.information) for edge in [edges[k], *options]]
        best = int(np.argmin(chi))
        if best > 0:
            edges[k] = options[best - 1]
            replaced += 1
    return replaced


def _mahalanobis(error: np.ndarray, information: np.ndarray) -> float:
    """chi = sqrt(e^T Lambda e)."""
    return float(np.sqrt(max(float(error @ information @ error), 0.0)))


def _cauchy_weights(edges: list[Edge], errors: list[np.ndarray], settings: GraphSettings) -> np.ndarray:
    """Cauchy weights; the scale comes from the edges that close cycles (kind other than odometry): in a
    chain with few extra edges most odometry edges sit on no cycle and have chi = 0 whatever their error."""
    chi = np.array([_mahalanobis(e, edge.information) for edge, e in zip(edges, errors)])
    closing = np.array([edge.kind != "odometry" for edge in edges])
    reference = chi[closing] if closing.any() else chi
    scale = max(settings.robust_scale * float(np.median(reference)), settings.min_chi)
    return 1.0 / (1.0 + (chi / scale) ** 2)


def _gauss_newton_step(poses: np.ndarray, edges: list[Edge], errors: list[np.ndarray], weights: np.ndarray) -> np.ndarray:
    """Right-perturbation steps of nodes 1..N-1 (node 0 fixed), from the weighted normal equations.

    X_s <- X_s exp(d_s) changes e by Ad(Z) d_s (to first order), X_t <- X_t exp(d_t) by -d_t."""
    m = 6 * (len(poses) - 1)
    H, b = np.zeros((m, m)), np.zeros(m)
    for edge, e, w in zip(edges, errors, weights):
        blocks = {edge.source: adjoint(edge.transform), edge.target: -np.eye(6)}
        for i, Ji in blocks.items():
            if i == 0:
                continue
            si = slice(6 * (i - 1), 6 * i)
            b[si] += w * Ji.T @ edge.information @ e
            for j, Jj in blocks.items():
                if j != 0:
                    H[si, 6 * (j - 1): 6 * j] += w * Ji.T @ edge.information @ Jj
    H += 1e-9 * np.trace(H) / max(m, 1) * np.eye(m)
    return np.linalg.solve(H, -b)
