"""Stage 3's composed step (BlurScene.step): (1 - l_B) L1 + l_B D-SSIM of the k-view average against
a blurred frame, plus l_D times the masked depth L1 of the mid-exposure view, back-propagated to
the Gaussians and to both exposure offsets. Checked against central finite differences in float64
of a loss written independently here in NumPy (L1, D-SSIM with the 3DGS window and zero padding,
masked depth L1, the k-view mean), and BlurScene's own float32 gradients against the float64 ones."""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti

from taichi_gs.geometry import raster_intrinsics, se3_exp, virtual_pose
from taichi_gs.kernels import runtime
from taichi_gs.render import Camera, Rasterizer
from taichi_gs.splats import Splats
from taichi_gs.stages.deblur.model import BlurScene, exposure_taus

WIDTH, HEIGHT = 40, 32
K = np.array([[38.0, 0.0, 19.3], [0.0, 37.0, 15.6], [0.0, 0.0, 1.0]])  # OpenCV convention
BASE = se3_exp(np.array([0.05, -0.08, 0.03, 0.04, -0.03, 0.02]))
D_START = np.array([-0.03, 0.012, -0.008, 0.01, -0.015, 0.006])
D_END = np.array([0.025, -0.01, 0.012, -0.012, 0.018, -0.004])
K_VIEWS, LAMBDA_DSSIM, LAMBDA_DEPTH = 3, 0.2, 0.3
STEPS = (1e-6, 2.5e-7)  # second step for entries whose first straddles a cut-off jump (see test_render)


def _scene(seed: int, n: int = 30) -> Splats:
    rng = np.random.default_rng(seed)
    cam = np.stack([rng.uniform(-1.1, 1.1, n), rng.uniform(-0.9, 0.9, n), rng.uniform(2.5, 4.0, n)], axis=1)
    means = cam @ BASE[:3, :3].T + BASE[:3, 3]
    return Splats(means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.08, 0.3, (n, 3))), rng.normal(0.5, 1.0, n),
                  rng.normal(size=(n, 4, 3)) * 0.5)


def _window() -> np.ndarray:
    x = np.arange(11) - 5.0
    w = np.exp(-x**2 / (2 * 1.5**2))
    return w / w.sum()


def _gaussian_blur(img: np.ndarray) -> np.ndarray:
    """Separable 11-tap Gaussian (sigma 1.5) over the first two axes, zero padding."""
    w = _window()
    h, wd = img.shape[:2]
    padded = np.pad(img, ((5, 5), (5, 5), (0, 0)))
    rows = sum(w[i] * padded[:, i:i + wd] for i in range(11))
    return sum(w[i] * rows[i:i + h] for i in range(11))


def _dssim(x: np.ndarray, y: np.ndarray) -> float:
    c1, c2 = 0.01**2, 0.03**2
    mu1, mu2 = _gaussian_blur(x), _gaussian_blur(y)
    s11 = _gaussian_blur(x * x) - mu1**2
    s22 = _gaussian_blur(y * y) - mu2**2
    s12 = _gaussian_blur(x * y) - mu1 * mu2
    ssim = (2 * mu1 * mu2 + c1) * (2 * s12 + c2) / ((mu1**2 + mu2**2 + c1) * (s11 + s22 + c2))
    return float(1.0 - ssim.mean())


def _loss_f64(gaussians, rasterizer: Rasterizer, frame, depth, d_start, d_end, colour=None) -> float:
    """The stage-3 loss of one frame, from float64 renders, in NumPy (``colour``: the frame's 3 x 4
    affine transform applied to the k-view mean)."""
    taus = exposure_taus(K_VIEWS)
    mid = int(np.argmin(np.abs(taus - 0.5)))
    rgbs, depths = [], []
    for tau in taus:
        camera = Camera(raster_intrinsics(K), virtual_pose(BASE, d_start, d_end, tau), WIDTH, HEIGHT)
        view = rasterizer.forward(gaussians, camera)
        rgbs.append(view.rgb.to_numpy())
        depths.append(view.depth.to_numpy())
    blurred = np.mean(rgbs, axis=0)
    if colour is not None:
        blurred = blurred @ colour[:, :3].T + colour[:, 3]
    l1 = np.abs(blurred - frame).mean()
    valid = depth > 0
    depth_l1 = np.abs(depths[mid] - depth)[valid].sum() / max(valid.sum(), 1)
    return (1 - LAMBDA_DSSIM) * l1 + LAMBDA_DSSIM * _dssim(blurred, frame) + LAMBDA_DEPTH * depth_l1


