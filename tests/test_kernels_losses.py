"""Loss, blur and Adam kernels against NumPy references and central differences (float64)."""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti
from scipy.ndimage import correlate1d

from taichi_gs.kernels import blur, launch_budget, losses, runtime
from taichi_gs.kernels.optim import Adam
from taichi_gs.kernels.splat import to_device

runtime.init("cpu")


def device(arr, dtype=ti.f64):
    return to_device(np.asarray(arr, dtype=np.float64), dtype)


def zeros(shape, dtype=ti.f64):
    return device(np.zeros(shape), dtype)


def numpy_ssim_map(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """SSIM map with the 3DGS window (11 taps, sigma 1.5, zero padding), per channel."""
    t = np.arange(11) - 5
    w = np.exp(-(t**2) / (2 * 1.5**2))
    w /= w.sum()

    def blur2(a):
        return correlate1d(correlate1d(a, w, axis=0, mode="constant"), w, axis=1, mode="constant")

    mu1, mu2 = blur2(x), blur2(y)
    s11 = blur2(x * x) - mu1**2
    s22 = blur2(y * y) - mu2**2
    s12 = blur2(x * y) - mu1 * mu2
    c1, c2 = 0.01**2, 0.03**2
    return (2 * mu1 * mu2 + c1) * (2 * s12 + c2) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))


def numpy_ssim(x: np.ndarray, y: np.ndarray) -> float:
    """Mean of :func:`numpy_ssim_map`."""
    return float(numpy_ssim_map(x, y).mean())


def fd_gradient(f, x: np.ndarray, indices, h: float = 1e-6) -> np.ndarray:
    out = []
    for idx in indices:
        xp, xm = x.copy(), x.copy()
        xp[idx] += h
        xm[idx] -= h
        out.append((f(xp) - f(xm)) / (2 * h))
    return np.array(out)


@pytest.fixture
def images():
    rng = np.random.default_rng(0)
    return rng.uniform(0, 1, (13, 17, 3)), rng.uniform(0, 1, (13, 17, 3))


def test_l1_value_and_gradient(images) -> None:
    pred, target = images
    grad = device(np.full(pred.shape, 0.5))
    value = losses.l1(device(pred), device(target), grad, weight=2.0)
    assert value == pytest.approx(np.abs(pred - target).mean(), rel=1e-12)
    want = 0.5 + 2.0 * np.sign(pred - target) / pred.size
    np.testing.assert_allclose(grad.to_numpy(), want, rtol=1e-12)
    stretched = 1.4 * pred - 0.2  # partly outside [0, 1]: the PSNR's MSE clips the prediction
    l1, mse = losses.l1_and_clipped_mse(device(stretched), device(target), device(np.zeros(pred.shape)))
    assert l1 == pytest.approx(np.abs(stretched - target).mean(), rel=1e-12)
    assert mse == pytest.approx(np.mean((np.clip(stretched, 0, 1) - target) ** 2), rel=1e-12)


def test_masked_depth_l1_ignores_invalid_targets() -> None:
    rng = np.random.default_rng(1)
    pred = rng.uniform(0.5, 3, (12, 10))
    target = rng.uniform(0.5, 3, (12, 10))
    target[rng.uniform(size=target.shape) < 0.3] = 0.0
    mask = target > 0
    grad = zeros(pred.shape)
    value = losses.masked_depth_l1(device(pred), device(target), grad, weight=3.0)
    assert value == pytest.approx(np.abs(pred - target)[mask].mean(), rel=1e-12)
    np.testing.assert_allclose(grad.to_numpy(), 3.0 * mask * np.sign(pred - target) / mask.sum(), rtol=1e-12)
    empty = zeros(pred.shape)
    assert losses.masked_depth_l1(device(pred), zeros(pred.shape), empty) == 0.0
    assert not empty.to_numpy().any()


def test_dssim_value_and_gradient(images) -> None:
    pred, target = images
    target = 0.6 * pred + 0.4 * target  # correlated, so SSIM is far from 0
    grad = zeros(pred.shape)
    value = losses.dssim(device(pred), device(target), grad)
    assert value == pytest.approx(1 - numpy_ssim(pred, target), rel=1e-10)
    rng = np.random.default_rng(2)
    indices = [tuple(rng.integers(0, s) for s in pred.shape) for _ in range(25)] + [(0, 0, 0), (12, 16, 2)]
    numeric = fd_gradient(lambda x: 1 - numpy_ssim(x, target), pred, indices)
    analytic = np.array([grad.to_numpy()[i] for i in indices])
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("shape", [(4, 7, 3), (11, 12, 1), (12, 30, 3)],
                         ids=["window-wider-than-image", "one-interior-row", "wide-interior"])
