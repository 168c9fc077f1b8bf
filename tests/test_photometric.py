"""Per-frame affine colour compensation: gradients against central finite differences in float64,
and stage 3's schedule helpers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from taichi_gs.photometric import IDENTITY, affine_backward, apply_affine, identity_penalty
from taichi_gs.stages.deblur import PRESETS, scaled_schedule, training_frame


def _loss(image, M, weights):
    return float(np.sum(weights * apply_affine(image, M) ** 2))


def test_affine_gradients_match_finite_differences():
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (7, 5, 3))
    M = IDENTITY + 0.1 * rng.normal(size=(3, 4))
    weights = rng.normal(size=(7, 5, 3))
    grad_out = 2 * weights * apply_affine(image, M)
    grad_image, grad_M = affine_backward(image, M, grad_out)
    h = 1e-6
    fd_M = np.zeros_like(M)
    for idx in np.ndindex(M.shape):
        step = np.zeros_like(M)
        step[idx] = h
        fd_M[idx] = (_loss(image, M + step, weights) - _loss(image, M - step, weights)) / (2 * h)
    fd_image = np.zeros_like(image)
    for idx in [(0, 0, 0), (3, 2, 1), (6, 4, 2), (2, 3, 0)]:
        step = np.zeros_like(image)
        step[idx] = h
        fd_image[idx] = (_loss(image + step, M, weights) - _loss(image - step, M, weights)) / (2 * h)
        assert grad_image[idx] == pytest.approx(fd_image[idx], rel=1e-6, abs=1e-8)
    assert np.allclose(grad_M, fd_M, rtol=1e-6, atol=1e-8)


def test_identity_is_a_no_op_and_the_pull_gradient_is_exact():
    image = np.random.default_rng(1).uniform(0, 1, (4, 4, 3))
    assert np.array_equal(apply_affine(image, IDENTITY), image)
    M = IDENTITY + 0.05
    value, grad = identity_penalty(M, 0.3)
    assert value == pytest.approx(0.3 * 12 * 0.05**2)
    h = 1e-6
    step = np.zeros_like(M)
    step[1, 3] = h
    fd = (identity_penalty(M + step, 0.3)[0] - identity_penalty(M - step, 0.3)[0]) / (2 * h)
    assert grad[1, 3] == pytest.approx(fd, rel=1e-6)


def test_schedule_scales_with_training_views():
    fast = dataclasses.replace(PRESETS["fast"], iterations_per_view=40)
    assert scaled_schedule(fast, 10) is fast  # 400 < 600: unchanged
    long = scaled_schedule(fast, 30)
    assert long.iterations == 1200 and long.densify_from == 2 * fast.densify_from
    assert long.densify_until == 2 * fast.densify_until and long.exposure_from == 2 * fast.exposure_from
    assert long.densify_every == 2 * fast.densify_every


def test_epoch_sampling_visits_every_view_once_per_epoch():
    train = [0, 2, 3, 5, 7]
    rng = np.random.default_rng(0)
    for epoch in range(3):
        seen = [training_frame(train, epoch * 5 + i, rng, seed=4, epochs=True) for i in range(5)]
        assert sorted(seen) == train
    assert training_frame(train, 7, rng, 4, True) == training_frame(train, 7, np.random.default_rng(9), 4, True)
