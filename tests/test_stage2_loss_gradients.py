"""Stage 2's loss (alpha-normalised masked depth L1 + coverage) and its hand-written gradient: a NumPy
reference against central finite differences in float64, the device kernel
(``losses.normalised_depth_l1_and_coverage``) against that reference, and the kernel composed with the
rasterizer against finite differences (w.r.t. Gaussian centres, opacities and the camera pose)."""

from __future__ import annotations

import numpy as np
import taichi as ti

from taichi_gs.geometry import se3_exp
from taichi_gs.kernels import losses, runtime
from taichi_gs.kernels.splat import Camera, DeviceGaussians, Rasterizer, to_device

WIDTH, HEIGHT = 40, 32
K = np.array([[36.0, 0.0, 19.6], [0.0, 35.0, 15.8], [0.0, 0.0, 1.0]])
POSE = se3_exp(np.array([0.05, -0.1, 0.02, 0.03, -0.05, 0.02]))
MIN_ALPHA, WEIGHT, COVERAGE = 0.5, 1.3, 0.4


def depth_losses(depth: np.ndarray, transmittance: np.ndarray, target: np.ndarray, min_alpha: float,
                 weight: float, coverage_weight: float) -> tuple[float, float, np.ndarray, np.ndarray]:
    """Reference in NumPy: (depth term, coverage, d/d blended depth, d/d alpha) of
    ``weight * depth term + coverage_weight * coverage`` (see ``losses.normalised_depth_l1_and_coverage``)."""
    alpha = 1.0 - transmittance
    valid = target > 0
    mask = valid & (alpha >= min_alpha)
    count, n_valid = max(int(mask.sum()), 1), max(int(valid.sum()), 1)
    safe = np.where(mask, alpha, 1.0)
    residual = np.where(mask, depth / safe - target, 0.0)
    g = weight * np.sign(residual) / count
    d_alpha = -g * depth / safe**2 - coverage_weight * valid / n_valid
    coverage = float((1.0 - alpha)[valid].sum() / n_valid)
    return float(np.abs(residual).sum() / count), coverage, g / safe, d_alpha


def device_losses(depth: np.ndarray, transmittance: np.ndarray, target: np.ndarray, dtype=ti.f64,
                  grad_depth: np.ndarray | None = None, grad_alpha: np.ndarray | None = None):
    """The kernel's (depth term, coverage, d/d depth, d/d alpha) for NumPy inputs (gradients added to the given
    starting values, zero by default)."""
    runtime.init()
    grads = [to_device(np.zeros_like(depth) if g is None else g, dtype) for g in (grad_depth, grad_alpha)]
    d, c = losses.normalised_depth_l1_and_coverage(to_device(depth, dtype), to_device(transmittance, dtype),
                                                   to_device(target, dtype), *grads, MIN_ALPHA, WEIGHT, COVERAGE)
    return d, c, grads[0].to_numpy(), grads[1].to_numpy()


def _random_view(rng, height=HEIGHT, width=WIDTH):
    """(depth, transmittance, target): about 20% of pixels without input depth, some under min_alpha."""
    transmittance = rng.uniform(0.0, 0.8, (height, width))
    target = rng.uniform(1.0, 3.0, (height, width)) * (rng.uniform(size=(height, width)) > 0.2)
    depth = (target + rng.normal(0, 0.2, target.shape)) * (1 - transmittance)  # alpha x surface depth
    return depth, transmittance, target


def test_the_device_kernel_matches_the_reference():
    rng = np.random.default_rng(7)
    depth, transmittance, target = _random_view(rng, 37, 53)  # rows longer than one GPU span
    transmittance[0, :5] = 1.0 - MIN_ALPHA  # alpha exactly at the threshold counts
    depth[1, :5] = target[1, :5] * (1.0 - transmittance[1, :5])  # residual 0: no depth gradient
    expected = depth_losses(depth, transmittance, target, MIN_ALPHA, WEIGHT, COVERAGE)
    start = rng.normal(size=(2,) + depth.shape)
    got = device_losses(depth, transmittance, target, grad_depth=start[0], grad_alpha=start[1])
    assert np.isclose(got[0], expected[0], rtol=1e-12) and np.isclose(got[1], expected[1], rtol=1e-12)
    np.testing.assert_allclose(got[2] - start[0], expected[2], rtol=1e-10, atol=1e-15)  # added, not written
    np.testing.assert_allclose(got[3] - start[1], expected[3], rtol=1e-10, atol=1e-15)
    depth, transmittance, target = _random_view(rng, 37, 53)  # float32 (production): no exact ties
    expected = depth_losses(depth, transmittance, target, MIN_ALPHA, WEIGHT, COVERAGE)
    f32 = device_losses(depth, transmittance, target, dtype=ti.f32)
    assert np.isclose(f32[0], expected[0], rtol=1e-5) and np.isclose(f32[1], expected[1], rtol=1e-5)
    np.testing.assert_allclose(f32[2], expected[2], rtol=1e-4, atol=1e-9)
    np.testing.assert_allclose(f32[3], expected[3], rtol=1e-4, atol=1e-9)


