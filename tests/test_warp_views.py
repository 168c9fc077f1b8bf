"""[ours] Warped virtual views (``kernels.warp``, ``BlurScene.step(anchors=...)``, ``[deblur] warp_views``).

The warp kernel against an independent NumPy implementation (fixed-point depth, Catmull-Rom
interpolation) and its backward against central finite differences in float64 (with each pixel's depth
held at the forward's value, as the backward defines it); the composed stage-3 step with anchors against
finite differences of a NumPy loss built from float64 anchor renders; and how closely warped exposures
follow rendered ones.
"""

from __future__ import annotations

import numpy as np
import pytest
import taichi as ti

from taichi_gs.geometry import invert, raster_intrinsics, se3_exp, virtual_pose
from taichi_gs.kernels import runtime, warp
from taichi_gs.kernels.splat import to_device
from taichi_gs.rolling_shutter import shutter_rows
from taichi_gs.splats import Splats
from taichi_gs.stages.deblur import run as deblur
from taichi_gs.stages.deblur.model import BlurScene, FrozenAnchors, anchor_groups, exposure_taus

H, W, MARGIN = 18, 22, 4
K_RASTER = np.array([[30.0, 0.0, 11.3], [0.0, 31.0, 9.1], [0.0, 0.0, 1.0]])
WEIGHT = 0.7


def catmull_rom(x: np.ndarray) -> np.ndarray:
    """The Catmull-Rom cubic convolution kernel (Keys' a = -1/2)."""
    x = np.abs(x)
    return np.where(x <= 1, (1.5 * x - 2.5) * x * x + 1, np.where(x <= 2, ((-0.5 * x + 2.5) * x - 4) * x + 2, 0.0))


