"""Stage 2's loss (alpha-normalised masked depth L1 + coverage) and its hand-written gradient,
against central finite differences in float64: alone (w.r.t. the rendered depth and transmittance)
and composed with the rasterizer (w.r.t. Gaussian centres, opacities and the camera pose)."""

from __future__ import annotations

import numpy as np
import taichi as ti

from taichi_gs.geometry import se3_exp
from taichi_gs.kernels.splat import Camera, DeviceGaussians, Rasterizer, to_device
from taichi_gs.refine_model import depth_losses

WIDTH, HEIGHT = 40, 32
K = np.array([[36.0, 0.0, 19.6], [0.0, 35.0, 15.8], [0.0, 0.0, 1.0]])
POSE = se3_exp(np.array([0.05, -0.1, 0.02, 0.03, -0.05, 0.02]))
MIN_ALPHA, WEIGHT, COVERAGE = 0.5, 1.3, 0.4


def _total(depth, transmittance, target) -> float:
    d, c, _, _ = depth_losses(depth, transmittance, target, MIN_ALPHA, WEIGHT, COVERAGE)
    return WEIGHT * d + COVERAGE * c


def test_depth_loss_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    transmittance = rng.uniform(0.0, 0.8, (HEIGHT, WIDTH))
    alpha = 1 - transmittance
    target = rng.uniform(1.0, 3.0, (HEIGHT, WIDTH)) * (rng.uniform(size=(HEIGHT, WIDTH)) > 0.2)
    depth = (target + rng.normal(0, 0.2, target.shape)) * alpha  # blended depth = alpha x surface depth
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
        _, _, d_depth, d_alpha = depth_losses(depth, transmittance, self.target, MIN_ALPHA, WEIGHT, COVERAGE)
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