def test_a_view_without_input_depth_has_no_loss():
    depth, transmittance, target = _random_view(np.random.default_rng(8))
    d, c, g_depth, g_alpha = device_losses(depth, transmittance, np.zeros_like(target))
    assert d == 0.0 and c == 0.0 and not g_depth.any() and not g_alpha.any()


def _total(depth, transmittance, target) -> float:
    d, c, _, _ = depth_losses(depth, transmittance, target, MIN_ALPHA, WEIGHT, COVERAGE)
    return WEIGHT * d + COVERAGE * c


def test_depth_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    depth, transmittance, target = _random_view(rng)
    _, _, d_depth, d_alpha = depth_losses(depth, transmittance, target, MIN_ALPHA, WEIGHT, COVERAGE)
    h = 1e-7
    for name, base, analytic, sign in (("depth", depth, d_depth, 1.0), ("alpha", transmittance, d_alpha, -1.0)):
        for index in [tuple(i) for i in rng.integers(0, [HEIGHT, WIDTH], (40, 2))]:
            moved = [base.copy(), base.copy()]
            moved[0][index] += h
            moved[1][index] -= h
            args = ((m, transmittance, target) if name == "depth" else (depth, m, target) for m in moved)
            plus, minus = (_total(*a) for a in args)
            numeric = sign * (plus - minus) / (2 * h)  # d/d alpha = -d/d transmittance
            assert abs(numeric - analytic[index]) <= 1e-6 * max(1.0, abs(numeric)), (name, index)


class _Stage2LossF64:
    """The stage-2 loss of one view, rendered in float64, as a function of centres, logits and pose."""

    def __init__(self, means: np.ndarray, logits: np.ndarray, scale: float, target: np.ndarray):
        n = len(means)
        self.log_scales = np.full(n, np.log(scale))
        self.colors = np.zeros((n, 1, 3))
        self.gs = DeviceGaussians.from_numpy(means, None, self.log_scales, logits, self.colors, isotropic=True,
                                             dtype=ti.f64)
        self.rast = Rasterizer(ti.f64)
        self.target = target

    def _render(self, means, logits, pose):
        self.gs.upload(means=means, opacity_logits=logits)
        view = self.rast.forward(self.gs, Camera(K, pose, WIDTH, HEIGHT))
        return view, view.depth.to_numpy(), view.transmittance.to_numpy()

    def __call__(self, means, logits, pose) -> float:
        _, depth, transmittance = self._render(means, logits, pose)
        return _total(depth, transmittance, self.target)

    def gradients(self, means, logits, pose):
        view, depth, transmittance = self._render(means, logits, pose)
        _, _, d_depth, d_alpha = device_losses(depth, transmittance, self.target)
        self.gs.zero_grad()
        pose_grad = self.rast.backward(self.gs, view, d_depth=to_device(d_depth, ti.f64),
                                       d_alpha=to_device(d_alpha, ti.f64))
        grads = self.gs.download(grads=True)
        return grads["means"], grads["opacity_logits"], pose_grad


def _agrees(analytic: float, f, h: float) -> bool:
    """Central difference at two steps (a step may straddle a mask or cut-off jump); either agreeing passes."""
    for step in (h, h / 4):
        numeric = (f(step) - f(-step)) / (2 * step)
        if abs(numeric - analytic) <= 2e-5 * max(abs(numeric), 1e-3):
            return True
    return False


def test_stage2_loss_through_the_rasterizer_matches_finite_differences():
    rng = np.random.default_rng(3)
    n = 60
    cam_points = np.stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-0.9, 0.9, n), rng.uniform(2.5, 3.5, n)], axis=1)
    means = cam_points @ POSE[:3, :3].T + POSE[:3, 3]
    logits = rng.normal(1.0, 0.5, n)
    target = np.full((HEIGHT, WIDTH), 3.0) + rng.normal(0, 0.1, (HEIGHT, WIDTH))
    target[:4] = 0.0  # rows without input depth
    loss = _Stage2LossF64(means, logits, scale=0.25, target=target)
    d_means, d_logits, d_pose = loss.gradients(means, logits, POSE)
    assert np.abs(d_means).max() > 0 and np.abs(d_pose).max() > 0

    checked = 0
    for i in rng.choice(n, 12, replace=False):
        for axis in range(3):
            def f(step, i=i, axis=axis):
                moved = means.copy()
                moved[i, axis] += step
                return loss(moved, logits, POSE)
            assert _agrees(d_means[i, axis], f, 1e-6), ("means", i, axis)
            checked += 1

        def g(step, i=i):
            moved = logits.copy()
            moved[i] += step
            return loss(means, moved, POSE)
        assert _agrees(d_logits[i], g, 1e-6), ("logit", i)

    for k in range(6):  # the pose gradient is w.r.t. a left-multiplied twist of camera-to-world
        def p(step, k=k):
            twist = np.zeros(6)
            twist[k] = step
            return loss(means, logits, se3_exp(twist) @ POSE)
        assert _agrees(d_pose[k], p, 1e-6), ("pose", k)
    assert checked == 36
