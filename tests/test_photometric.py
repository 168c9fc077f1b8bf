"""Per-frame affine colour compensation: gradients against central finite differences in float64,
and stage 3's schedule helpers."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import taichi as ti

from taichi_gs.kernels import runtime
from taichi_gs.photometric import IDENTITY, affine_backward, apply_affine, identity_penalty
from taichi_gs.render import affine, to_device
from taichi_gs.stages.deblur import PRESETS, scaled_schedule, training_frame, with_headroom


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


def test_device_transform_matches_the_numpy_reference_in_float64():
    """kernels/affine (what stage 3 runs each step) against apply_affine / affine_backward above."""
    runtime.init()
    rng = np.random.default_rng(3)
    image = rng.uniform(0, 1, (9, 70, 3))
    M = IDENTITY + 0.1 * rng.normal(size=(3, 4))
    grad_out = rng.normal(size=image.shape)
    out, grad_image = to_device(np.zeros(image.shape), ti.f64), to_device(np.full(image.shape, 7.0), ti.f64)
    affine.forward(to_device(image, ti.f64), M, out)
    np.testing.assert_allclose(out.to_numpy(), apply_affine(image, M), rtol=1e-12, atol=1e-14)
    grad_M = affine.backward(to_device(image, ti.f64), M, to_device(grad_out, ti.f64), grad_image)
    want_image, want_M = affine_backward(image, M, grad_out)
    np.testing.assert_allclose(grad_image.to_numpy(), want_image, rtol=1e-12, atol=1e-14)  # overwritten, not added
    np.testing.assert_allclose(grad_M, want_M, rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        affine.forward(to_device(image, ti.f64), M, to_device(np.zeros((9, 70, 1)), ti.f64))


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
    fast = PRESETS["fast"]
    assert fast.iterations_per_view == 80 and PRESETS["paper"].iterations_per_view == 0  # the method: fixed count
    assert fast.iterations == 840
    assert scaled_schedule(fast, 10) is fast  # 800 < 840: unchanged
    sample = scaled_schedule(fast, 11)  # the bundled sample's 11 training views: the schedule the notebook measured
    assert (sample.iterations, sample.densify_from, sample.densify_until, sample.densify_every,
            sample.exposure_from) == (880, 73, 330, 73, 88)
    long = scaled_schedule(fast, 21)
    assert long.iterations == 1680 and long.densify_from == 2 * fast.densify_from
    assert long.densify_until == 2 * fast.densify_until and long.exposure_from == 2 * fast.exposure_from
    assert long.densify_every == 2 * fast.densify_every
    # from 15 training views on, exactly the schedule of the 1200-iteration base this preset replaced
    old = dataclasses.replace(fast, iterations=1200, densify_from=100, densify_until=450, densify_every=100,
                              exposure_from=120)
    for n in range(15, 200):
        assert scaled_schedule(fast, n) == dataclasses.replace(scaled_schedule(old, n), iterations_per_view=0)


def test_the_cap_leaves_headroom_above_what_stage_2_hands_over():
    fast, paper = PRESETS["fast"], PRESETS["paper"]
    assert fast.densify_headroom == 1.3 and paper.densify_headroom == 0.0  # the method: its cap alone
    assert with_headroom(fast, 72_663) is fast  # the bundled sample's stage 2: 1.3 x 72,663 < 100k, unchanged
    assert with_headroom(fast, 192_923).max_gaussians == 250_800  # a 60-frame sequence's stage 2 (docs/notebook)
    assert with_headroom(paper, 10_000_000) is paper


def test_epoch_sampling_visits_every_view_once_per_epoch():
    train = [0, 2, 3, 5, 7]
    rng = np.random.default_rng(0)
    for epoch in range(3):
        seen = [training_frame(train, epoch * 5 + i, rng, seed=4, epochs=True) for i in range(5)]
        assert sorted(seen) == train
    assert training_frame(train, 7, rng, 4, True) == training_frame(train, 7, np.random.default_rng(9), 4, True)


def test_nearest_filled_takes_the_closest_valid_depth():
    from taichi_gs.stages.deblur.density import nearest_filled

    depth = np.zeros((5, 7))
    depth[:, 0], depth[:, 6] = 1.0, 3.0
    filled = nearest_filled(depth)
    assert np.all(filled[:, :3] == 1.0) and np.all(filled[:, 4:] == 3.0)
    assert np.all(nearest_filled(np.zeros((3, 3))) == 0.0)


def test_uncovered_pixels_get_gaussians_at_the_nearest_depth():
    from taichi_gs.kernels import runtime
    from taichi_gs.splats import Splats, logit, rgb_to_sh_dc
    from taichi_gs.stages.deblur import fill_uncovered
    from taichi_gs.stages.deblur.model import BlurScene

    runtime.init()
    w, h, f = 40, 30, 40.0
    K = np.array([[f, 0, 19.5], [0, f, 14.5], [0, 0, 1]])
    ys, xs = np.mgrid[-0.75:0.76:0.05, -1.0:0.01:0.05]  # a wall at z = 2 covering the left half
    n = xs.size
    means = np.stack([xs.ravel(), ys.ravel(), np.full(n, 2.0)], axis=1)
    splats = Splats(means.astype(np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                    np.full((n, 3), np.log(0.04), np.float32), np.full(n, logit(0.9), np.float32),
                    np.tile(rgb_to_sh_dc([0.5, 0.5, 0.5])[None, None], (n, 1, 1)))
    model = BlurScene(splats, K, w, h)
    _, alpha = model.coverage(np.eye(4))
    assert alpha[:, :15].mean() > 0.9 and alpha[:, 25:].mean() < 0.05
    color = np.full((h, w, 3), 0.8, np.float32)
    sensor = np.zeros((h, w), np.float32)  # no sensor depth at all: the wall's rendered depth is used
    added = fill_uncovered(model, color, sensor, np.eye(4), K, 2, 10_000, np.random.default_rng(0))
    assert added == model.count - n and added >= 0.4 * (w * h / 4)
    new = model.arrays()["means"][n:]
    assert np.allclose(new[:, 2], 2.0, atol=0.02) and new[:, 0].max() > 0.5
    # radius: the stride's footprint (sigma = 2 px at the depth), or radius_px's when given
    np.testing.assert_allclose(np.exp(model.arrays()["log_scales"][n:]), np.repeat(2 * new[:, 2:3] / f, 3, axis=1), rtol=0.02)
    narrow = BlurScene(splats, K, w, h)
    fill_uncovered(narrow, color, sensor, np.eye(4), K, 2, 10_000, np.random.default_rng(0), radius_px=0.5)
    np.testing.assert_allclose(np.exp(narrow.arrays()["log_scales"][n:]), np.repeat(0.5 * narrow.arrays()["means"][n:, 2:3] / f, 3, 1),
                               rtol=0.02)
    rgb, _ = model.render(np.eye(4))
    _, alpha = model.coverage(np.eye(4))
    assert alpha[:, 25:].mean() > 0.9 and np.allclose(rgb[:, 30:].mean(), 0.8 * alpha[:, 30:].mean(), atol=0.05)