def rays(K: np.ndarray, h: int, w: int) -> np.ndarray:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.stack([(u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def anchor_coordinates(z: np.ndarray, M: np.ndarray, K: np.ndarray, margin: int) -> tuple[np.ndarray, np.ndarray]:
    """Index coordinates in the padded anchor of each target pixel at depth z."""
    X = rays(K, *z.shape) * z[..., None] @ M[:3, :3].T + M[:3, 3]
    return (K[0, 0] * X[..., 0] / X[..., 2] + K[0, 2] + margin - 0.5,
            K[1, 1] * X[..., 1] / X[..., 2] + K[1, 2] + margin - 0.5)


def interpolate(image: np.ndarray, sx: np.ndarray, sy: np.ndarray) -> np.ndarray:
    """Catmull-Rom interpolation at index coordinates, clamped so that all four taps lie in the image."""
    hp, wp = image.shape[:2]
    cx, cy = np.clip(sx, 1, wp - 2), np.clip(sy, 1, hp - 2)
    x0, y0 = np.minimum(cx.astype(int), wp - 3), np.minimum(cy.astype(int), hp - 3)
    out = 0.0
    for b in range(4):
        for a in range(4):
            weight = catmull_rom(cx - x0 - (a - 1)) * catmull_rom(cy - y0 - (b - 1))
            out = out + weight[..., None] * image[y0 - 1 + b, x0 - 1 + a]
    return out


def surface(depth: np.ndarray, trans: np.ndarray, sx: np.ndarray, sy: np.ndarray, fallback: float) -> np.ndarray:
    hp, wp = depth.shape
    iu = np.clip(np.floor(sx + 0.5).astype(int), 0, wp - 1)
    iv = np.clip(np.floor(sy + 0.5).astype(int), 0, hp - 1)
    alpha = 1.0 - trans[iv, iu]
    return np.where(alpha >= 0.5, depth[iv, iu] / np.maximum(alpha, 1e-12), fallback)


def reference_depths(depth, trans, M, K, margin, fallback, h, w) -> np.ndarray:
    """The fixed point of the module docstring, in NumPy."""
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    z = surface(depth, trans, u + margin, v + margin, fallback)
    inverse = invert(M)
    for _ in range(warp.FIXED_POINT_STEPS):
        sx, sy = anchor_coordinates(z, M, K, margin)
        zs = surface(depth, trans, sx, sy, fallback)
        seen = np.stack([(sx + 0.5 - margin - K[0, 2]) / K[0, 0], (sy + 0.5 - margin - K[1, 2]) / K[1, 1],
                         np.ones_like(sx)], axis=-1) * zs[..., None]
        z = np.maximum((seen @ inverse[:3, :3].T + inverse[:3, 3])[..., 2], warp.MIN_Z)
    return z


@pytest.fixture(scope="module")
def anchor():
    runtime.init()
    rng = np.random.default_rng(3)
    hp, wp = H + 2 * MARGIN, W + 2 * MARGIN
    rgb = rng.uniform(0, 1, (hp, wp, 3))
    alpha = np.where(rng.uniform(size=(hp, wp)) < 0.85, rng.uniform(0.6, 1.0, (hp, wp)), 0.2)
    z = 2.0 + 0.3 * np.sin(np.arange(wp) / 5.0)[None, :] + 0.1 * np.cos(np.arange(hp) / 4.0)[:, None]
    M = se3_exp(np.array([0.04, -0.03, 0.02, 0.03, -0.05, 0.04]))
    return rgb, z * alpha, 1.0 - alpha, M


def run_warp(rgb, depth, trans, M, dtype=ti.f64):
    """One view warped from the anchor: (anchor on the device, weighted view, its depths (1, H, W))."""
    out = to_device(np.zeros((H, W, 3)), dtype)
    z = to_device(np.zeros((1, H, W)), dtype)
    a = to_device(rgb, dtype)
    warp.accumulate(a, to_device(depth, dtype), to_device(trans, dtype), M, K_RASTER, MARGIN, 2.5, WEIGHT, out, z,
                    first=True)
    return a, out, z


def test_warp_matches_numpy_reference(anchor):
    rgb, depth, trans, M = anchor
    _, out, z = run_warp(rgb, depth, trans, M)
    z_ref = reference_depths(depth, trans, M, K_RASTER, MARGIN, 2.5, H, W)
    np.testing.assert_allclose(z.to_numpy()[0], z_ref, rtol=1e-12)
    expected = WEIGHT * interpolate(rgb, *anchor_coordinates(z_ref, M, K_RASTER, MARGIN))
    np.testing.assert_allclose(out.to_numpy(), expected, atol=1e-12)
    moved = np.abs(np.array(anchor_coordinates(z_ref, M, K_RASTER, MARGIN)) - np.mgrid[0:H, 0:W][::-1] - MARGIN)
    assert moved.max() > 1.0, "the test transform should move pixels by more than a pixel"


def test_warp_accumulates_onto_out(anchor):
    rgb, depth, trans, M = anchor
    a, out, z = run_warp(rgb, depth, trans, M)
    once = out.to_numpy()
    warp.accumulate(a, to_device(depth, ti.f64), to_device(trans, ti.f64), M, K_RASTER, MARGIN, 2.5, WEIGHT, out, z)
    np.testing.assert_allclose(out.to_numpy(), 2 * once, rtol=1e-12)


def test_identity_warp_reproduces_the_anchor(anchor):
    rgb, depth, trans, _ = anchor
    _, out, _ = run_warp(rgb, depth, trans, np.eye(4))
    np.testing.assert_allclose(out.to_numpy(), WEIGHT * rgb[MARGIN:-MARGIN, MARGIN:-MARGIN], atol=1e-12)


@pytest.mark.parametrize("own", [False, True], ids=["moved", "the anchor's own pose"])
def test_warp_backward_matches_finite_differences(anchor, own):
    """Also for the anchor's own pose (identity), whose pixels the kernels read instead of interpolating."""
    rgb, depth, trans, M = anchor
    M = np.eye(4) if own else M
    a, _, z = run_warp(rgb, depth, trans, M)
    z_fixed = z.to_numpy()[0]
    g = np.random.default_rng(4).normal(size=(H, W, 3))
    grad_anchor = to_device(np.zeros(rgb.shape), ti.f64)
    g_eps = warp.backward(to_device(g, ti.f64), a, z, M, K_RASTER, MARGIN, WEIGHT, grad_anchor)[0]

    def loss(image, transform):
        return float(np.sum(g * WEIGHT * interpolate(image, *anchor_coordinates(z_fixed, transform, K_RASTER, MARGIN))))

    def central(h: float) -> np.ndarray:
        return np.array([(loss(rgb, se3_exp(h * e) @ M) - loss(rgb, se3_exp(-h * e) @ M)) / (2 * h) for e in np.eye(6)])

    h = 1e-6
    # Richardson's extrapolation: at the anchor's own pose every sample sits on a knot, where Catmull-Rom's
    # second derivative jumps, so a central difference is off by O(h) there (O(h^2) elsewhere)
    numeric = 2.0 * central(h / 2) - central(h)
    assert np.abs(numeric).min() > 1e-3
    np.testing.assert_allclose(g_eps, numeric, rtol=1e-6)
    got = grad_anchor.to_numpy()
    for idx in [(6, 7, 0), (10, 12, 2), (15, 3, 1), (0, 0, 0), (12, 20, 1)]:
        bump = np.zeros(rgb.shape)
        bump[idx] = h
        assert got[idx] == pytest.approx((loss(rgb + bump, M) - loss(rgb - bump, M)) / (2 * h), abs=1e-7)
    # the gradient of a linear map is the map's transpose: <g, warp(x)> = <warp^T g, x>
    assert np.sum(got * rgb) == pytest.approx(loss(rgb, M), rel=1e-10)


def test_backward_adds_into_the_anchor_gradient(anchor):
    rgb, depth, trans, M = anchor
    a, _, z = run_warp(rgb, depth, trans, M)
    g = to_device(np.ones((H, W, 3)), ti.f64)
    grad_anchor = to_device(np.zeros(rgb.shape), ti.f64)
    first = warp.backward(g, a, z, M, K_RASTER, MARGIN, WEIGHT, grad_anchor)
    once = grad_anchor.to_numpy()
    second = warp.backward(g, a, z, M, K_RASTER, MARGIN, WEIGHT, grad_anchor)
    np.testing.assert_allclose(grad_anchor.to_numpy(), 2 * once, rtol=1e-12)
    np.testing.assert_allclose(first, second, rtol=1e-12)


def test_backward_without_an_anchor_gradient_returns_the_same_pose_gradient(anchor):
    """``grad_anchor=None`` (the anchor a constant, as in a frozen fit): the same dL/d epsilon, bit for bit,
    and nothing left behind for the next backward that does scatter."""
    rgb, depth, trans, M = anchor
    a, _, z = run_warp(rgb, depth, trans, M)
    g = to_device(np.random.default_rng(4).normal(size=(H, W, 3)), ti.f64)
    grad_anchor = to_device(np.zeros(rgb.shape), ti.f64)
    with_anchor = warp.backward(g, a, z, M, K_RASTER, MARGIN, WEIGHT, grad_anchor)
    once = grad_anchor.to_numpy()
    assert np.abs(once).max() > 0.01
    np.testing.assert_array_equal(warp.backward(g, a, z, M, K_RASTER, MARGIN, WEIGHT, None), with_anchor)
    np.testing.assert_array_equal(a.to_numpy(), rgb)  # the anchor stands in for the unwritten buffer
    grad_anchor.fill(0.0)
    warp.backward(g, a, z, M, K_RASTER, MARGIN, WEIGHT, grad_anchor)
    np.testing.assert_array_equal(grad_anchor.to_numpy(), once)


def test_the_anchors_own_view_follows_the_interpolated_path(anchor):
    """A view at the anchor's own pose is flagged and read pixel by pixel (``warp.IDENTITY``); one a hair away
    takes the interpolating path. Forward, depths and both gradients agree to the hair's effect."""
    rgb, depth, trans, _ = anchor
    near = se3_exp(np.full(6, 1e-8))
    views = np.stack([np.eye(4), near])
    hair = np.eye(4) + 1e-12
    flags = warp._args(np.stack([hair, near]), K_RASTER, MARGIN, H, ti.f64)[2].to_numpy()[:2, warp.IDENTITY]
    np.testing.assert_array_equal(flags, [1.0, 0.0])
    np.testing.assert_array_equal(hair, np.eye(4) + 1e-12)  # snapped to the identity on the device only
    results = []
    for M in views:
        a, out, z = run_warp(rgb, depth, trans, M)
        g = to_device(np.random.default_rng(8).normal(size=(H, W, 3)), ti.f64)
        grad_anchor = to_device(np.zeros(rgb.shape), ti.f64)
        pose = warp.backward(g, a, z, M, K_RASTER, MARGIN, WEIGHT, grad_anchor)[0]
        results.append((out.to_numpy(), z.to_numpy(), pose, grad_anchor.to_numpy()))
    (out0, z0, pose0, grad0), (out1, z1, pose1, grad1) = results
    np.testing.assert_allclose(out0, out1, atol=1e-6)
    np.testing.assert_allclose(z0, z1, rtol=1e-7)
    np.testing.assert_allclose(pose0, pose1, rtol=1e-5, atol=1e-5 * np.abs(pose0).max())
    np.testing.assert_allclose(grad0, grad1, atol=1e-6)
    assert np.abs(pose0).max() > 0.1


def test_views_of_one_launch_add_up(anchor):
    """Two views in one launch: the sum of the two warped separately; the backward per view likewise."""
    rgb, depth, trans, M = anchor
    M2 = se3_exp(np.array([-0.02, 0.01, 0.0, -0.01, 0.03, 0.0])) @ M
    a, one, z1 = run_warp(rgb, depth, trans, M)
    _, two, z2 = run_warp(rgb, depth, trans, M2)
    both, z = to_device(np.zeros((H, W, 3)), ti.f64), to_device(np.zeros((3, H, W)), ti.f64)
    warp.accumulate(a, to_device(depth, ti.f64), to_device(trans, ti.f64), np.stack([M, M2]), K_RASTER, MARGIN, 2.5,
                    WEIGHT, both, z, first=True)
    np.testing.assert_allclose(both.to_numpy(), one.to_numpy() + two.to_numpy(), atol=1e-12)
    np.testing.assert_allclose(z.to_numpy()[:2], np.concatenate([z1.to_numpy(), z2.to_numpy()]), rtol=1e-12)
    g = to_device(np.random.default_rng(6).normal(size=(H, W, 3)), ti.f64)
    grads = [to_device(np.zeros(rgb.shape), ti.f64) for _ in range(3)]
    joint = warp.backward(g, a, z, np.stack([M, M2]), K_RASTER, MARGIN, WEIGHT, grads[0])
    first = warp.backward(g, a, z1, M, K_RASTER, MARGIN, WEIGHT, grads[1])
    second = warp.backward(g, a, z2, M2, K_RASTER, MARGIN, WEIGHT, grads[2])
    np.testing.assert_allclose(joint, np.concatenate([first, second]), rtol=1e-10)
    np.testing.assert_allclose(grads[0].to_numpy(), grads[1].to_numpy() + grads[2].to_numpy(), atol=1e-12)


def test_a_wrongly_padded_anchor_is_refused(anchor):
    rgb, depth, trans, M = anchor
    out, z = to_device(np.zeros((H, W, 3)), ti.f64), to_device(np.zeros((1, H, W)), ti.f64)
    with pytest.raises(ValueError, match="does not pad"):
        warp.accumulate(to_device(rgb, ti.f64), to_device(depth, ti.f64), to_device(trans, ti.f64), M, K_RASTER,
                        MARGIN + 1, 2.5, 1.0, out, z)


ROLL = np.array([0.03, -0.02, 0.01, 0.04, 0.02, -0.05])  # a rolling shutter's motion over the readout


def warp_by_rows(rgb, depth, trans, Ms) -> tuple[np.ndarray, np.ndarray]:
    """NumPy: (depths, weighted colours) of a view whose row v is warped through transform Ms[v]."""
    z, out = np.zeros((H, W)), np.zeros((H, W, 3))
    for v, M in enumerate(Ms):
        z_full = reference_depths(depth, trans, M, K_RASTER, MARGIN, 2.5, H, W)
        z[v] = z_full[v]
        out[v] = WEIGHT * interpolate(rgb, *anchor_coordinates(z_full, M, K_RASTER, MARGIN))[v]
    return z, out


def test_a_rolling_shutter_warps_each_row_at_its_own_pose(anchor):
    """[ours] A transform per image row (V, H, 4, 4): row v of the view is row v of the view warped through
    its own transform, against the NumPy reference; and it differs from the global shutter's by pixels."""
    rgb, depth, trans, M = anchor
    Ms = M[None] @ shutter_rows(ROLL, H)
    _, out, z = run_warp(rgb, depth, trans, Ms[None])
    z_ref, expected = warp_by_rows(rgb, depth, trans, Ms)
    np.testing.assert_allclose(z.to_numpy()[0], z_ref, rtol=1e-12)
    np.testing.assert_allclose(out.to_numpy(), expected, atol=1e-12)
    _, global_shutter, _ = run_warp(rgb, depth, trans, M)
    assert np.abs(out.to_numpy() - global_shutter.to_numpy()).max() > 0.1


def test_equal_row_transforms_are_the_global_shutter(anchor):
    """[ours] The same transform on every row gives the one-per-view warp exactly, forward and backward."""
    rgb, depth, trans, M = anchor
    g = to_device(np.random.default_rng(9).normal(size=(H, W, 3)), ti.f64)
    results = []
    for transforms in (M, np.repeat(M[None, None], H, axis=1)):
        a, out, z = run_warp(rgb, depth, trans, transforms)
        grad_anchor = to_device(np.zeros(rgb.shape), ti.f64)
        pose = warp.backward(g, a, z, transforms, K_RASTER, MARGIN, WEIGHT, grad_anchor)
        results.append((out.to_numpy(), pose, grad_anchor.to_numpy()))
    for one, per_row in zip(*results):
        np.testing.assert_array_equal(one, per_row)


def test_a_rolling_shutter_backward_matches_finite_differences(anchor):
    """[ours] With a transform per row, dL/d epsilon is for exp(epsilon) on every row's transform at once, and
    the anchor's gradient is the per-row warp's transpose."""
    rgb, depth, trans, M = anchor
    Ms = M[None] @ shutter_rows(ROLL, H)
    a, _, z = run_warp(rgb, depth, trans, Ms[None])
    z_fixed = z.to_numpy()[0]
    g = np.random.default_rng(10).normal(size=(H, W, 3))
    grad_anchor = to_device(np.zeros(rgb.shape), ti.f64)
    g_eps = warp.backward(to_device(g, ti.f64), a, z, Ms[None], K_RASTER, MARGIN, WEIGHT, grad_anchor)[0]

    def loss(image, lead=np.eye(4)):
        total = 0.0
        for v in range(H):
            sx, sy = anchor_coordinates(z_fixed, lead @ Ms[v], K_RASTER, MARGIN)
            total += np.sum(g[v] * WEIGHT * interpolate(image, sx, sy)[v])
        return float(total)

    h = 1e-6
    numeric = np.array([(loss(rgb, se3_exp(h * e)) - loss(rgb, se3_exp(-h * e))) / (2 * h) for e in np.eye(6)])
    assert np.abs(numeric).min() > 1e-3
    np.testing.assert_allclose(g_eps, numeric, rtol=1e-6)
    assert np.sum(grad_anchor.to_numpy() * rgb) == pytest.approx(loss(rgb), rel=1e-10)


def test_row_transforms_for_another_height_are_refused(anchor):
    rgb, depth, trans, M = anchor
    with pytest.raises(ValueError, match="row transforms per view"):
        run_warp(rgb, depth, trans, np.repeat(M[None, None], H + 1, axis=1))


# ---- the composed stage-3 step -------------------------------------------------------------------------

WIDTH, HEIGHT, STEP_MARGIN = 40, 32, 5
K = np.array([[38.0, 0.0, 19.3], [0.0, 37.0, 15.6], [0.0, 0.0, 1.0]])  # OpenCV convention
BASE = se3_exp(np.array([0.05, -0.08, 0.03, 0.04, -0.03, 0.02]))
D_START = np.array([-0.03, 0.012, -0.008, 0.01, -0.015, 0.006])
D_END = np.array([0.025, -0.01, 0.012, -0.012, 0.018, -0.004])
K_VIEWS, ANCHORS, LAMBDA_DEPTH = 5, 3, 0.3  # three anchors: the middle one at mid-exposure


def scene(seed: int, n: int = 40, depth: tuple = (2.5, 4.0)) -> Splats:
    rng = np.random.default_rng(seed)
    cam = np.stack([rng.uniform(-1.2, 1.2, n), rng.uniform(-1.0, 1.0, n), rng.uniform(*depth, n)], axis=1)
    means = cam @ BASE[:3, :3].T + BASE[:3, 3]
    return Splats(means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.1, 0.3, (n, 3))), rng.normal(1.0, 1.0, n),
                  rng.normal(size=(n, 1, 3)) * 0.5)


def targets(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    other = BlurScene(scene(seed + 100), K, WIDTH, HEIGHT)
    frame = other.render_blurred(BASE, 0.7 * D_START, 1.3 * D_END, 5) + rng.normal(0, 0.05, (HEIGHT, WIDTH, 3))
    _, depth = other.render(virtual_pose(BASE, D_START, D_END, 0.5))
    depth = np.where(rng.uniform(size=depth.shape) < 0.3, 0.0, depth)
    return frame.astype(np.float32), depth.astype(np.float32)


def warp_rows_from(rgb, z, M, rows) -> np.ndarray:
    """NumPy: a view warped at depths z through M, or with a rolling shutter's ``rows`` row v through M @ rows[v]."""
    Kr = raster_intrinsics(K)
    if rows is None:
        return interpolate(rgb, *anchor_coordinates(z, M, Kr, STEP_MARGIN))
    return np.stack([interpolate(rgb, *anchor_coordinates(z, M @ row, Kr, STEP_MARGIN))[v] for v, row in enumerate(rows)])


def warped_loss(model: BlurScene, frame, depth, d_start, d_end, z_fixed: list[np.ndarray], rows=None) -> float:
    """L1 of the mean of the k views warped (at the given depths) from float64 anchor renders, plus the
    mid anchor's masked depth L1 (NumPy; D-SSIM is off here: its kernel is checked elsewhere); ``rows``: a
    rolling shutter's row transforms (:func:`shutter_rows`)."""
    taus = exposure_taus(K_VIEWS)
    groups = anchor_groups(K_VIEWS, ANCHORS)
    anchor_taus = [float(np.mean(taus[g])) for g in groups]
    mid = int(np.argmin(np.abs(np.array(anchor_taus) - 0.5)))
    blurred, depth_l1 = 0.0, 0.0
    for a, group in enumerate(groups):
        anchor_pose = virtual_pose(BASE, d_start, d_end, anchor_taus[a])
        view = model.rasterizer.forward(model.gaussians, model.padded_camera(anchor_pose))
        rgb, rendered_depth = view.rgb.to_numpy(), view.depth.to_numpy()
        for i in group:
            M = invert(anchor_pose) @ virtual_pose(BASE, d_start, d_end, taus[i])
            blurred = blurred + warp_rows_from(rgb, z_fixed[i], M, rows) / K_VIEWS
        if a == mid:
            padded = np.pad(depth.astype(np.float64), STEP_MARGIN)
            valid = padded > 0
            depth_l1 = np.abs(rendered_depth - padded)[valid].sum() / valid.sum()
    return float(np.abs(blurred - frame).mean() + LAMBDA_DEPTH * depth_l1)


def check_gaussian_gradients(grads: dict, params: dict, loss, names: tuple, picks: int, seed: int,
                             h: float = 1e-6) -> None:
    """Every entry of the parameters ``names`` of ``picks`` random Gaussians that a colour gradient reached:
    ``grads`` against central differences of ``loss(arrays)``."""
    seen = np.flatnonzero(np.abs(grads["colors"]).sum(axis=(1, 2)) > 1e-6)
    assert len(seen) >= 10
    rng = np.random.default_rng(seed)
    for name in names:
        for i in rng.choice(seen, picks, replace=False):
            for idx in np.ndindex(params[name].shape[1:]):
                moved_plus, moved_minus = dict(params), dict(params)
                moved_plus[name], moved_minus[name] = params[name].copy(), params[name].copy()
                moved_plus[name][(i, *idx)] += h
                moved_minus[name][(i, *idx)] -= h
                numeric = (loss(moved_plus) - loss(moved_minus)) / (2 * h)
                scale = np.abs(grads[name]).max()
                assert grads[name][(i, *idx)] == pytest.approx(numeric, abs=1e-4 * scale), (name, i, idx)


def test_warped_step_gradients_match_finite_differences():
    runtime.init()
    frame, depth = targets(5)
    model = BlurScene(scene(4), K, WIDTH, HEIGHT, precision="f64", warp_margin=STEP_MARGIN)
    step = model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.0, LAMBDA_DEPTH, rates=None, anchors=ANCHORS)
    grads = model.gaussians.download(grads=True)
    params = model.arrays()
    z_fixed = [model.warp_depths[a].to_numpy()[j] for a, group in enumerate(anchor_groups(K_VIEWS, ANCHORS))
               for j in range(len(group))]
    frame64 = frame.astype(np.float64)

    def loss(arrays=None, d_start=D_START, d_end=D_END) -> float:
        model.gaussians.upload(**(arrays or params))
        return warped_loss(model, frame64, depth, d_start, d_end, z_fixed)

    assert step.losses["l1"] + LAMBDA_DEPTH * step.losses["depth"] == pytest.approx(loss(), rel=1e-9)
    assert step.losses["depth"] > 0.05
    h = 1e-6
    for which, analytic in (("d_start", step.grad_start), ("d_end", step.grad_end)):
        numeric = []
        for e in np.eye(6):
            plus = loss(**{which: (D_START if which == "d_start" else D_END) + h * e})
            minus = loss(**{which: (D_START if which == "d_start" else D_END) - h * e})
            numeric.append((plus - minus) / (2 * h))
        np.testing.assert_allclose(analytic, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max(), err_msg=which)
    check_gaussian_gradients(grads, params, loss, ("means", "colors", "opacity_logits"), picks=4, seed=1)


ROLL_STEP = np.array([0.02, -0.015, 0.005, 0.03, -0.02, 0.025])


def test_rolling_shutter_step_gradients_match_finite_differences():
    """[ours] A step with a rolling shutter (``readout_motion``): its loss is the per-row warped NumPy loss,
    and its exposure and Gaussian gradients match that loss's finite differences."""
    runtime.init()
    frame, depth = targets(7)
    model = BlurScene(scene(4), K, WIDTH, HEIGHT, precision="f64", warp_margin=STEP_MARGIN)
    step = model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.0, LAMBDA_DEPTH, rates=None, anchors=ANCHORS,
                      readout_motion=ROLL_STEP)
    grads = model.gaussians.download(grads=True)
    params = model.arrays()
    z_fixed = [model.warp_depths[a].to_numpy()[j] for a, group in enumerate(anchor_groups(K_VIEWS, ANCHORS))
               for j in range(len(group))]
    rows = shutter_rows(ROLL_STEP, HEIGHT)
    frame64 = frame.astype(np.float64)

    def loss(arrays=None, d_start=D_START, d_end=D_END, shutter=rows) -> float:
        model.gaussians.upload(**(arrays or params))
        return warped_loss(model, frame64, depth, d_start, d_end, z_fixed, shutter)

    total = step.losses["l1"] + LAMBDA_DEPTH * step.losses["depth"]
    assert total == pytest.approx(loss(), rel=1e-9)
    assert abs(loss(shutter=None) - total) > 1e-3, "the test's shutter should change the loss"
    h = 1e-6
    for which, analytic, value in (("d_start", step.grad_start, D_START), ("d_end", step.grad_end, D_END)):
        numeric = np.array([(loss(**{which: value + h * e}) - loss(**{which: value - h * e})) / (2 * h)
                            for e in np.eye(6)])
        np.testing.assert_allclose(analytic, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max(), err_msg=which)
    check_gaussian_gradients(grads, params, loss, ("means", "colors"), picks=3, seed=2)


