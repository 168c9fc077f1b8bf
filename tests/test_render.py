"""Rasterizer: forward against a per-pixel NumPy reference, gradients against central finite
differences in float64 (every input and the camera pose), the isotropic variant, the device API.

The checks are plain functions so the CUDA tests can rerun them in a fresh process."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import reference_renderer
from taichi_gs.geometry import se3_exp
from taichi_gs.kernels import runtime
from taichi_gs.render import Camera, DeviceGaussians, Rasterizer, rasterize

WIDTH, HEIGHT = 48, 40
K = np.array([[42.0, 0.0, 24.3], [0.0, 40.0, 19.7], [0.0, 0.0, 1.0]])
POSE = se3_exp(np.array([0.1, -0.2, 0.05, 0.05, 0.1, -0.03]))
BACKGROUND = (0.1, 0.2, 0.3)


def make_scene(seed: int, n: int = 40, n_sh: int = 16, dense: int = 0) -> list[np.ndarray]:
    """Random Gaussians in front of POSE; index 0 sits behind the camera, index 1 far off screen;
    ``dense`` extra small, fairly opaque ones are packed into the tile at pixels [16, 32)^2."""
    rng = np.random.default_rng(seed)
    cam = rng.normal(size=(n, 3)) * [1.2, 1.0, 0.6] + [0.0, 0.0, 4.0]
    cam[0] = [0.2, 0.1, -1.5]
    cam[1] = [30.0, 0.0, 4.0]
    log_scales = np.log(rng.uniform(0.05, 0.35, (n, 3)))
    logits = rng.normal(size=n)
    if dense:
        z = rng.uniform(3.0, 5.0, dense)
        u = rng.uniform(17, 31, dense)
        v = rng.uniform(17, 31, dense)
        pts = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
        cam = np.concatenate([cam, pts])
        log_scales = np.concatenate([log_scales, np.log(rng.uniform(0.05, 0.2, (dense, 3)))])
        logits = np.concatenate([logits, rng.uniform(1.0, 4.0, dense)])
    total = len(cam)
    means = cam @ POSE[:3, :3].T + POSE[:3, 3]
    quats = rng.normal(size=(total, 4))
    colors = rng.normal(size=(total, n_sh, 3)) * 0.4
    return [means, quats, log_scales, logits, colors]


def loss_weights(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(HEIGHT, WIDTH, 3)), rng.normal(size=(HEIGHT, WIDTH)), rng.normal(size=(HEIGHT, WIDTH))


class LossF64:
    """Random linear functional of (rgb, depth, alpha), rendered in float64 on device."""

    def __init__(self, scene: list[np.ndarray], isotropic: bool = False, seed: int = 7) -> None:
        import taichi as ti

        self.isotropic = isotropic
        self.gs = DeviceGaussians.from_numpy(*scene, isotropic=isotropic, dtype=ti.f64)
        self.rast = Rasterizer(ti.f64)
        self.w_rgb, self.w_depth, self.w_alpha = loss_weights(seed)

    def __call__(self, scene: list[np.ndarray], pose: np.ndarray) -> float:
        names = ("means", "quats", "log_scales", "opacity_logits", "colors")
        self.gs.upload(**{k: (None if self.isotropic and k == "quats" else v) for k, v in zip(names, scene)})
        view = self.rast.forward(self.gs, Camera(K, pose, WIDTH, HEIGHT), background=BACKGROUND)
        rgb = view.rgb.to_numpy()
        depth = view.depth.to_numpy()
        alpha = 1.0 - view.transmittance.to_numpy()
        return float((rgb * self.w_rgb).sum() + (depth * self.w_depth).sum() + (alpha * self.w_alpha).sum())

    def gradients(self, scene: list[np.ndarray], pose: np.ndarray) -> tuple[dict, np.ndarray]:
        from taichi_gs.kernels.splat import to_device
        import taichi as ti

        self(scene, pose)
        self.gs.zero_grad()
        view = self.rast.views[0]
        pose_grad = self.rast.backward(
            self.gs, view, to_device(self.w_rgb, ti.f64), to_device(self.w_depth, ti.f64),
            to_device(self.w_alpha, ti.f64),
        )
        return self.gs.download(grads=True), pose_grad


# Central-difference steps. The image is piecewise smooth: a step can straddle a pixel whose
# alpha crosses 1/255, the support cut-off or the 1e-4 transmittance stop, which shows up as a
# huge difference quotient. Such a jump sits inside one step size but almost never inside both,
# so an entry passes when either step agrees with the analytic value.
STEPS = (1e-6, 2.5e-7)


def central_difference(f, h: float) -> float:
    return (f(h) - f(-h)) / (2 * h)


def finite_differences(loss: LossF64, scene, pose, k: int, indices, h: float) -> np.ndarray:
    def shifted(idx):
        def f(step):
            moved = [a.copy() for a in scene]
            moved[k][idx] += step
            return loss(moved, pose)

        return f

    return np.array([central_difference(shifted(idx), h) for idx in indices])


def relative_errors(analytic: np.ndarray, numeric: np.ndarray) -> np.ndarray:
    floor = 1e-3 * max(np.abs(numeric).max(), 1e-8)
    return np.abs(analytic - numeric) / np.maximum(np.abs(numeric), floor)


def gradient_error(analytic: np.ndarray, numeric_at) -> float:
    """Max relative error, entries failing at the first step retried at the second."""
    numeric = numeric_at(STEPS[0], np.arange(len(analytic)))
    err = relative_errors(analytic, numeric)
    retry = np.flatnonzero(err > 1e-5)
    if len(retry):
        numeric[retry] = numeric_at(STEPS[1], retry)
        err = np.minimum(err, relative_errors(analytic, numeric))
    return float(err.max())


def check_forward_matches_reference(precision: str, seed: int = 3, n_sh: int = 9) -> float:
    """Max abs difference of rgb, depth, alpha against the NumPy reference."""
    scene = make_scene(seed, n=80, n_sh=n_sh, dense=120)
    got = rasterize(*scene, K, POSE, WIDTH, HEIGHT, background=BACKGROUND, precision=precision)
    want = reference_renderer.render(*scene, K, POSE, WIDTH, HEIGHT, background=BACKGROUND)
    assert want[2].max() > 0.999, "scene should drive some pixels close to full opacity"
    return max(np.abs(a - b).max() for a, b in zip((got.rgb, got.depth, got.alpha), want))


def silence_pixels(loss: LossF64) -> None:
    """Zero every image gradient of ``loss`` in a 6-pixel border (a padded anchor's margin) and in the upper half of
    the dense tile at [16, 32)^2, and all but the depth gradient in rows 30-33 (pixels the backward must still
    replay)."""
    for w in (loss.w_rgb, loss.w_depth, loss.w_alpha):
        w[:6] = 0.0
        w[-6:] = 0.0
        w[:, :6] = 0.0
        w[:, -6:] = 0.0
        w[16:24, 16:32] = 0.0
    loss.w_rgb[30:34] = 0.0
    loss.w_alpha[30:34] = 0.0


def check_gradients(isotropic: bool, n_sh: int, seed: int, dense: int, sample: int = 0,
                    silent: bool = False) -> dict[str, float]:
    """Max relative error of every gradient against central differences (f64); with ``silent``, some pixels have no
    image gradient (:func:`silence_pixels`)."""
    scene = make_scene(seed, n=16, n_sh=n_sh, dense=dense)
    if isotropic:
        scene[2] = scene[2][:, :1]
    loss = LossF64(scene, isotropic=isotropic)
    if silent:
        silence_pixels(loss)
    grads, pose_grad = loss.gradients(scene, POSE)
    tiles_per_gaussian = loss.rast.views[0].tiles_per_gaussian()
    assert tiles_per_gaussian.max() > 1, "some Gaussian should straddle a tile border"
    assert tiles_per_gaussian[0] == 0 and tiles_per_gaussian[1] == 0, "culled: behind / off screen"
    errors = {}
    names = ("means", "quats", "log_scales", "opacity_logits", "colors")
    rng = np.random.default_rng(seed)
    for k, name in enumerate(names):
        if isotropic and name in ("quats", "log_scales"):
            assert not np.any(grads[name]), f"{name} must get no gradient in the isotropic variant"
            continue
        indices = list(np.ndindex(scene[k].shape))
        if sample and len(indices) > sample:
            indices = [indices[i] for i in rng.choice(len(indices), sample, replace=False)]
        analytic = np.array([grads[name][i] for i in indices])
        errors[name] = gradient_error(
            analytic, lambda h, rows: finite_differences(loss, scene, POSE, k, [indices[r] for r in rows], h)
        )
        culled = [j for j, i in enumerate(indices) if i[0] in (0, 1)]
        assert np.all(analytic[culled] == 0), "culled Gaussians must get no gradient"

    def pose_fd(h, rows):
        return np.array([
            central_difference(lambda step: loss(scene, se3_exp(step * np.eye(6)[r]) @ POSE), h) for r in rows
        ])

    errors["pose"] = gradient_error(pose_grad, pose_fd)
    return errors


def test_forward_matches_reference_f32() -> None:
    assert check_forward_matches_reference("f32") < 2e-5


def test_forward_matches_reference_f64() -> None:
    # f64 kernels, but RenderResult images are float32: only output rounding remains
    assert check_forward_matches_reference("f64") < 3e-7


def test_forward_sh_degree_0_matches_reference() -> None:
    """Degree 0 compiles without the higher SH bands (``view_dependent`` off): the DC colour alone."""
    assert check_forward_matches_reference("f64", seed=4, n_sh=1) < 3e-7


def test_gradients_full_model_sh3_dense_tile() -> None:
    errors = check_gradients(isotropic=False, n_sh=16, seed=11, dense=30, sample=300)
    assert max(errors.values()) < 1e-5, errors


def test_gradients_sh_degree_1() -> None:
    errors = check_gradients(isotropic=False, n_sh=4, seed=12, dense=0)
    assert max(errors.values()) < 1e-5, errors


def test_gradients_sh_degree_0() -> None:
    """Stage 3's fast-preset path: anisotropic Gaussians with the DC colour only."""
    errors = check_gradients(isotropic=False, n_sh=1, seed=14, dense=20)
    assert max(errors.values()) < 1e-5, errors


def test_gradients_with_pixels_without_image_gradients() -> None:
    """The backward skips pixels whose image gradients are all zero; a depth-only gradient is still replayed."""
    errors = check_gradients(isotropic=False, n_sh=1, seed=14, dense=20, silent=True)
    assert max(errors.values()) < 1e-5, errors


def test_gradients_isotropic_fixed_scale() -> None:
    errors = check_gradients(isotropic=True, n_sh=1, seed=13, dense=20)
    assert max(errors.values()) < 1e-5, errors


def test_rgb_colours_are_sh_dc_and_result_shapes() -> None:
    scene = make_scene(5, n=30, n_sh=1)
    flat = scene[:4] + [scene[4][:, 0, :]]
    a = rasterize(*flat, K, POSE, WIDTH, HEIGHT)
    b = rasterize(*scene, K, POSE, WIDTH, HEIGHT)
    assert a.rgb.shape == (HEIGHT, WIDTH, 3) and a.depth.shape == (HEIGHT, WIDTH) and a.alpha.shape == (HEIGHT, WIDTH)
    assert a.rgb.dtype == np.float32
    np.testing.assert_array_equal(a.rgb, b.rgb)
    grads = a.backward(d_rgb=np.ones((HEIGHT, WIDTH, 3)))
    assert grads.colors.shape == (30, 3) and grads.pose.shape == (6,)
    # a single opaque DC colour renders as 0.2820948 * dc + 0.5
    one = rasterize(np.array([[0.0, 0.0, 3.0]]), np.array([[1.0, 0, 0, 0]]), np.full((1, 3), np.log(2.0)),
                    np.array([20.0]), np.array([[1.0, -1.0, 0.0]]), K, np.eye(4), WIDTH, HEIGHT)
    centre = one.rgb[int(K[1, 2]), int(K[0, 2])]
    np.testing.assert_allclose(centre, 0.99 * np.maximum(0.2820948 * np.array([1.0, -1.0, 0.0]) + 0.5, 0), atol=1e-5)


def test_all_gaussians_culled_renders_background() -> None:
    scene = make_scene(6, n=5, n_sh=1)
    scene[0] = scene[0] - 100.0 * POSE[:3, 2]  # everything behind the camera
    out = rasterize(*scene, K, POSE, WIDTH, HEIGHT, background=BACKGROUND)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(BACKGROUND, out.rgb.shape), atol=1e-7)
    assert not out.depth.any() and not out.alpha.any()
    assert not np.any(out.backward(np.ones((HEIGHT, WIDTH, 3))).means)


