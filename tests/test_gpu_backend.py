"""The GPU execution model, checked on a GPU backend (f32) against the CPU backend.

Runs only with ``TAICHI_GS_ARCH`` set to a GPU backend: ``vulkan`` (CI: ``source scripts/vulkan.sh``
first, which gives a CPU Vulkan driver, Mesa 25's lavapipe), ``cuda`` or ``metal``; skipped
otherwise. Asking for a backend that is not there fails (BackendError), it never skips. The CPU side
runs in a subprocess (Taichi starts one backend per process) and hands back the same quantities in
an .npz: images, every parameter gradient and the pose gradient of several scenes, and the loss /
blur / Adam kernels. Both sides must agree to 1e-5 relative (per array: max |gpu - cpu| / max |cpu|);
the 640x480 scene allows threshold flips.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from taichi_gs.errors import BackendError
from taichi_gs.kernels import runtime

GPU_ARCHS = ("vulkan", "cuda", "metal")
ARCH = os.environ.get(runtime.ARCH_ENV, "").lower()
pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(ARCH not in GPU_ARCHS,
                       reason="set TAICHI_GS_ARCH=vulkan (after `source scripts/vulkan.sh`), cuda or metal to run"),
]
TESTS = Path(__file__).parent
RTOL = 1e-5
# name -> (make_scene seed, n, n_sh, dense, isotropic, width, height)
SCENES = {
    "full_sh2_dense": (3, 80, 9, 120, False, 48, 40),
    "isotropic_dc": (13, 60, 1, 40, True, 48, 40),
    "many_tiles": (21, 3000, 4, 400, False, 200, 150),
    # 1200 tiles x 256 threads: more than Taichi's SPIR-V launches (131072), so blocks loop (grid-stride)
    "grid_stride_640x480": (31, 1500, 1, 200, False, 640, 480),
}


def scene_outputs(name: str, subgroup: bool | None = None) -> dict[str, np.ndarray]:
    """Images and all gradients (f32, current backend) of a random linear loss on one scene;
    ``subgroup`` False makes the GPU backward add per pixel (the CUDA / Metal code path)."""
    import taichi as ti

    sys.path.insert(0, str(TESTS))
    import test_render as tr
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer, to_device

    seed, n, n_sh, dense, iso, width, height = SCENES[name]
    scene = tr.make_scene(seed, n=n, n_sh=n_sh, dense=dense)
    if iso:
        scene[2] = scene[2][:, :1]
    K = tr.K * [[width / tr.WIDTH], [height / tr.HEIGHT], [1.0]]
    gs = DeviceGaussians.from_numpy(*scene, isotropic=iso, dtype=ti.f32)
    rast = Rasterizer(ti.f32)
    if subgroup is not None:
        rast.gpu.subgroup = subgroup
    view = rast.forward(gs, Camera(K, tr.POSE, width, height), background=tr.BACKGROUND)
    rgb, depth, alpha = view.to_numpy()
    rng = np.random.default_rng(seed)
    weights = [to_device(rng.normal(size=s), ti.f32) for s in ((height, width, 3), (height, width), (height, width))]
    pose = rast.backward(gs, view, *weights)
    tiles = view.tiles_per_gaussian()
    if rast.gpu is None:  # the CPU path's Gaussian-major slot offsets say the same
        np.testing.assert_array_equal(np.diff(view.offsets.to_numpy()[: n + dense + 1]), tiles)
    out = {"rgb": rgb, "depth": depth, "alpha": alpha, "pose": pose, "slots": np.array([view.n_slots]),
           "tiles_per_gaussian": tiles}
    for key, value in gs.download(grads=True).items():
        if not (iso and key in ("quats", "log_scales")):  # fixed in the isotropic variant
            out[f"d_{key}"] = value
    return {f"{name}/{k}": v for k, v in out.items()}


def kernel_outputs() -> dict[str, np.ndarray]:
    """Loss values and gradients, blur average / spread, the colour transform and its gradients, the
    densification statistic, a warped view and its gradients, and three Adam steps on (N,), (N, C) and
    (N, A, B) parameters (f32)."""
    import taichi as ti

    from taichi_gs.geometry import se3_exp
    from taichi_gs.rolling_shutter import shutter_rows
    from taichi_gs.kernels import affine, blur, density_stats, losses, warp
    from taichi_gs.kernels.optim import Adam
    from taichi_gs.kernels.splat import to_device

    rng = np.random.default_rng(0)
    pred, target = rng.uniform(0, 1, (2, 37, 45, 3))
    target = 0.6 * pred + 0.4 * target
    depth_pred, depth_target = rng.uniform(0.5, 3, (2, 37, 45))
    depth_target[rng.uniform(size=depth_target.shape) < 0.3] = 0.0
    logits = rng.normal(size=2500) * 2
    out = {}

    def dev(a):
        return to_device(a, ti.f32)

    for name, fn, a, b in (("l1", losses.l1, pred, target), ("dssim", losses.dssim, pred, target),
                           ("depth_l1", losses.masked_depth_l1, depth_pred, depth_target)):
        grad = dev(np.zeros(a.shape))
        out[name] = np.array([fn(dev(a), dev(b), grad, weight=1.5)])
        out[f"d_{name}"] = grad.to_numpy()
    seen = np.ones((37, 45), bool)
    seen[:5], seen[:, -7:] = False, False  # an unsourced border: the image losses over a pixel mask
    for name, fn in (("masked_l1", losses.l1), ("masked_dssim", losses.dssim)):
        grad = dev(np.zeros(pred.shape))
        out[name] = np.array([fn(dev(pred), dev(target), grad, weight=1.5, mask=losses.pixel_weights(seen, ti.f32))])
        out[f"d_{name}"] = grad.to_numpy()
    grad = dev(np.zeros(logits.shape))
    out["opacity"] = np.array([losses.opacity_binarization(dev(logits), grad, len(logits), weight=0.5)])
    out["d_opacity"] = grad.to_numpy()
    trans = rng.uniform(0.0, 0.8, depth_pred.shape)  # stage 2's terms: blended depth = alpha x surface depth
    grad_depth, grad_alpha = dev(np.zeros(trans.shape)), dev(np.zeros(trans.shape))
    out["stage2_depth"] = np.array(losses.normalised_depth_l1_and_coverage(
        dev(depth_pred * (1 - trans)), dev(trans), dev(depth_target), grad_depth, grad_alpha, 0.5, 1.3, 0.4))
    out["d_stage2_depth"], out["d_stage2_alpha"] = grad_depth.to_numpy(), grad_alpha.to_numpy()
    views = [rng.uniform(size=(37, 45, 3)) for _ in range(4)]
    avg = dev(np.zeros((37, 45, 3)))
    out["blur_average"] = blur.average([dev(v) for v in views], avg).to_numpy()
    share = dev(np.zeros((37, 45, 3)))
    out["blur_spread"] = blur.spread(dev(pred), 4, share).to_numpy()
    grad = dev(np.zeros(pred.shape))
    out["clipped_mse"] = np.array([losses.l1_and_clipped_mse(dev(1.2 * pred - 0.1), dev(target), grad)[1]])
    M = np.hstack([np.eye(3), np.zeros((3, 1))]) + 0.05 * rng.normal(size=(3, 4))
    moved, grad_image = dev(np.zeros(pred.shape)), dev(np.zeros(pred.shape))
    out["affine"] = affine.forward(dev(pred), M, moved).to_numpy()
    out["d_affine_M"] = affine.backward(dev(pred), M, dev(target - 0.5), grad_image)
    out["d_affine_image"] = grad_image.to_numpy()
    means, grad_means = rng.normal(size=(2, 300, 3))
    grad_means[5] = 0.0
    pose = np.eye(4)
    pose[:3, 3] = [0.1, -0.2, -2.0]
    out["density_stats"] = density_stats.image_plane_gradient(dev(means), dev(grad_means), 300, pose, 40.0)
    margin, K = 4, np.array([[40.0, 0.0, 22.5], [0.0, 40.0, 18.5], [0.0, 0.0, 1.0]])
    anchor = rng.uniform(size=(37 + 2 * margin, 45 + 2 * margin, 3))
    alpha = np.where(rng.uniform(size=anchor.shape[:2]) < 0.9, 0.95, 0.1)  # a few pixels without a surface
    anchor_depth = (2.0 + 0.2 * np.sin(np.arange(anchor.shape[1]) / 6.0))[None, :] * alpha
    M = se3_exp(np.array([0.03, -0.02, 0.01, 0.02, -0.03, 0.01]))
    views = np.stack([M, se3_exp(np.array([-0.02, 0.01, 0.0, 0.01, 0.02, -0.01])) @ M,
                      np.eye(4)])  # the last at the anchor's own pose
    warped, z, grad_anchor = dev(np.zeros(pred.shape)), dev(np.zeros((3, 37, 45))), dev(np.zeros(anchor.shape))
    warp.accumulate(dev(anchor), dev(anchor_depth), dev(1.0 - alpha), views, K, margin, 2.0, 0.5, warped, z,
                    first=True)
    out["warp"], out["warp_depth"] = warped.to_numpy(), z.to_numpy()
    out["d_warp_pose"] = warp.backward(dev(target - 0.5), dev(anchor), z, views, K, margin, 0.5, grad_anchor)
    out["d_warp_anchor"] = grad_anchor.to_numpy()
    out["d_warp_pose_only"] = warp.backward(dev(target - 0.5), dev(anchor), z, views, K, margin, 0.5, None)
    rows = views[:2, None] @ shutter_rows(np.array([0.01, 0.0, -0.01, 0.02, 0.01, -0.02]), 37)[None]  # rolling
    grad_anchor.fill(0.0)
    warp.accumulate(dev(anchor), dev(anchor_depth), dev(1.0 - alpha), rows, K, margin, 2.0, 0.5, warped, z, first=True)
    out["warp_rows"] = warped.to_numpy()
    out["d_warp_rows_pose"] = warp.backward(dev(target - 0.5), dev(anchor), z, rows, K, margin, 0.5, grad_anchor)
    out["d_warp_rows_anchor"] = grad_anchor.to_numpy()
    shapes = {"x": (300, 3), "y": (300,), "z": (300, 4, 3)}
    params = {name: dev(rng.normal(size=shape)) for name, shape in shapes.items()}
    grads = {name: dev(np.zeros(shape)) for name, shape in shapes.items()}
    opt = Adam(params, grads, {name: 0.01 for name in shapes})
    for _ in range(3):
        for name, shape in shapes.items():
            grads[name].from_numpy(rng.normal(size=shape).astype(np.float32))
        opt.step()
    for name in shapes:
        out[f"adam_{name}"] = params[name].to_numpy()
    return {f"kernels/{k}": v for k, v in out.items()}


REFINE_STEPS = 3
ADAM_MOVE_TOL = 1e-3  # see test_stage2_refine_steps_match_cpu


def refine_outputs() -> dict[str, np.ndarray]:
    """A few stage-2 steps (taichi_gs.stages.refine.model.DepthRefiner, f32): a noisy, partly transparent
    layer of Gaussians pulled onto a tilted plane's depth seen by two cameras. Per step the loss
    values, both cameras' pose gradients and the Gaussians' gradients; after the steps how far the
    centres and opacity logits moved."""
    from taichi_gs.geometry import se3_exp
    from taichi_gs.stages.refine.model import DepthRefiner

    rng = np.random.default_rng(7)
    width, height = 64, 48
    K = np.array([[55.0, 0.0, 31.5], [0.0, 55.0, 23.5], [0.0, 0.0, 1.0]])
    gx, gy = np.meshgrid(np.linspace(-1.4, 1.4, 36), np.linspace(-1.0, 1.0, 26))
    means = np.stack([gx, gy, 2.0 + 0.2 * gx], axis=-1).reshape(-1, 3) + rng.normal(0, 0.03, (gx.size, 3))
    logits = rng.normal(0.5, 1.0, len(means))
    poses = [np.eye(4), se3_exp(np.array([0.06, -0.03, 0.01, 0.01, 0.03, -0.01]))]
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    targets = []
    for pose in poses:  # camera z of the plane z - 0.2 x = 2 along each pixel's ray
        d, o = rays @ pose[:3, :3].T, pose[:3, 3]
        depth = (2.0 - o[2] + 0.2 * o[0]) / (d[..., 2] - 0.2 * d[..., 0])
        depth[rng.uniform(size=depth.shape) < 0.1] = 0.0  # sensor holes
        targets.append(depth)
    model = DepthRefiner(means, logits, scale=0.04, K=K, width=width, height=height)
    out = {}
    for step in range(REFINE_STEPS):
        values, pose_grads = model.step(targets, poses, lambda_depth=1.0, lambda_coverage=0.3, lambda_opacity=0.01,
                                        lrs={"means": 2e-3, "opacity_logits": 0.05})
        out[f"losses_{step}"] = np.array([values["depth"], values["coverage"], values["opacity"]])
        out[f"pose_grads_{step}"] = np.stack(pose_grads)
        for name in ("means", "opacity_logits"):  # the step's gradients (Adam leaves them in place)
            out[f"d_{name}_{step}"] = model.gaussians.grads[name].to_numpy()[: model.count]
    kept = model.kept_indices()  # the steps move the Gaussians by ~1e-2: compare the moves, not the positions
    out["means_moved"] = model.means() - means[kept].astype(np.float32)
    out["logits_moved"] = model.opacity_logits() - logits[kept].astype(np.float32)
    return {f"refine/{k}": v for k, v in out.items()}


def all_outputs() -> dict[str, np.ndarray]:
    out = kernel_outputs()
    out.update(refine_outputs())
    for name in SCENES:
        out.update(scene_outputs(name))
    return out


CPU_SCRIPT = """
import sys
import numpy as np
sys.path.insert(0, {tests!r})
from taichi_gs.kernels import runtime
runtime.init("cpu")
import test_gpu_backend
np.savez({path!r}, **test_gpu_backend.all_outputs())
"""


@pytest.fixture(scope="module")
def backend():
    got = runtime.init()  # TAICHI_GS_ARCH names the GPU: a BackendError here fails loudly
    assert got.arch == ARCH, got
    return got


@pytest.fixture(scope="module")
def cpu_reference(tmp_path_factory) -> dict[str, np.ndarray]:
    path = tmp_path_factory.mktemp("cpu") / "cpu.npz"
    env = dict(os.environ, **{runtime.ARCH_ENV: "cpu"})
    script = CPU_SCRIPT.format(tests=str(TESTS), path=str(path))
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr[-3000:]
    with np.load(path) as data:
        return dict(data)


def test_atomic_loop_canary(backend) -> None:
    """Mesa 22's lavapipe drops loop iterations that contain an atomic (bookworm's driver counted
    8 of 400000); the rasterizer's binning relies on them. Use Mesa >= 25 (scripts/vulkan.sh)."""
    from taichi_gs.kernels import canary

    for got, want in canary.atomic_loop_counts():
        assert got == want, f"the {ARCH} driver dropped atomic loop iterations: {got} of {want} ({backend.device})"