def test_dssim_near_and_away_from_the_edges_matches_the_reference(shape) -> None:
    """The kernel skips edge checks away from the edges: images with no, one and many interior rows
    and columns give the reference's value and gradient, at corners, edges and centre."""
    rng = np.random.default_rng(5)
    pred = rng.uniform(0, 1, shape)
    target = 0.6 * pred + 0.4 * rng.uniform(0, 1, shape)
    grad = zeros(shape)
    value = losses.dssim(device(pred), device(target), grad, weight=0.5)
    assert value == pytest.approx(1 - numpy_ssim(pred, target), rel=1e-10)
    h, w, c = shape
    indices = [(v, u, k) for v in {0, h // 2, h - 1} for u in {0, 5, w // 2, w - 6, w - 1} if 0 <= u < w
               for k in {0, c - 1}]
    numeric = 0.5 * fd_gradient(lambda x: 1 - numpy_ssim(x, target), pred, indices)
    analytic = np.array([grad.to_numpy()[i] for i in indices])
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-9)


def test_dssim_float32_matches_float64(images) -> None:
    pred, target = images
    g32, g64 = zeros(pred.shape, ti.f32), zeros(pred.shape)
    v32 = losses.dssim(device(pred, ti.f32), device(target, ti.f32), g32)
    v64 = losses.dssim(device(pred), device(target), g64)
    assert v32 == pytest.approx(v64, abs=1e-5)
    np.testing.assert_allclose(g32.to_numpy(), g64.to_numpy(), atol=1e-7)


def test_opacity_binarization_value_and_gradient() -> None:
    rng = np.random.default_rng(3)
    logits = rng.normal(size=2500) * 2
    grad = zeros(logits.shape)

    def f(z):
        o = 1 / (1 + np.exp(-z))
        return float((o**2 * (1 - o) ** 2).sum())

    value = losses.opacity_binarization(device(logits), grad, len(logits), weight=0.5)
    assert value == pytest.approx(f(logits), rel=1e-12)
    picked = np.arange(0, 2500, 97)
    numeric = fd_gradient(f, logits[picked], list(np.ndindex(len(picked))))  # the sum is separable
    np.testing.assert_allclose(grad.to_numpy()[picked], 0.5 * numeric, rtol=1e-6, atol=1e-9)


def test_blur_average_and_spread() -> None:
    rng = np.random.default_rng(4)
    views = [rng.uniform(size=(6, 5, 3)) for _ in range(4)]
    out = zeros((6, 5, 3))
    blur.average([device(v) for v in views], out)
    np.testing.assert_allclose(out.to_numpy(), np.mean(views, axis=0), rtol=1e-12)
    g = rng.normal(size=(6, 5, 3))
    share = zeros(g.shape)
    blur.spread(device(g), 4, share)
    np.testing.assert_allclose(share.to_numpy(), g / 4, rtol=1e-12)
    with pytest.raises(ValueError):
        blur.average([device(views[0]), zeros((2, 2, 3))], out)