def test_empty_scene() -> None:
    out = rasterize(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)),
                    K, POSE, WIDTH, HEIGHT, background=BACKGROUND)
    np.testing.assert_allclose(out.rgb, np.broadcast_to(BACKGROUND, out.rgb.shape), atol=1e-7)
    grads = out.backward(np.ones((HEIGHT, WIDTH, 3)))
    assert grads.means.shape == (0, 3) and not grads.pose.any()


def test_memory_order_of_the_gaussians_changes_nothing() -> None:
    """The Morton reordering of stage 3 (spatial_order) only moves rows: the images, the pose gradient
    and every Gaussian's gradient (permuted back) are those of the original order, in float64."""
    from taichi_gs.gaussian_store import morton_order

    scene = make_scene(11, n=60, n_sh=4, dense=40)
    order = morton_order(scene[0])
    assert not np.array_equal(order, np.arange(len(order)))
    weights = loss_weights(12)
    plain = rasterize(*scene, K, POSE, WIDTH, HEIGHT, background=BACKGROUND, precision="f64")
    moved = rasterize(*[a[order] for a in scene], K, POSE, WIDTH, HEIGHT, background=BACKGROUND, precision="f64")
    for a, b in zip((plain.rgb, plain.depth, plain.alpha), (moved.rgb, moved.depth, moved.alpha)):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-6)  # float32 images of float64 renders
    g_plain, g_moved = plain.backward(*weights), moved.backward(*weights)
    np.testing.assert_allclose(g_moved.pose, g_plain.pose, rtol=1e-10, atol=1e-12)
    for name in ("means", "quats", "log_scales", "opacity_logits", "colors"):
        np.testing.assert_allclose(getattr(g_moved, name), getattr(g_plain, name)[order], rtol=1e-10, atol=1e-12)