@pytest.mark.skipif(ARCH == "cuda", reason="CUDA has float64 (tests/test_render.py checks it there)")
def test_f64_is_refused_with_a_clear_error(backend) -> None:
    import taichi as ti

    from taichi_gs.render import Rasterizer

    from taichi_gs.render import DeviceGaussians, rasterize, to_device

    with pytest.raises(BackendError, match="CPU or CUDA"):
        Rasterizer(ti.f64)
    with pytest.raises(BackendError, match="CPU or CUDA"):
        DeviceGaussians(4, dtype=ti.f64)
    with pytest.raises(BackendError, match="CPU or CUDA"):
        to_device(np.zeros(3), ti.f64)
    with pytest.raises(BackendError, match="CPU or CUDA"):
        rasterize(np.zeros((1, 3)), np.ones((1, 4)), np.zeros((1, 3)), np.zeros(1), np.zeros((1, 3)),
                  np.eye(3), np.eye(4), 8, 8, precision="f64")


def test_forward_matches_numpy_reference(backend) -> None:
    sys.path.insert(0, str(TESTS))
    import test_render as tr

    assert tr.check_forward_matches_reference("f32") < 2e-5


# At 640x480 some of the ~6M threshold tests (alpha >= 1/255, the 3-sigma cut-off, the 1e-4
# transmittance stop) land within an ulp of exp's last bit, and lavapipe's exp and LLVM's differ
# there: one Gaussian flips in or out at a pixel (measured: 2 of 307200 pixels, up to 3.4e-4). Such
# a scene gets: all but 1e-4 of the pixels within RTOL, every pixel within 1e-3, gradients 1e-4.
FLIP_PIXEL_SHARE, FLIP_IMAGE_TOL, FLIP_GRAD_TOL = 1e-4, 1e-3, 1e-4


