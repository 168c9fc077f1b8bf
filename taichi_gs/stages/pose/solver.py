"""Robust Levenberg-Marquardt on the 6-DoF relative pose: IRLS weights turn sums of norms into
weighted least squares, re-linearised (and the masks re-evaluated) at every accepted step."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...geometry import se3_exp
from .losses import (PairSamples, Residuals, depth_consistency_residuals, flow_residuals, photometric_residuals,
                     point_to_plane_residuals, warp)


@dataclass(frozen=True)
class SolverSettings:
    """Loss weights, IRLS floors (residual below which a point's weight stops growing) and stopping rules."""

    photometric_weight: float
    depth_consistency_weight: float
    flow_floor_px: float
    photometric_floor: float
    depth_floor_m: float
    min_baseline_m: float
    min_points: int
    max_iterations: int
    step_tolerance: float
    cost_tolerance: float
    initial_damping: float
    plane_weight: float = 0.0  # [ours] L_P's weight; needs the samples' target normals
    plane_floor: float = 1.0  # in units of L_P's residual (depth noise sigmas)
    plane_noise: tuple = (1.0, 0.0)  # sigma(z) = a + b z^2 metres: L_P's residuals are divided by it


@dataclass(frozen=True)
class Linearisation:
    """Robust cost at T (mean over valid points of sum_k weight_k |r_k|) and the IRLS normal equations."""

    T: np.ndarray
    cost: float
    valid_points: int
    hessian: np.ndarray
    gradient: np.ndarray


@dataclass(frozen=True)
class SolveResult:
    T: np.ndarray
    cost: float
    iterations: int
    converged: bool
    valid_points: int


def active_terms(T: np.ndarray, samples: PairSamples, settings: SolverSettings) -> tuple[np.ndarray, list[tuple[Residuals, float, float]]]:
    """Valid-point mask and the (residuals, weight, IRLS floor) of every term with a non-zero weight."""
    w = warp(T, samples)
    terms = [(flow_residuals(w, samples), 1.0, settings.flow_floor_px)]
    if settings.photometric_weight > 0:
        terms.append((photometric_residuals(w, samples), settings.photometric_weight, settings.photometric_floor))
    if settings.depth_consistency_weight > 0:
        consistency = depth_consistency_residuals(w, samples, settings.min_baseline_m)
        if consistency is not None:
            terms.append((consistency, settings.depth_consistency_weight, settings.depth_floor_m))
    if settings.plane_weight > 0 and samples.target_normals is not None:
        terms.append((point_to_plane_residuals(w, samples, settings.plane_noise), settings.plane_weight,
                      settings.plane_floor))
    return w.valid, terms


def typical_residuals(T: np.ndarray, samples: PairSamples, settings: SolverSettings) -> list[float]:
    """Median residual norm of each active term at T (in :func:`active_terms`' order) over the valid points
    where the term is defined (non-zero); NaN for a term with none."""
    valid, terms = active_terms(T, samples, settings)
    medians = []
    for residuals, _, _ in terms:
        norms = residuals.norms()[valid]
        norms = norms[norms > 0]
        medians.append(float(np.median(norms)) if len(norms) else float("nan"))
    return medians


def linearise(T: np.ndarray, samples: PairSamples, settings: SolverSettings) -> Linearisation:
    """Cost and IRLS Gauss-Newton system at T; infinite cost when too few points stay valid."""
    valid, terms = active_terms(T, samples, settings)
    n = int(valid.sum())
    if n < settings.min_points:
        return Linearisation(T, float("inf"), n, np.zeros((6, 6)), np.zeros(6))
    cost = 0.0
    hessian, gradient = np.zeros((6, 6)), np.zeros(6)
    for residuals, weight, floor in terms:
        r, J = residuals.values[valid], residuals.jacobian[valid]
        norms = np.linalg.norm(r, axis=1)
        cost += weight * norms.sum() / n
        irls = weight / np.maximum(norms, floor) / n
        weighted = (J * irls[:, None, None]).reshape(-1, 6)
        hessian += weighted.T @ J.reshape(-1, 6)
        gradient += weighted.T @ r.reshape(-1)
    return Linearisation(T, float(cost), n, hessian, gradient)


def solve(T0: np.ndarray, samples: PairSamples, settings: SolverSettings) -> SolveResult:
    """Minimise the robust cost from T0 with damped Gauss-Newton steps T <- exp(delta) T."""
    current = linearise(T0, samples, settings)
    if not np.isfinite(current.cost):
        return SolveResult(T0, current.cost, 0, False, current.valid_points)
    damping = settings.initial_damping
    converged = False
    iteration = 0
    for iteration in range(1, settings.max_iterations + 1):
        H = current.hessian + damping * np.diag(np.diag(current.hessian) + 1e-12)
        try:
            delta = np.linalg.solve(H, -current.gradient)
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(delta)):
            break
        candidate = linearise(se3_exp(delta) @ current.T, samples, settings)
        small_step = np.linalg.norm(delta) < settings.step_tolerance
        if candidate.cost < current.cost:
            decrease = current.cost - candidate.cost
            current = candidate
            damping = max(damping / 3.0, 1e-9)
            if small_step or decrease < settings.cost_tolerance * current.cost:
                converged = True
                break
        else:
            damping *= 4.0
            if small_step or damping > 1e8:
                converged = True
                break
    return SolveResult(current.T, current.cost, iteration, converged, current.valid_points)
