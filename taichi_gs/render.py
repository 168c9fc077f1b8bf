"""The one door to the rasterizer: render Gaussians from a pinhole camera, and back-propagate.

Two ways in:

* :func:`rasterize` — NumPy in, NumPy out, for tests, tools and one-off renders. Returns a
  :class:`RenderResult` whose ``backward(d_rgb, d_depth, d_alpha)`` gives :class:`RenderGrads`.
* The device-resident API for training loops (parameters, gradients, images and optimiser state
  stay in Taichi ndarrays; what comes back, pose gradients and loss values, comes in one read per step):
  :class:`DeviceGaussians` (``params`` / ``grads`` dicts of ndarrays), :class:`Rasterizer`
  (``forward(gaussians, camera, view=i) -> View`` with ``.rgb`` (H, W, 3), ``.depth``,
  ``.transmittance`` (= 1 - alpha) ndarrays; ``backward(gaussians, view, d_rgb=, d_depth=,
  d_alpha=) -> np.ndarray (6,)`` pose gradient, parameter gradients ADDED to ``gaussians.grads``; a
  training step renders ``deferred=True`` and passes ``pose_into=`` a row of its :class:`StepValues`),
  ``StepValues`` (what a step's kernels leave for the host, in named slots, read in one go: the pose
  rows, then ``Rasterizer.pose_gradients(rows)``: None when a view overflowed its slot buffers),
  ``losses`` (value returned, ``weight * gradient`` added into a given ndarray, or the value left in a
  slot, ``into=``), ``blur`` (k-view average and its gradient), ``affine`` (a frame's affine colour
  transform and its gradient), ``density_stats`` (each Gaussian's positional gradient in pixels summed on
  the device, for densification), ``warp`` ([ours] a view near an anchor's pose sampled from the anchor's
  render through its depth), ``Adam``,
  ``to_device`` (upload targets) and ``host_copy`` (``read`` / ``write`` between NumPy and an ndarray
  without a copy kernel on the CPU backend), all re-exported here.

Stage 2 (isotropic fixed scale, depth only; ``K`` from ``geometry.raster_intrinsics``)::

    gs = DeviceGaussians.from_numpy(means, None, np.full(n, log_s), logits, np.zeros((n, 1, 3)),
                                    isotropic=True)
    rast = Rasterizer()
    adam = Adam(gs.params, gs.grads, {"means": 1.6e-4 * extent, "opacity_logits": 0.05})
    target, g_depth = to_device(depth_i, gs.dtype), to_device(np.zeros((h, w)), gs.dtype)
    view = rast.forward(gs, Camera(K, poses[i], w, h), with_colour=False)  # depth and alpha only
    gs.zero_grad(); g_depth.fill(0.0)
    l_d = losses.masked_depth_l1(view.depth, target, g_depth, weight=lam_d)
    l_o = losses.opacity_binarization(gs.params["opacity_logits"], gs.grads["opacity_logits"], n,
                                      weight=lam_o)
    pose_grad = rast.backward(gs, view, d_depth=g_depth)   # means/opacity grads in gs.grads
    adam.step(n)                                            # poses: update on the host

Stage 3 (k virtual views of one blurred frame)::

    taus = np.linspace(0, 1, k)
    views = [rast.forward(gs, Camera(K, virtual_pose(T, d_s, d_e, tau), w, h), view=j,  # geometry.py
                          deferred=True) for j, tau in enumerate(taus)]
    blur.average([v.rgb for v in views], blurred)
    g_blur.fill(0.0)
    losses.l1(blurred, frame, g_blur, weight=1 - lam); losses.dssim(blurred, frame, g_blur, weight=lam)
    blur.spread(g_blur, k, g_view)                          # dL/d(each view) = dL/dblur / k
    gs.zero_grad()
    rows = values.rows("poses", k, POSE_COLUMNS)            # values: the step's StepValues, cleared
    for j, v in enumerate(views):
        rast.backward(gs, v, d_rgb=g_view, pose_into=rows.row(j))   # the pose gradient stays on the device
    pose_grads = rast.pose_gradients(values.read()["poses"])  # one read; None: a view overflowed, run again
    g_s, g_e, _ = exposure_pose_gradients(T, d_s, d_e, taus, pose_grads)   # from geometry.py
    adam.step()

Conventions: ``K`` uses the rasterizer's pixel centres (pixel u samples image coordinate u + 0.5;
``geometry.raster_intrinsics`` converts OpenCV intrinsics); ``cam_to_world`` is a 4x4 OpenCV pose.
Colours are SH coefficients, DC first: degree 0 renders ``0.2820948 * dc + 0.5`` (clamped at 0),
as in 3DGS. Depth is the alpha-blended camera z, not divided by alpha. The pose gradient is for
the left perturbation ``exp(delta) @ cam_to_world``, ``delta = [translation, rotation]``. A pixel
receives a Gaussian where ``o exp(power) >= 1/255`` within 3 sigma (see ``kernels.project``).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from .geometry import raster_intrinsics
from .kernels import affine, blur, density_stats, host_copy, losses, runtime, warp
from .kernels.optim import Adam
from .kernels.splat import POSE_COLUMNS, Camera, DeviceGaussians, Rasterizer, View, float_type, to_device
from .kernels.step_values import Slot, StepValues
from .splats import Splats

__all__ = [
    "Camera", "DeviceGaussians", "Rasterizer", "View", "RenderGrads", "RenderResult", "rasterize",
    "to_device", "losses", "blur", "affine", "density_stats",
    "Adam", "render_views", "upload_splats", "warp", "host_copy", "StepValues", "Slot", "POSE_COLUMNS",
]


@dataclass
class RenderGrads:
    """Gradients of a scalar loss w.r.t. every rasterizer input (NumPy, input shapes)."""

    means: np.ndarray
    quats: np.ndarray
    log_scales: np.ndarray
    opacity_logits: np.ndarray
    colors: np.ndarray
    pose: np.ndarray  # (6,) [translation, rotation], left perturbation of cam_to_world


@dataclass
class RenderResult:
    """Rendered images (float32): rgb (H, W, 3), depth (H, W), alpha (H, W)."""

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    _rasterizer: Rasterizer
    _gaussians: DeviceGaussians
    _view: View
    _colors_shape: tuple

    def backward(self, d_rgb=None, d_depth=None, d_alpha=None) -> RenderGrads:
        """Gradients given dL/d rgb (H, W, 3), dL/d depth (H, W), dL/d alpha (H, W); None = 0."""
        height, width = self.depth.shape
        dtype = self._rasterizer.dtype

        def upload(arr, shape):
            return None if arr is None else to_device(np.reshape(arr, shape), dtype)

        self._gaussians.zero_grad()
        pose = self._rasterizer.backward(
            self._gaussians, self._view,
            upload(d_rgb, (height, width, 3)), upload(d_depth, (height, width)), upload(d_alpha, (height, width)),
        )
        g = self._gaussians.download(grads=True)
        return RenderGrads(
            means=g["means"], quats=g["quats"], log_scales=g["log_scales"],
            opacity_logits=g["opacity_logits"], colors=g["colors"].reshape(self._colors_shape), pose=pose,
        )


def rasterize(
    means: np.ndarray,
    quats: np.ndarray,
    log_scales: np.ndarray,
    opacity_logits: np.ndarray,
    colors: np.ndarray,
    K: np.ndarray,
    cam_to_world: np.ndarray,
    width: int,
    height: int,
    background=(0.0, 0.0, 0.0),
    precision: str = "f32",
) -> RenderResult:
    """Render N Gaussians: means (N, 3), quats (N, 4) w x y z, log_scales (N, 3), opacity_logits
    (N,), colors (N, 3) SH DC or (N, M, 3) SH with M in {1, 4, 9, 16}; ``precision`` "f32"|"f64"."""
    runtime.init()
    dtype = float_type(precision)
    colors = np.asarray(colors)
    gaussians = DeviceGaussians.from_numpy(means, quats, log_scales, opacity_logits, colors, dtype=dtype)
    rasterizer = Rasterizer(dtype)
    camera = Camera(np.asarray(K), np.asarray(cam_to_world), int(width), int(height))
    view = rasterizer.forward(gaussians, camera, background=background)
    rgb, depth, alpha = view.to_numpy()
    return RenderResult(rgb, depth, alpha, rasterizer, gaussians, view, colors.shape)


def upload_splats(splats: Splats) -> DeviceGaussians:
    """``splats`` as float32 device Gaussians (DeviceGaussians starts the runtime if needed)."""
    return DeviceGaussians.from_numpy(splats.means, splats.quats, splats.log_scales, splats.opacity_logits, splats.sh)


def render_views(
    splats: Splats, K: np.ndarray, width: int, height: int, poses: Iterable[np.ndarray], background=(0.0, 0.0, 0.0)
) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Render one scene from many cameras: yields (rgb, depth, alpha) float32 per pose. ``K`` is in
    the data's OpenCV convention; the Gaussians are uploaded once."""
    gaussians = upload_splats(splats)
    rasterizer = Rasterizer(gaussians.dtype)
    K_raster = raster_intrinsics(K)
    for pose in poses:
        view = rasterizer.forward(gaussians, Camera(K_raster, pose, int(width), int(height)), background=background)
        yield view.to_numpy()