def test_a_rolling_shutter_needs_warped_views():
    runtime.init()
    frame, depth = targets(7)
    model = BlurScene(scene(4), K, WIDTH, HEIGHT, precision="f64", warp_margin=STEP_MARGIN)
    with pytest.raises(ValueError, match="needs warped views"):
        model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.0, 0.0, rates=None, readout_motion=ROLL_STEP)
    # a zero motion is a global shutter: allowed without anchors
    model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.0, 0.0, rates=None, readout_motion=np.zeros(6))


@pytest.mark.parametrize("anchors", [1, 2, 3, 4, 5])
def test_the_depth_loss_is_taken_at_mid_exposure(anchors):
    """[ours] Whatever number of anchors is asked for, one is rendered at tau = 1/2 and carries the depth
    loss: against the blended depth of a plain render at the mid-exposure pose the loss vanishes, against
    one a quarter of the exposure away it does not."""
    runtime.init()
    model = BlurScene(scene(4), K, WIDTH, HEIGHT, precision="f64", warp_margin=STEP_MARGIN)
    frame = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    losses = {}
    for tau in (0.5, 0.25):
        view = model.rasterizer.forward(model.gaussians, model.camera(virtual_pose(BASE, D_START, D_END, tau)))
        depth = view.depth.to_numpy().astype(np.float32)
        assert (depth > 0.5).mean() > 0.5  # the scene covers most of the view
        step = model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.2, 1.0, rates=None, anchors=anchors)
        losses[tau] = step.losses["depth"]
    assert losses[0.5] < 1e-5 and losses[0.25] > 1e-2, losses