@pytest.mark.parametrize("name", sorted(SCENES))
def test_rasterizer_matches_cpu(backend, cpu_reference, name) -> None:
    import taichi as ti

    from taichi_gs.render import Rasterizer

    assert Rasterizer(ti.f32).gpu is not None, "the block-per-tile kernels should run on a GPU backend"
    got = scene_outputs(name)
    assert got[f"{name}/slots"][0] == cpu_reference[f"{name}/slots"][0]
    assert got[f"{name}/alpha"].max() > 0.99, "scene should reach full opacity somewhere"
    large = got[f"{name}/depth"].size > 100_000
    for key, value in got.items():
        if large and key.split("/")[1] in ("rgb", "depth", "alpha"):
            want = cpu_reference[key]
            err = np.abs(value - want).reshape(want.shape[0], want.shape[1], -1).max(axis=2) / np.abs(want).max()
            assert (err > RTOL).mean() <= FLIP_PIXEL_SHARE and err.max() <= FLIP_IMAGE_TOL, (key, err.max())
        else:
            check_close(key, value, cpu_reference[key], FLIP_GRAD_TOL if large else RTOL)


@pytest.mark.parametrize("check", ["test_empty_scene", "test_all_gaussians_culled_renders_background",
                                   "test_rgb_colours_are_sh_dc_and_result_shapes",
                                   "test_device_api_views_accumulate_gradients"])
