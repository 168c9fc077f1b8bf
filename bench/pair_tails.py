"""How much of a trajectory's largest pair error chance explains: issue 11's "no pair error above 3x the median"
read against an unbiased estimator whose pair errors are Gaussian.

A sequence's pair translation errors (n x 3, mm, in the camera's axes) give their covariance (second moments
about zero: an unbiased estimator's). Two figures follow from it:

- ``gaussian_tail_chance``: the probability that n pair errors drawn from that Gaussian keep their largest within
  ``ratio`` x their median. Errors spread over one or two directions (a weak direction along a corridor, along
  the optical axis) miss such a target often by chance alone: for n = 59, errors along one direction do so 87%
  of the time, isotropic ones in a plane 15%, isotropic ones in space 1%.
- ``whitened_errors``: each pair error in units of the covariance of the other pairs (leave-one-out Mahalanobis
  distance); the largest of them beside the ``quantile`` of that largest over n Gaussian errors
  (``whitened_error_quantile``; the statistic is affine-invariant, so the quantile depends on n alone). Above it,
  the pair is an outlier of the sequence's own error distribution: something a better pair estimate could fix,
  not the spread every pair has.

``adjacent_correlation`` says what the pair errors are made of: about 0 when each pair errs on its own, -0.5
when every frame's pose errs on its own (white noise about the path: each frame's error shows in both of its pairs
with opposite signs and does not accumulate), positive when the pairs share a bias that accumulates (a scale).

Pairs whose errors differ in spread (faster motion, less overlap) make the pooled Gaussian lighter-tailed than
the errors: the chance then overstates an ideal estimator's, and the whitened test flags such pairs as outliers.
Both lean against excusing a miss.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np


def _second_moments(errors: np.ndarray) -> np.ndarray:
    """Sum of outer products over the last-but-one axis: (..., n, 3) -> (..., 3, 3)."""
    return np.einsum("...ni,...nj->...ij", errors, errors)


def gaussian_tail_chance(errors: np.ndarray, ratio: float = 3.0, draws: int = 20000, seed: int = 0) -> float:
    """Probability that ``len(errors)`` zero-mean Gaussian vectors with the covariance of ``errors`` (n x 3) have
    no norm above ``ratio`` x their median norm (Monte Carlo over ``draws`` sequences)."""
    n = len(errors)
    covariance = _second_moments(errors) / n
    root = np.linalg.cholesky(covariance + 1e-12 * np.trace(covariance) * np.eye(3))
    norms = np.linalg.norm(np.random.default_rng(seed).standard_normal((draws, n, 3)) @ root.T, axis=2)
    return float(np.mean(norms.max(axis=1) <= ratio * np.median(norms, axis=1)))


def whitened_errors(errors: np.ndarray) -> np.ndarray:
    """Each pair's error (..., n, 3) in units of the covariance of the other n - 1 pairs: its leave-one-out
    Mahalanobis distance, sqrt((n - 1) h / (1 - h)) with h = e^T (sum of all e e^T)^-1 e (Sherman-Morrison)."""
    n = errors.shape[-2]
    leverage = np.einsum("...ni,...ij,...nj->...n", errors, np.linalg.inv(_second_moments(errors)), errors)
    return np.sqrt((n - 1) * leverage / np.maximum(1.0 - leverage, 1e-12))


@lru_cache
def whitened_error_quantile(n: int, quantile: float = 0.99, draws: int = 20000, seed: int = 0) -> float:
    """The ``quantile`` of the largest of n whitened errors (``whitened_errors``) over n zero-mean Gaussian errors
    (any covariance); computed once per argument set."""
    samples = np.random.default_rng(seed).standard_normal((draws, n, 3))
    return float(np.quantile(whitened_errors(samples).max(axis=1), quantile))


def adjacent_correlation(errors: np.ndarray) -> float:
    """Correlation of consecutive pair errors (n x 3): sum of e_k . e_k+1 over the sum of |e_k|^2."""
    return float(np.sum(errors[:-1] * errors[1:]) / np.sum(errors * errors))


def tail_line(name: str, errors: np.ndarray, ratio: float = 3.0) -> str:
    """One line on a sequence's pair errors (n x 3, mm): its largest against ``ratio`` x the median, the chance an
    unbiased Gaussian estimator with the same covariance meets that, the adjacent pairs' correlation, and whether
    the most outlying pair is an outlier. Pairs without a finite reference are left out."""
    kept = np.nonzero(np.all(np.isfinite(errors), axis=1))[0]
    errors = errors[kept]
    norms, whitened = np.linalg.norm(errors, axis=1), whitened_errors(errors)
    k, threshold = int(np.argmax(whitened)), whitened_error_quantile(len(errors))
    verdict = "an outlier" if whitened[k] > threshold else "within the spread"
    return (f"- {name}: largest {norms.max() / np.median(norms):.1f}x the median; a Gaussian estimator with this "
            f"covariance keeps it within {ratio:g}x with probability {gaussian_tail_chance(errors, ratio):.2f}; "
            f"adjacent pairs' errors correlate {adjacent_correlation(errors):+.2f}; largest whitened error "
            f"{whitened[k]:.2f}, pair {kept[k]} ({norms[k]:.1f} mm; 99% of Gaussian sequences: under {threshold:.2f}): "
            f"{verdict}")