def frozen_loss(model: BlurScene, frame, anchor_poses: list[np.ndarray], d_start, d_end,
                z_fixed: list[np.ndarray]) -> float:
    """L1 of the mean of the k views warped (at the given depths) from float64 renders at the fixed
    ``anchor_poses`` (NumPy): the loss of a held-out fit's step with frozen anchors."""
    taus = exposure_taus(K_VIEWS)
    Kr = raster_intrinsics(K)
    blurred = 0.0
    for a, group in enumerate(anchor_groups(K_VIEWS, len(anchor_poses))):
        rgb = model.rasterizer.forward(model.gaussians, model.padded_camera(anchor_poses[a])).rgb.to_numpy()
        for i in group:
            M = invert(anchor_poses[a]) @ virtual_pose(BASE, d_start, d_end, taus[i])
            blurred = blurred + interpolate(rgb, *anchor_coordinates(z_fixed[i], M, Kr, STEP_MARGIN)) / K_VIEWS
    return float(np.abs(blurred - frame).mean())


def test_frozen_anchor_step_gradients_match_finite_differences():
    """[ours] A held-out fit's step with frozen anchors: the loss depends on the exposure through the
    warps from renders at fixed poses alone; its exposure gradients against finite differences of that
    loss, and the Gaussians' gradients untouched (no rasterizer backward)."""
    runtime.init()
    frame, depth = targets(6)
    model = BlurScene(scene(4), K, WIDTH, HEIGHT, precision="f64", warp_margin=STEP_MARGIN)
    frozen = FrozenAnchors(refresh_px=1e9, focal=K[0, 0], depth=3.0)
    model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.0, 0.0, rates=None, anchors=ANCHORS, frozen=frozen)
    moved = np.array([0.004, -0.003, 0.002, 0.003, -0.002, 0.001])  # the fit moved on: the anchors stay
    d_start, d_end = D_START + moved, D_END - 0.5 * moved
    grads_before = model.gaussians.download(grads=True)
    step = model.step(frame, depth, BASE, d_start, d_end, K_VIEWS, 0.0, 0.0, rates=None, anchors=ANCHORS,
                      frozen=frozen)
    assert frozen.renders == ANCHORS
    for name, value in model.gaussians.download(grads=True).items():
        np.testing.assert_array_equal(value, grads_before[name], err_msg=name)
    z_fixed = [model.warp_depths[a].to_numpy()[j] for a, group in enumerate(anchor_groups(K_VIEWS, ANCHORS))
               for j in range(len(group))]
    frame64 = frame.astype(np.float64)
    poses = list(frozen.poses)
    assert step.losses["l1"] == pytest.approx(frozen_loss(model, frame64, poses, d_start, d_end, z_fixed), rel=1e-9)
    h = 1e-6
    for which, analytic, value in (("d_start", step.grad_start, d_start), ("d_end", step.grad_end, d_end)):
        numeric = []
        for e in np.eye(6):
            ends = {"d_start": d_start, "d_end": d_end}
            plus = frozen_loss(model, frame64, poses, **{**ends, which: value + h * e}, z_fixed=z_fixed)
            minus = frozen_loss(model, frame64, poses, **{**ends, which: value - h * e}, z_fixed=z_fixed)
            numeric.append((plus - minus) / (2 * h))
        assert np.abs(numeric).max() > 1e-3
        np.testing.assert_allclose(analytic, numeric, rtol=1e-4, atol=1e-6 * np.abs(numeric).max(), err_msg=which)