def test_blur_average_takes_one_launch_per_sixteen_views() -> None:
    rng = np.random.default_rng(5)
    views = [rng.uniform(size=(6, 5, 3)) for _ in range(blur.VIEWS_PER_LAUNCH + 4)]
    out = zeros((6, 5, 3))
    for k in (blur.VIEWS_PER_LAUNCH, len(views)):
        on_device = [device(v) for v in views[:k]]
        with launch_budget.counting() as budget:
            blur.average(on_device, out)
        assert budget.launches == -(-k // blur.VIEWS_PER_LAUNCH)
        np.testing.assert_allclose(out.to_numpy(), np.mean(views[:k], axis=0), rtol=1e-12)


def test_adam_matches_numpy_reference() -> None:
    rng = np.random.default_rng(5)
    p0 = rng.normal(size=(7, 3))
    params = {"x": device(p0), "y": device(np.ones(7))}
    grads = {"x": zeros((7, 3)), "y": zeros(7)}
    opt = Adam(params, grads, {"x": 0.01}, betas=(0.9, 0.999), eps=1e-8)
    p, m, v = p0.copy(), np.zeros_like(p0), np.zeros_like(p0)
    for t in range(1, 6):
        g = rng.normal(size=(7, 3))
        grads["x"].from_numpy(g)
        opt.step()
        m = 0.9 * m + 0.1 * g
        v = 0.999 * v + 0.001 * g * g
        p = p - 0.01 * (m / (1 - 0.9**t)) / (np.sqrt(v / (1 - 0.999**t)) + 1e-8)
    np.testing.assert_allclose(params["x"].to_numpy(), p, rtol=1e-10)
    np.testing.assert_array_equal(params["y"].to_numpy(), np.ones(7))
    before = params["x"].to_numpy()
    opt.step(n=3)  # only the first rows move
    after = params["x"].to_numpy()
    np.testing.assert_array_equal(after[3:], before[3:])
    assert np.all(after[:3] != before[:3])


def test_adam_over_more_tensors_than_one_launch_takes() -> None:
    """Seven tensors of ranks 1 to 3 (two launches of up to five), each at its own rate, match the NumPy
    reference; a step over the first rows leaves the others where they were."""
    rng = np.random.default_rng(6)
    shapes = {"a": (9,), "b": (9, 3), "c": (9, 4), "d": (9, 1, 3), "e": (9, 4, 3), "f": (9, 2), "g": (9,)}
    rates = {name: 0.01 * (i + 1) for i, name in enumerate(shapes)}
    start = {name: rng.normal(size=shape) for name, shape in shapes.items()}
    params = {name: device(value) for name, value in start.items()}
    grads = {name: zeros(shape) for name, shape in shapes.items()}
    opt = Adam(params, grads, rates, betas=(0.9, 0.999), eps=1e-8)
    expected = {name: [value.copy(), np.zeros_like(value), np.zeros_like(value)] for name, value in start.items()}
    for t in range(1, 4):
        rows = None if t < 3 else 4
        for name, shape in shapes.items():
            g = rng.normal(size=shape)
            grads[name].from_numpy(g)
            p, m, v = expected[name]
            r = slice(None, rows)
            m[r] = 0.9 * m[r] + 0.1 * g[r]
            v[r] = 0.999 * v[r] + 0.001 * g[r] ** 2
            p[r] = p[r] - rates[name] * (m[r] / (1 - 0.9**t)) / (np.sqrt(v[r] / (1 - 0.999**t)) + 1e-8)
        opt.step(n=rows)
    for name in shapes:
        np.testing.assert_allclose(params[name].to_numpy(), expected[name][0], rtol=1e-10, err_msg=name)
        np.testing.assert_allclose(opt.moments[name][1].to_numpy(), expected[name][2], rtol=1e-10, err_msg=name)


def _sourced_mask(shape) -> np.ndarray:
    mask = np.ones(shape[:2], bool)
    mask[:3, :] = False  # an unsourced top strip and left corner, as an undistorted frame has
    mask[:, :2] = False
    return mask


def test_l1_with_a_pixel_mask_averages_over_its_pixels_only(images) -> None:
    pred, target = images
    mask = _sourced_mask(pred.shape)
    weights = losses.pixel_weights(mask, ti.f64)
    grad = zeros(pred.shape)
    l1, mse = losses.l1_and_clipped_mse(device(pred), device(target), grad, weight=2.0, mask=weights)
    assert l1 == pytest.approx(np.abs(pred - target)[mask].mean(), rel=1e-12)
    assert mse == pytest.approx(np.mean((pred - target)[mask] ** 2), rel=1e-12)
    want = 2.0 * mask[..., None] * np.sign(pred - target) / (mask.sum() * 3)
    np.testing.assert_allclose(grad.to_numpy(), want, rtol=1e-12)
    smeared = target.copy()
    smeared[~mask] = 0.5  # what lies outside the mask changes nothing
    assert losses.l1(device(pred), device(smeared), zeros(pred.shape), mask=weights) == pytest.approx(l1, rel=1e-12)
    every_pixel = losses.pixel_weights(np.ones(mask.shape), ti.f64)
    every = losses.l1(device(pred), device(target), zeros(pred.shape), mask=every_pixel)
    assert every == pytest.approx(np.abs(pred - target).mean(), rel=1e-12)


def test_dssim_with_a_pixel_mask_matches_finite_differences(images) -> None:
    pred, target = images
    target = 0.6 * pred + 0.4 * target
    mask = _sourced_mask(pred.shape)

    def masked_ssim(x):
        return float(numpy_ssim_map(x, target)[mask].mean())

    grad = zeros(pred.shape)
    value = losses.dssim(device(pred), device(target), grad, weight=0.7, mask=losses.pixel_weights(mask, ti.f64))
    assert value == pytest.approx(1 - masked_ssim(pred), rel=1e-10)
    rng = np.random.default_rng(4)
    indices = [tuple(rng.integers(0, s) for s in pred.shape) for _ in range(25)] + [(0, 0, 0), (1, 4, 2), (12, 16, 2)]
    numeric = 0.7 * fd_gradient(lambda x: 1 - masked_ssim(x), pred, indices)
    analytic = np.array([grad.to_numpy()[i] for i in indices])
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-9)


def test_a_pixel_mask_must_fit_the_image(images) -> None:
    pred, target = images
    with pytest.raises(ValueError, match="does not fit"):
        losses.l1(device(pred), device(target), zeros(pred.shape), mask=losses.pixel_weights(np.ones((4, 4)), ti.f64))
    with pytest.raises(ValueError, match="non-empty"):
        losses.pixel_weights(np.zeros((13, 17)), ti.f64)
