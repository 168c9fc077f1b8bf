"""Rprop (the held-out fits' optimiser): step sizes grow while a coordinate's gradient keeps its
sign, halve when it flips, stay within their bounds, and find a quadratic's minimum."""

from __future__ import annotations

import numpy as np
import pytest

from taichi_gs.stages.deblur.rprop import GROW, SHRINK, Rprop


def test_steps_grow_with_a_steady_sign_and_shrink_at_a_flip():
    opt = Rprop((2,), step=0.1, max_ratio=100.0)
    x = opt.step(np.zeros(2), np.array([1.0, -1.0]))
    np.testing.assert_allclose(x, [-0.1, 0.1])
    x = opt.step(x, np.array([1.0, 1.0]))  # first coordinate keeps its sign, second flips
    np.testing.assert_allclose(opt.steps, [0.1 * GROW, 0.1 * SHRINK])
    np.testing.assert_allclose(x, [-0.1 - 0.1 * GROW, 0.1])  # the flipped one waits a step
    x = opt.step(x, np.array([1.0, 1.0]))  # after the wait the second moves with its smaller step
    np.testing.assert_allclose(x[1], 0.1 - 0.1 * SHRINK)


def test_steps_stay_within_their_bounds():
    opt = Rprop((1,), step=1.0, min_ratio=0.25, max_ratio=2.0)
    x = np.zeros(1)
    for _ in range(20):
        x = opt.step(x, np.ones(1))
    assert opt.steps[0] == pytest.approx(2.0)
    for sign in [1.0, -1.0] * 10:
        x = opt.step(x, np.full(1, sign))
    assert opt.steps[0] == pytest.approx(0.25)


def test_finds_the_minimum_of_an_ill_scaled_quadratic():
    scales = np.array([1.0, 100.0, 0.01])  # curvatures 4 orders of magnitude apart
    target = np.array([0.3, -0.2, 0.5])
    opt = Rprop((3,), step=0.01)
    x = np.zeros(3)
    for _ in range(80):
        x = opt.step(x, scales * (x - target))
    np.testing.assert_allclose(x, target, atol=1e-3)


def test_rejects_a_non_positive_step():
    with pytest.raises(ValueError, match="positive"):
        Rprop((2,), step=0.0)