def test_device_api_views_accumulate_gradients() -> None:
    """Two views rendered before either backward; gradients add up across backward calls."""
    import taichi as ti

    from taichi_gs.kernels.splat import to_device

    scene = make_scene(8, n=40, n_sh=4)
    gs = DeviceGaussians.from_numpy(*scene)
    rast = Rasterizer(ti.f32)
    moved = se3_exp(np.array([0.05, 0, 0, 0, 0.02, 0])) @ POSE
    cams = [Camera(K, POSE, WIDTH, HEIGHT), Camera(K, moved, WIDTH, HEIGHT)]
    views = [rast.forward(gs, cam, view=i) for i, cam in enumerate(cams)]
    ones = to_device(np.ones((HEIGHT, WIDTH)), ti.f32)
    separate = []
    for v in views:
        gs.zero_grad()
        rast.backward(gs, v, d_depth=ones)
        separate.append(gs.download(grads=True)["means"])
    gs.zero_grad()
    for v in views:
        rast.backward(gs, v, d_depth=ones)
    np.testing.assert_allclose(gs.download(grads=True)["means"], separate[0] + separate[1], rtol=1e-5, atol=1e-5)
    ref = reference_renderer.render(*scene, K, cams[1].cam_to_world, WIDTH, HEIGHT)
    np.testing.assert_allclose(views[1].depth.to_numpy(), ref[1], atol=2e-5)