def _targets(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A blurred frame (another scene seen over another exposure, plus noise) and a depth map with holes."""
    rng = np.random.default_rng(seed)
    other = BlurScene(_scene(seed + 100), K, WIDTH, HEIGHT)
    frame = other.render_blurred(BASE, 0.7 * D_START, 1.3 * D_END, 5) + rng.normal(0, 0.05, (HEIGHT, WIDTH, 3))
    _, depth = other.render(virtual_pose(BASE, D_START, D_END, 0.5))
    depth = np.where(rng.uniform(size=depth.shape) < 0.3, 0.0, depth + rng.normal(0, 0.1, depth.shape))
    return frame.astype(np.float32), np.maximum(depth, 0.0).astype(np.float32)


def _f64_blur_scene(splats: Splats) -> BlurScene:
    """BlurScene itself, with its Gaussians and rasterizer in float64."""
    model = BlurScene(splats, K, WIDTH, HEIGHT, precision="f64")
    assert model.gaussians.dtype == ti.f64
    return model


def _relative_error(analytic: float, numeric: float, scale: float) -> float:
    return abs(analytic - numeric) / max(abs(numeric), 1e-3 * scale)


def _fd_error(analytic: float, f, scale: float) -> float:
    """Relative error of a central difference; the second step is tried when the first disagrees."""
    errors = []
    for h in STEPS:
        errors.append(_relative_error(analytic, (f(h) - f(-h)) / (2 * h), scale))
        if errors[-1] <= 1e-5:
            break
    return min(errors)


@pytest.fixture(scope="module")
def problem():
    runtime.init()
    frame, depth = _targets(5)
    return _scene(4), frame, depth


def _f64_step(splats, frame, depth):
    model = _f64_blur_scene(splats)
    step = model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, LAMBDA_DSSIM, LAMBDA_DEPTH, rates=None)
    return model, step, model.gaussians.download(grads=True)


def test_stage3_step_gradients_match_finite_differences(problem):
    splats, frame, depth = problem
    model, step, grads = _f64_step(splats, frame, depth)
    params = model.arrays()
    frame64, depth64 = frame.astype(np.float64), depth.astype(np.float64)

    def loss(arrays=None, d_start=D_START, d_end=D_END) -> float:
        model.gaussians.upload(**(arrays or params))
        return _loss_f64(model.gaussians, model.rasterizer, frame64, depth64, d_start, d_end)

    # the loss value BlurScene reports is the same function
    reported = (1 - LAMBDA_DSSIM) * step.losses["l1"] + LAMBDA_DSSIM * step.losses["dssim"] \
        + LAMBDA_DEPTH * step.losses["depth"]
    assert reported == pytest.approx(loss(), rel=1e-9)
    assert step.losses["dssim"] > 0.05 and step.losses["depth"] > 0.05, "every term should contribute"

    # Gaussians seen by the mid view with a non-trivial gradient; every parameter of each
    rng = np.random.default_rng(1)
    seen = np.flatnonzero(np.abs(grads["means"]).sum(axis=1) > 1e-6 * np.abs(grads["means"]).max())
    assert len(seen) >= 10
    sample = rng.choice(seen, 6, replace=False)
    errors: dict[str, float] = {}
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        scale = float(np.abs(grads[name][sample]).max())
        assert scale > 0, name
        worst = 0.0
        for i in sample:
            for idx in np.ndindex(params[name].shape[1:]):
                entry = (i, *idx)

                def f(h, name=name, entry=entry):
                    moved = dict(params)
                    moved[name] = params[name].copy()
                    moved[name][entry] += h
                    return loss(moved)

                worst = max(worst, _fd_error(float(grads[name][entry]), f, scale))
        errors[name] = worst
    loss()  # restore

    for which, analytic in (("d_start", step.grad_start), ("d_end", step.grad_end)):
        assert np.abs(analytic).max() > 0
        scale = float(np.abs(analytic).max())
        worst = 0.0
        for c in range(6):
            e = np.eye(6)[c]

            def g(h, e=e, which=which):
                return loss(d_start=D_START + h * e, d_end=D_END) if which == "d_start" \
                    else loss(d_start=D_START, d_end=D_END + h * e)

            worst = max(worst, _fd_error(float(analytic[c]), g, scale))
        errors[which] = worst
    assert max(errors.values()) < 1e-4, errors


def test_the_depth_instant_steps_gradients_match_finite_differences(problem):
    """[ours] ``depth_instant_step``: the masked depth L1 of a render at the mid-exposure pose (of an exposure bowed by
    a bend) moved by a twist, checked against central differences of that loss written here from float64 renders."""
    splats, _, depth = problem
    model = _f64_blur_scene(splats)
    shift = np.array([0.01, -0.02, 0.015, -0.01, 0.02, 0.005])
    bend = np.array([0.004, 0.003, -0.002, 0.003, -0.004, 0.002])
    loss_value, g_start, g_end, g_bend = model.depth_instant_step(depth, BASE, D_START, D_END, shift, LAMBDA_DEPTH,
                                                                  bend)
    valid = depth > 0

    def loss(d_start=D_START, d_end=D_END, b=bend) -> float:
        pose = BASE @ se3_exp(0.5 * (d_start + d_end) + shift + b)  # 4 tau (1 - tau) = 1 at mid-exposure
        rendered = model.rasterizer.forward(model.gaussians, Camera(raster_intrinsics(K), pose, WIDTH, HEIGHT),
                                            with_colour=False).depth.to_numpy()
        return LAMBDA_DEPTH * np.abs(rendered - depth)[valid].sum() / valid.sum()

    assert loss_value == pytest.approx(loss(), rel=1e-9) and loss_value > 0.01
    moved = {"d_start": lambda h, e: loss(d_start=D_START + h * e), "d_end": lambda h, e: loss(d_end=D_END + h * e),
             "bend": lambda h, e: loss(b=bend + h * e)}
    for which, analytic in (("d_start", g_start), ("d_end", g_end), ("bend", g_bend)):
        scale = float(np.abs(analytic).max())
        assert scale > 0
        for c in range(6):
            e = np.eye(6)[c]

            def g(h, e=e, which=which):
                return moved[which](h, e)

            assert _fd_error(float(analytic[c]), g, scale) < 1e-4, (which, c)


def test_float32_step_agrees_with_float64(problem):
    """The production (float32) BlurScene.step gives the float64 gradients to float32 accuracy."""
    splats, frame, depth = problem
    model32 = BlurScene(splats, K, WIDTH, HEIGHT)
    assert model32.gaussians.dtype == ti.f32
    step32 = model32.step(frame, depth, BASE, D_START, D_END, K_VIEWS, LAMBDA_DSSIM, LAMBDA_DEPTH, rates=None)
    grads32 = model32.gaussians.download(grads=True)
    _, step64, grads64 = _f64_step(splats, frame, depth)
    for name in ("l1", "dssim", "depth"):
        assert step32.losses[name] == pytest.approx(step64.losses[name], rel=1e-4, abs=1e-6), name
    pairs = {name: (grads32[name], grads64[name]) for name in grads64}
    pairs.update(d_start=(step32.grad_start, step64.grad_start), d_end=(step32.grad_end, step64.grad_end))
    for name, (g32, g64) in pairs.items():
        assert np.linalg.norm(g64) > 0, name
        assert np.linalg.norm(g32 - g64) <= 1e-4 * np.linalg.norm(g64), name


def test_stage3_step_with_a_colour_transform_matches_finite_differences(problem):
    """With a frame's affine colour transform (done on device): the transform's own gradient, the
    exposure gradients and a few colour gradients through it, the loss and the PSNR it reports."""
    splats, frame, depth = problem
    colour = np.hstack([np.eye(3), np.zeros((3, 1))]) + 0.05 * np.random.default_rng(7).normal(size=(3, 4))
    model = _f64_blur_scene(splats)
    step = model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, LAMBDA_DSSIM, LAMBDA_DEPTH, rates=None,
                      colour=colour)
    grads = model.gaussians.download(grads=True)
    params = model.arrays()
    frame64, depth64 = frame.astype(np.float64), depth.astype(np.float64)

    def loss(arrays=None, M=colour, d_start=D_START) -> float:
        model.gaussians.upload(**(arrays or params))
        return _loss_f64(model.gaussians, model.rasterizer, frame64, depth64, d_start, D_END, M)

    reported = (1 - LAMBDA_DSSIM) * step.losses["l1"] + LAMBDA_DSSIM * step.losses["dssim"] \
        + LAMBDA_DEPTH * step.losses["depth"]
    assert reported == pytest.approx(loss(), rel=1e-9)
    reblurred = model.render_blurred(BASE, D_START, D_END, K_VIEWS).astype(np.float64) @ colour[:, :3].T + colour[:, 3]
    mse = np.mean((np.clip(reblurred, 0, 1) - frame64) ** 2)
    assert step.psnr == pytest.approx(-10 * np.log10(mse), rel=1e-5)

    errors = {}
    scale = float(np.abs(step.grad_colour).max())
    for idx in np.ndindex(3, 4):
        def f(h, idx=idx):
            moved = colour.copy()
            moved[idx] += h
            return loss(M=moved)
        errors[f"colour{idx}"] = _fd_error(float(step.grad_colour[idx]), f, scale)
    scale = float(np.abs(step.grad_start).max())
    for c in range(6):
        def exposure(h, c=c):
            return loss(d_start=D_START + h * np.eye(6)[c])
        errors[f"d_start[{c}]"] = _fd_error(float(step.grad_start[c]), exposure, scale)
    seen = np.flatnonzero(np.abs(grads["colors"][:, 0]).sum(axis=1) > 0)
    scale = float(np.abs(grads["colors"][seen, 0]).max())
    for i in seen[:4]:
        for c in range(3):
            def g(h, i=i, c=c):
                moved = dict(params)
                moved["colors"] = params["colors"].copy()
                moved["colors"][i, 0, c] += h
                return loss(moved)
            errors[f"colors[{i}, {c}]"] = _fd_error(float(grads["colors"][i, 0, c]), g, scale)
    loss()  # restore
    assert max(errors.values()) < 1e-4, errors


def test_a_sourced_mask_leaves_unseen_pixels_out_of_the_step(problem):
    """With a sourced-pixel mask (an undistorted frame's unsourced border), what the frame holds there
    changes neither the losses nor any gradient; without the mask it does."""
    splats, frame, depth = problem
    sourced = np.ones((HEIGHT, WIDTH), bool)
    sourced[:4], sourced[:, -6:] = False, False
    smeared = frame.copy()
    smeared[~sourced] = np.clip(frame[~sourced] + 0.4, 0, 1)

    def step(image, mask):
        model = BlurScene(splats, K, WIDTH, HEIGHT, precision="f64", sourced=mask)
        result = model.step(image, depth, BASE, D_START, D_END, K_VIEWS, LAMBDA_DSSIM, LAMBDA_DEPTH, rates=None)
        return result, model.gaussians.download(grads=True)

    (masked, grads), (masked_smeared, grads_smeared) = step(frame, sourced), step(smeared, sourced)
    assert masked.losses == pytest.approx(masked_smeared.losses, rel=1e-12)
    np.testing.assert_allclose(masked.grad_start, masked_smeared.grad_start, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(masked.grad_end, masked_smeared.grad_end, rtol=1e-10, atol=1e-14)
    for name in grads:
        np.testing.assert_allclose(grads[name], grads_smeared[name], rtol=1e-10, atol=1e-14)
    plain, _ = step(frame, None)
    plain_smeared, _ = step(smeared, None)
    assert plain.losses["l1"] != pytest.approx(plain_smeared.losses["l1"], rel=1e-3)
    assert masked.losses["l1"] != pytest.approx(plain.losses["l1"], rel=1e-3)


def _dc_derivative_over_sh_c0(splats: Splats, i: int, value_of) -> float:
    """Sum over channels c of d value_of(scene, c) / d (Gaussian i's degree-0 colour c), by central
    differences of float64 scenes, over 3 SH_C0: a Gaussian's blending weight where value_of is linear in
    the rendered colour."""
    from taichi_gs.splats import SH_C0

    h, total = 0.05, 0.0
    for c in range(3):
        moved = []
        for sign in (1, -1):
            sh = splats.sh.copy()
            sh[i, 0, c] += sign * h
            other = BlurScene(Splats(splats.means, splats.quats, splats.log_scales, splats.opacity_logits, sh),
                              K, WIDTH, HEIGHT, precision="f64")
            moved.append(value_of(other, c))
        total += (moved[0] - moved[1]) / (2 * h)
    return total / (3 * SH_C0)


def test_error_mass_is_each_gaussians_blending_weight_times_the_error(problem):
    """error_mass(i) = sum over pixels of w_i(p) |e(p)| (k-view mean), the derivative of
    sum_p |e(p)| rgb(p) (the error held fixed) w.r.t. the Gaussian's colour over SH_C0: checked by
    differences of renders (the blurred image is linear in the colour)."""
    splats, frame, _ = problem
    sourced = np.ones((HEIGHT, WIDTH), bool)
    sourced[:, :5] = False
    model = BlurScene(splats, K, WIDTH, HEIGHT, precision="f64", sourced=sourced)
    mass = model.error_mass(frame, BASE, D_START, D_END, K_VIEWS)
    error = np.abs(model.render_blurred(BASE, D_START, D_END, K_VIEWS) - frame).sum(axis=2) * sourced
    assert mass.shape == (len(splats.means),) and (mass >= 0).all() and mass.max() > 0
    for i in np.argsort(-mass)[:4].tolist() + [int(np.argmin(mass))]:
        expected = _dc_derivative_over_sh_c0(
            splats, i, lambda other, c: (error * other.render_blurred(BASE, D_START, D_END, K_VIEWS)[..., c]).sum())
        assert mass[i] == pytest.approx(expected, rel=2e-3, abs=1e-3 * mass.max())


def test_blending_weights_are_each_gaussians_weight_summed_over_the_sourced_pixels_of_sharp_renders(problem):
    """blending_weights(i) = sum over poses and sourced pixels of w_i(p), the derivative of the sourced pixels'
    colour sum w.r.t. the Gaussian's degree-0 colour over SH_C0: checked by differences of renders."""
    splats = problem[0]
    sourced = np.ones((HEIGHT, WIDTH), bool)
    sourced[:, -6:] = False
    poses = [BASE, virtual_pose(BASE, D_START, D_END, 1.0)]
    model = BlurScene(splats, K, WIDTH, HEIGHT, precision="f64", sourced=sourced)
    weights = model.blending_weights(poses)
    assert weights.shape == (len(splats.means),) and (weights >= 0).all() and weights.max() > 0
    for i in np.argsort(-weights)[:3].tolist() + [int(np.argsort(weights)[len(weights) // 2])]:
        expected = _dc_derivative_over_sh_c0(
            splats, i, lambda other, c: sum((other.render(pose)[0][..., c] * sourced).sum() for pose in poses))
        assert weights[i] == pytest.approx(expected, rel=2e-3, abs=1e-3 * weights.max())