def test_frozen_anchors_render_again_only_when_moved_or_regrouped():
    """[ours] The first frozen step is the ordinary warped step; later steps reuse the renders until an
    anchor would move more than ``refresh_px`` or the number of anchors changes. A frozen step needs a
    frozen scene and no depth term."""
    runtime.init()
    frame, depth = targets(7)
    model = BlurScene(scene(4), K, WIDTH, HEIGHT, warp_margin=STEP_MARGIN)
    model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.2, 0.0, rates=None, anchors=1)
    ordinary = model.blurred.to_numpy()
    frozen = FrozenAnchors(refresh_px=1.0, focal=K[0, 0], depth=3.0)
    model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.2, 0.0, rates=None, anchors=1, frozen=frozen)
    np.testing.assert_array_equal(model.blurred.to_numpy(), ordinary)
    turn = np.zeros(6)
    for angle_px, renders in ((0.6, 1), (0.9, 1), (1.3, 2), (1.9, 2)):  # pixels turned from the first render
        turn[4] = angle_px / K[0, 0]
        model.step(frame, depth, BASE, D_START + turn, D_END + turn, K_VIEWS, 0.2, 0.0, rates=None, anchors=1,
                   frozen=frozen)
        assert frozen.renders == renders, angle_px
    model.step(frame, depth, BASE, D_START + turn, D_END + turn, K_VIEWS, 0.2, 0.0, rates=None, anchors=3,
               frozen=frozen)
    assert frozen.renders == 5  # regrouped: all three anchors rendered
    for bad in ({"rates": deblur_rates()}, {"lambda_depth": 0.1}, {"anchors": 0}):
        args = {"rates": None, "lambda_depth": 0.0, "anchors": 1, **bad}
        with pytest.raises(ValueError, match="frozen anchors"):
            model.step(frame, depth, BASE, D_START, D_END, K_VIEWS, 0.2, args["lambda_depth"], args["rates"],
                       anchors=args["anchors"], frozen=frozen)


