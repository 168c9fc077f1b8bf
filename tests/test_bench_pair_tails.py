"""bench/pair_tails.py: the chance that Gaussian pair errors keep their largest within 3x the median falls as the
errors gather in fewer directions, the whitened error is the leave-one-out Mahalanobis distance, a planted
outlier is told from the spread while Gaussian errors are not, and the adjacent pairs' correlation tells frames'
own errors from pairs' own errors and from a shared bias."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from pair_tails import (adjacent_correlation, gaussian_tail_chance, tail_line, whitened_error_quantile,  # noqa: E402
                        whitened_errors)


def _errors_with_covariance(spreads: list[float], n: int = 59) -> np.ndarray:
    """n vectors whose second moments over n are diag(spreads)."""
    errors = np.zeros((n, 3))
    for axis, spread in enumerate(spreads):
        errors[axis::3, axis] = np.sqrt(n / len(errors[axis::3]) * spread)
    return errors


def test_the_chance_falls_as_the_errors_gather_in_fewer_directions():
    space = gaussian_tail_chance(_errors_with_covariance([1.0, 1.0, 1.0]))
    plane = gaussian_tail_chance(_errors_with_covariance([1.0, 1.0, 1e-8]))
    line = gaussian_tail_chance(_errors_with_covariance([1.0, 1e-8, 1e-8]))
    assert space > 0.97 and 0.75 < plane < 0.93 and 0.05 < line < 0.25
    # scale does not matter, nor which axis
    assert abs(gaussian_tail_chance(_errors_with_covariance([0.0, 1e-8, 25.0])) - line) < 0.02


def test_the_whitened_error_is_the_distance_in_the_other_pairs_covariance():
    rng = np.random.default_rng(3)
    errors = rng.standard_normal((40, 3)) @ np.array([[2.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.3, 0.1]])
    for k in (0, 7, 39):
        others = np.delete(errors, k, axis=0)
        covariance = others.T @ others / len(others)
        assert np.isclose(whitened_errors(errors)[k], np.sqrt(errors[k] @ np.linalg.solve(covariance, errors[k])))


def test_a_planted_outlier_is_told_from_the_spread():
    threshold = whitened_error_quantile(59)
    rng = np.random.default_rng(5)
    plain = rng.standard_normal((59, 3)) * [1.0, 0.5, 0.1]
    assert whitened_errors(plain).max() < threshold
    # 1 mm off along the direction the other pairs barely err in: small in mm, an outlier of the distribution
    planted = plain.copy()
    planted[20] = [0.0, 0.0, 1.0]
    assert np.linalg.norm(planted[20]) < np.linalg.norm(plain, axis=1).max()
    assert np.argmax(whitened_errors(planted)) == 20 and whitened_errors(planted).max() > threshold
    assert tail_line("s", planted).endswith("pair 20 (1.0 mm; 99% of Gaussian sequences: under 4.97): an outlier")
    assert tail_line("s", plain).endswith(": within the spread")
    without_reference = tail_line("s", np.vstack([[np.nan] * 3, planted]))  # left out; pairs keep their numbers
    assert without_reference.endswith("pair 21 (1.0 mm; 99% of Gaussian sequences: under 4.97): an outlier")


def test_the_quantile_holds_for_gaussian_sequences():
    rng = np.random.default_rng(11)
    threshold = whitened_error_quantile(30)
    above = [whitened_errors(rng.standard_normal((30, 3)) @ rng.standard_normal((3, 3))).max() > threshold
             for _ in range(400)]
    assert 0.0 < np.mean(above) < 0.03


def test_the_adjacent_correlation_tells_frame_errors_from_pair_errors_and_from_a_bias():
    rng = np.random.default_rng(2)
    frames = rng.standard_normal((2001, 3))
    assert abs(adjacent_correlation(np.diff(frames, axis=0)) + 0.5) < 0.05  # each frame's error in both its pairs
    assert abs(adjacent_correlation(rng.standard_normal((2000, 3)))) < 0.05  # each pair errs on its own
    assert adjacent_correlation(rng.standard_normal((2000, 3)) + [1.0, 0.0, 0.0]) > 0.2  # a shared bias