def test_depth_only_render_matches_the_full_render() -> None:
    """``with_colour=False`` (stage 2's renders): the same depth, alpha, parameter and pose gradients
    as a full render, in float64, with rgb black; a colour gradient for such a view is refused."""
    import taichi as ti

    from taichi_gs.kernels.splat import to_device

    scene = make_scene(21, n=50, n_sh=4, dense=30)
    _, d_depth, d_alpha = loss_weights(22)
    gs = DeviceGaussians.from_numpy(*scene, dtype=ti.f64)
    rast = Rasterizer(ti.f64)
    g_depth, g_alpha = to_device(d_depth, ti.f64), to_device(d_alpha, ti.f64)
    results = []
    for with_colour in (True, False):
        view = rast.forward(gs, Camera(K, POSE, WIDTH, HEIGHT), background=BACKGROUND, with_colour=with_colour)
        gs.zero_grad()
        pose = rast.backward(gs, view, d_depth=g_depth, d_alpha=g_alpha)
        results.append((view.rgb.to_numpy(), view.depth.to_numpy(), view.transmittance.to_numpy(), pose,
                        gs.download(grads=True)))
    (rgb, depth, trans, pose, grads), (rgb_d, depth_d, trans_d, pose_d, grads_d) = results
    assert np.abs(rgb).max() > 0.1 and not rgb_d.any()
    assert (trans < 0.9).mean() > 0.3  # the scene covers the image
    np.testing.assert_allclose(depth_d, depth, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(trans_d, trans, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(pose_d, pose, rtol=1e-10, atol=1e-12)
    assert np.abs(pose).max() > 1e-3
    for name in ("means", "quats", "log_scales", "opacity_logits"):
        assert np.abs(grads[name]).max() > 1e-6, name
        np.testing.assert_allclose(grads_d[name], grads[name], rtol=1e-10, atol=1e-12)
    assert not grads_d["colors"].any()
    with pytest.raises(ValueError, match="without colour"):
        rast.backward(gs, view, d_rgb=to_device(np.ones((HEIGHT, WIDTH, 3)), ti.f64))


CUDA_SCRIPT = """
import sys
sys.path.insert(0, {tests!r})
from taichi_gs.kernels import runtime
runtime.init("cuda")
import test_render as t
assert t.check_forward_matches_reference("f32") < 2e-5
assert t.check_forward_matches_reference("f64") < 3e-7
for iso, n_sh, seed, dense in [(False, 16, 11, 30), (True, 1, 13, 20)]:
    errors = t.check_gradients(iso, n_sh, seed, dense, sample=100)
    assert max(errors.values()) < 1e-5, errors
print("cuda ok")
"""


@pytest.mark.cuda
@pytest.mark.skipif(not runtime.cuda_available(), reason="no CUDA GPU")
def test_cuda_backend_matches() -> None:
    """The same checks on the CUDA backend (a fresh process: Taichi inits once per process)."""
    script = CUDA_SCRIPT.format(tests=str(Path(__file__).parent))
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=dict(os.environ))
    assert result.returncode == 0 and "cuda ok" in result.stdout, result.stderr[-3000:]


def test_exposure_pose_gradients_chain_virtual_views() -> None:
    """Blur of k virtual views along a straight and [ours] a bent exposure: the chained pose gradients of the start,
    end and bend offsets match finite differences."""
    from taichi_gs.geometry import exposure_pose_gradients, virtual_pose

    scene = make_scene(9, n=30, n_sh=1)
    loss = LossF64(scene)
    d_start = np.array([0.02, -0.01, 0.01, 0.01, -0.02, 0.005])
    d_end = np.array([-0.015, 0.02, 0.0, -0.01, 0.015, 0.01])
    taus = np.linspace(0.0, 1.0, 4)
    for bend in (None, np.array([0.004, 0.006, -0.003, -0.005, 0.002, 0.004])):
        def blurred_loss(ds, de, b):
            return sum(loss(scene, virtual_pose(POSE, ds, de, tau, b)) for tau in taus) / len(taus)

        grads = [loss.gradients(scene, virtual_pose(POSE, d_start, d_end, tau, bend))[1] / len(taus) for tau in taus]
        analytic = exposure_pose_gradients(POSE, d_start, d_end, taus, grads, bend)
        h = 1e-6
        at = [d_start, d_end, np.zeros(6) if bend is None else bend]
        for which in range(3):
            numeric = []
            for e in np.eye(6):
                up, down = [a.copy() for a in at], [a.copy() for a in at]
                up[which] += h * e
                down[which] -= h * e
                numeric.append((blurred_loss(*up) - blurred_loss(*down)) / (2 * h))
            assert relative_errors(analytic[which], np.array(numeric)).max() < 1e-5