def deblur_rates():
    from taichi_gs.stages.deblur.model import Rates
    return Rates(means=1e-4, quats=1e-3, log_scales=1e-3, opacity_logits=1e-2, colors=1e-2)


@pytest.mark.parametrize("motion, min_psnr", [("rotation", 45.0), ("rotation and translation", 42.0)])
def test_warped_exposure_follows_the_rendered_one(motion, min_psnr):
    """A k-view exposure warped from one anchor against all k views rendered: exact up to interpolation
    for a rotation, close for a translation (disocclusions)."""
    runtime.init()
    rng = np.random.default_rng(8)
    n = 2500
    cam = np.stack([rng.uniform(-1.6, 1.6, n), rng.uniform(-1.3, 1.3, n), rng.uniform(2.0, 4.0, n)], axis=1)
    splats = Splats(cam @ BASE[:3, :3].T + BASE[:3, 3], np.tile([1.0, 0, 0, 0], (n, 1)),
                    np.log(np.full((n, 3), 0.05)), np.full(n, 3.0), rng.uniform(-1, 1, (n, 1, 3)))
    d_end = np.array([0.0, 0.0, 0.0, 0.02, -0.03, 0.01])
    if motion != "rotation":
        d_end[:3] = [0.04, -0.02, 0.01]
    model = BlurScene(splats, K, WIDTH, HEIGHT, warp_margin=8)
    frame = np.zeros((HEIGHT, WIDTH, 3), np.float32)
    depth = np.full((HEIGHT, WIDTH), 3.0, np.float32)
    model.step(frame, depth, BASE, -d_end, d_end, 7, 0.2, 0.0, rates=None, anchors=1)
    warped = model.blurred.to_numpy()
    rendered = model.render_blurred(BASE, -d_end, d_end, 7)
    assert np.abs(warped - rendered).max() > 0  # not the same computation
    psnr = -10 * np.log10(np.mean((warped - rendered) ** 2))
    assert psnr > min_psnr, psnr