def test_render_checks_in_f32_on_the_gpu(backend, check) -> None:
    """tests/test_render.py's float32 checks (empty and fully culled scenes, shapes, several views)."""
    sys.path.insert(0, str(TESTS))
    import test_render as tr

    getattr(tr, check)()


def test_backward_without_subgroup_sums_matches_cpu(backend, cpu_reference) -> None:
    """The per-pixel atomic backward that CUDA and Metal run (no Taichi subgroup ops there)."""
    for key, value in scene_outputs("many_tiles", subgroup=False).items():
        check_close(key, value, cpu_reference[key])


def test_many_tiles_scene_needs_several_batches_per_tile(backend) -> None:
    """A tile with more than 256 records makes the blend load several shared-memory batches."""
    import taichi as ti

    sys.path.insert(0, str(TESTS))
    import test_render as tr
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer

    seed, n, n_sh, dense, _, width, height = SCENES["many_tiles"]
    gs = DeviceGaussians.from_numpy(*tr.make_scene(seed, n=n, n_sh=n_sh, dense=dense))
    K = tr.K * [[width / tr.WIDTH], [height / tr.HEIGHT], [1.0]]
    view = Rasterizer(ti.f32).forward(gs, Camera(K, tr.POSE, width, height))
    ranges = view.tile_range.to_numpy()[: -(-width // 16) * -(-height // 16)]
    assert (ranges[:, 1] - ranges[:, 0]).max() > 256 and view.n_slots > 4 * 1024


def test_prefix_sum_and_radix_sort_match_numpy(backend) -> None:
    import taichi as ti

    from taichi_gs.kernels import scan

    scratch = scan.Scratch()
    rng = np.random.default_rng(0)
    # 300k: grid-stride blocks on Vulkan; 256**3 + 12345: all four scan levels hold more than one element
    for n in (0, 1, 256, 257, 70_000, 300_000, 256**3 + 12_345):
        x = rng.integers(0, 20, n).astype(np.int32)
        src, dst = ti.ndarray(ti.i32, (max(n, 1),)), ti.ndarray(ti.i32, (n + 1,))
        if n:
            src.from_numpy(x)
        scan.exclusive_scan(src, dst, n, scratch)
        np.testing.assert_array_equal(dst.to_numpy(), np.concatenate([[0], np.cumsum(x)]))
    for n, bits in ((3, 4), (5000, 11), (40_000, 31)):
        keys = rng.integers(0, 2**bits, n).astype(np.int32)
        keys[::7] = keys[0]  # many ties: the sort must be stable
        dev_keys, dev_vals = ti.ndarray(ti.i32, (n,)), ti.ndarray(ti.i32, (n,))
        dev_keys.from_numpy(keys)
        dev_vals.from_numpy(np.arange(n, dtype=np.int32))
        out_keys, out_vals = scan.radix_sort(dev_keys, dev_vals, n, bits, scratch)
        want = np.argsort(keys, kind="stable")
        np.testing.assert_array_equal(out_vals.to_numpy()[:n], want)
        np.testing.assert_array_equal(out_keys.to_numpy()[:n], keys[want])


def test_gpu_projection_and_binning_match_reference_parts(backend) -> None:
    """The GPU path's parts alone (see tests/test_kernel_parts.py for the CPU path): its projection
    against reference_renderer.project (f64), and its binning + radix sorts against
    reference_renderer.bin_tiles applied to the GPU's own records (so f32 rounding cannot move a
    Gaussian across a tile border or swap near-equal depths between the two)."""
    import taichi as ti

    sys.path.insert(0, str(TESTS))
    import reference_renderer as ref
    import test_kernel_parts as parts
    import test_render as tr
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer

    params = parts.scene(3)
    params[0][81] = params[0][80]  # a depth tie: the order falls back to the Gaussian index
    n = len(params[0])
    rast = Rasterizer(ti.f32)
    assert rast.gpu is not None
    view = rast.forward(DeviceGaussians.from_numpy(*params, dtype=ti.f32), Camera(tr.K, tr.POSE, tr.WIDTH, tr.HEIGHT))
    want = ref.project(*params, tr.K, tr.POSE, tr.WIDTH, tr.HEIGHT)
    rect = view.rect.to_numpy()[:n]
    visible = rect[:, 0] <= rect[:, 2]
    np.testing.assert_array_equal(visible, want["visible"])
    assert np.abs(rect[visible] - want["rect"][visible]).max() <= 1  # a box edge may round the other way
    assert (rect[visible] != want["rect"][visible]).mean() < 0.01
    got = view.proj.to_numpy()[:n][visible]
    expected = parts.record_columns(want)[visible]
    err = np.abs(got - expected).max(axis=0) / np.abs(expected).max(axis=0)
    assert err.max() < 2e-5, dict(enumerate(err))

    proj = view.proj.to_numpy()[:n].astype(np.float64)
    lists = ref.bin_tiles({"visible": visible, "rect": rect, "depth": proj[:, parts.P_DEPTH]}, tr.WIDTH, tr.HEIGHT)
    ranges = view.tile_range.to_numpy()[: len(lists)]
    gid = view.slot_gid.to_numpy()[view.order.to_numpy()[: view.n_slots]]
    assert view.n_slots == sum(len(ids) for ids in lists) and max(len(ids) for ids in lists) > 100
    for t, ids in enumerate(lists):
        np.testing.assert_array_equal(gid[ranges[t, 0]:ranges[t, 1]] if len(ids) else [], ids, err_msg=f"tile {t}")


def test_gpu_blend_matches_reference_given_reference_lists(backend) -> None:
    """The GPU blend kernel alone (block per tile, shared-memory batches), fed the reference's
    records and tile lists, against reference_renderer.blend_tiles (f64)."""
    import taichi as ti

    sys.path.insert(0, str(TESTS))
    import reference_renderer as ref
    import test_kernel_parts as parts
    import test_render as tr
    from taichi_gs.kernels.rasterize import E_BOX, E_WIDTH
    from taichi_gs.render import Rasterizer, to_device

    params = tr.make_scene(8, n=80, n_sh=9, dense=400)
    rec = ref.project(*params, tr.K, tr.POSE, tr.WIDTH, tr.HEIGHT)
    lists = ref.bin_tiles(rec, tr.WIDTH, tr.HEIGHT)
    want = ref.blend_tiles(rec, lists, tr.WIDTH, tr.HEIGHT, background=tr.BACKGROUND)
    ids = np.concatenate(lists)
    entries = np.zeros((len(ids), E_WIDTH))
    entries[:, :parts.P_WIDTH] = parts.record_columns(rec)[ids]
    entries[:, E_BOX:E_BOX + 4] = rec["rect"][ids]
    ends = np.cumsum([len(i) for i in lists])
    tile_range = ti.ndarray(ti.i32, (len(lists), 2))
    tile_range.from_numpy(np.stack([ends - [len(i) for i in lists], ends], axis=1).astype(np.int32))
    assert max(len(i) for i in lists) > 256, "a tile needing two shared-memory batches"
    h, w = tr.HEIGHT, tr.WIDTH
    images = [ti.ndarray(ti.f32, (h, w, 3)), ti.ndarray(ti.f32, (h, w)), ti.ndarray(ti.f32, (h, w)),
              ti.ndarray(ti.i32, (h, w))]
    Rasterizer(ti.f32).gpu.k.blend_forward(-(-w // 16), len(lists), w, h, tile_range, to_device(entries, ti.f32),
                                           ti.Vector(tr.BACKGROUND, dt=ti.f32), *images)
    rgb, depth, trans, last = (a.to_numpy() for a in images)
    for name, got, expected in (("rgb", rgb, want[0]), ("depth", depth, want[1]), ("alpha", 1 - trans, want[2])):
        assert np.abs(got - expected).max() <= 2e-5 * np.abs(expected).max(), name
    np.testing.assert_array_equal(last, want[3])


def test_losses_blur_adam_match_cpu(backend, cpu_reference) -> None:
    for key, value in kernel_outputs().items():
        check_close(key, value, cpu_reference[key])


def test_stage2_refine_steps_match_cpu(backend, cpu_reference) -> None:
    """Stage 2 on the GPU: each step's loss values, pose gradients and Gaussian gradients match the
    CPU f32 run to 1e-5; so do the Gaussians' moves after the steps, to ADAM_MOVE_TOL: Adam divides
    each gradient by its own running size, so a small gradient's last-bit difference (the GPU sums
    pixels in another order) becomes a difference relative to the learning rate (measured 1.6e-4)."""
    from taichi_gs.render import Rasterizer

    assert Rasterizer().gpu is not None
    got = refine_outputs()
    assert len(got) == 4 * REFINE_STEPS + 2
    for key, value in got.items():
        check_close(key, value, cpu_reference[key], ADAM_MOVE_TOL if key.endswith("_moved") else RTOL)


def check_close(key: str, got: np.ndarray, want: np.ndarray, rtol: float = RTOL) -> None:
    assert got.shape == want.shape, key
    scale = float(np.abs(want).max())
    assert scale > 0, f"{key}: the CPU reference is all zero, the comparison would prove nothing"
    err = float(np.abs(got.astype(np.float64) - want).max()) / scale
    assert err <= rtol, f"{key}: {ARCH} differs from cpu by {err:.2e} (relative to max |cpu| {scale:.3g})"