def test_anchor_count_follows_the_exposure_span():
    config = deblur.DeblurConfig(k=7, warp_views=True, warp_px=4.0)
    focal, depth = 200.0, 2.0
    spans = {0.5: 1, 8.0: 1, 8.5: 3, 20.0: 3, 24.5: 5, 400.0: 7}  # odd: one anchor at mid-exposure
    for span, expected in spans.items():
        d = np.array([np.zeros(6), np.r_[0, 0, 0, span / focal, 0, 0]])
        assert deblur.exposure_px(d[0], d[1], focal, depth) == pytest.approx(span)
        assert deblur._anchors(d, focal, depth, config, 7) == expected
    assert deblur._anchors(d, focal, depth, deblur.DeblurConfig(k=7), 7) == 0
    assert deblur.warp_margin(config) == 6 and deblur.warp_margin(deblur.DeblurConfig()) == 0
    assert [list(g) for g in anchor_groups(5, 2)] == [[0, 1], [2], [3, 4]]
    assert [list(g) for g in anchor_groups(8, 2)] == [[0, 1, 2], [3, 4], [5, 6, 7]]
    assert [list(g) for g in anchor_groups(8, 8)] == [[0], [1], [2], [3, 4], [5], [6], [7]]
    assert [list(g) for g in anchor_groups(3, 9)] == [[0], [1], [2]]
    assert deblur._anchors(d, focal, depth, deblur.DeblurConfig(k=8, warp_views=True, warp_px=4.0), 8) == 7
    assert deblur.PRESETS["fast"].warp_views and not deblur.PRESETS["paper"].warp_views  # paper: the method's views
    assert deblur.PRESETS["fast"].test_fit_refresh_px > 0 and deblur.PRESETS["paper"].test_fit_refresh_px == 0
