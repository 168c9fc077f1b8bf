"""Stage 3's trainable scene: full 3D Gaussians (SH colour, opacity, anisotropic scale, rotation,
position) kept on the device, trained against blurred frames through the k-view blur model, with
3DGS-style densification and pruning (:mod:`density_control`, over the :mod:`gaussian_store`). Exposure
poses live on the host (12 numbers per frame) in :mod:`run`."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from ... import profiling
from ...gaussian_store import FIELDS, GaussianStore, OnStore, morton_order
from ...geometry import (
    exposure_pose_gradients,
    invert,
    median_depth,
    raster_intrinsics,
    relative_pose_gradients,
    so3_log,
    virtual_pose,
)
from ...noreference import eroded
from ...render import POSE_COLUMNS, Camera, Rasterizer, StepValues, affine, blur, host_copy, losses, to_device, warp
from ...rolling_shutter import shutter_rows
from ...splats import SH_C0, Splats, logit, rgb_to_sh_dc
from .density_control import DensityControl

TRAINED = FIELDS  # every parameter of a full 3D Gaussian learns in stage 3


@dataclass(frozen=True)
class Rates:
    """Adam learning rates of the Gaussian parameters for one step."""

    means: float
    quats: float
    log_scales: float
    opacity_logits: float
    colors: float


@dataclass
class BlurStep:
    """What one blurred-frame step returns: loss terms, PSNR of the re-blurred render against the
    blurred frame, and the gradients of the exposure offsets (start, end)."""

    losses: dict[str, float]
    psnr: float
    grad_start: np.ndarray
    grad_end: np.ndarray
    grad_colour: np.ndarray | None = None  # (3, 4) when a colour transform was given
    grad_bend: np.ndarray | None = None  # [ours] (6,) the exposure's bend (:func:`geometry.exposure_twist`)


def loss_pixels(sourced: np.ndarray | None, dtype) -> tuple[losses.PixelWeights | None, losses.PixelWeights | None]:
    """[ours] The pixels the photometric losses average over: L1 over ``sourced`` (H x W bool, the pixels
    the camera saw; None: all), D-SSIM over those whose whole 11 x 11 window is sourced (the frame's
    own edges do not count as unsourced)."""
    if sourced is None:
        return None, None
    inner = eroded(sourced, losses.SSIM_RADIUS)
    return losses.pixel_weights(sourced, dtype), losses.pixel_weights(inner if inner.any() else sourced, dtype)


def exposure_taus(k: int) -> np.ndarray:
    """Exposure fractions of the k virtual views: linspace(0, 1, k), or the middle alone for k = 1."""
    return np.linspace(0.0, 1.0, k) if k > 1 else np.array([0.5])


def anchor_count(k: int, anchors: int) -> int:
    """[ours] Anchor renders for k virtual views when ``anchors`` are wanted: the least odd number not
    below it, at most the largest odd number not above k, so that one anchor sits at the exposure's middle."""
    return min(max(anchors, 1) | 1, k if k % 2 else k - 1)


def anchor_groups(k: int, anchors: int) -> list[np.ndarray]:
    """[ours] The k virtual views split into :func:`anchor_count` runs of neighbours, each warped from one
    anchor render at the mean exposure fraction of its run. The runs' sizes are symmetric about the middle
    run, whose anchor therefore sits at tau = 1/2: the mid-exposure pose, where the depth loss compares the
    render with the frame's depth and the densification statistics are gathered."""
    count = anchor_count(k, anchors)
    sizes = np.full(count, k // count)
    extra, middle = k % count, count // 2
    sizes[middle] += extra % 2
    for i in range(extra // 2):
        sizes[middle - 1 - i] += 1
        sizes[middle + 1 + i] += 1
    return np.split(np.arange(k), np.cumsum(sizes)[:-1])


def warped_views(k: int, anchors: int) -> int:
    """[ours] How many of k virtual views are interpolated from an anchor render: all but the middle view of
    each odd-sized group (:func:`anchor_groups`), which sits at its anchor's own pose and is read, not
    interpolated (``kernels.warp``); with no anchors, all k (each is rendered)."""
    if anchors < 1:
        return k
    return sum(len(group) - len(group) % 2 for group in anchor_groups(k, anchors))


ANCHOR_VIEWS = 1000  # rasterizer view buffers of the padded anchor renders (apart from the k full renders')
FROZEN_VIEWS = 2000  # those of :class:`FrozenAnchors` (kept across steps, so apart from the others)
DEPTH_INSTANT_VIEW = 3000  # the view buffer of :meth:`BlurScene.depth_instant_step`'s render


class FrozenAnchors:
    """[ours] Anchor renders kept across the steps of a held-out fit (the scene frozen: only the exposure
    moves): each step warps its virtual views from them, and the anchors are rendered again only when
    their number changes or one would move more than ``refresh_px`` on the image (at ``depth`` metres,
    focal ``focal`` px) from where it was rendered. The loss then depends on the exposure through the
    warps alone, so a step needs no rasterizer backward."""

    def __init__(self, refresh_px: float, focal: float, depth: float) -> None:
        self.refresh_px, self.focal, self.depth = refresh_px, focal, depth
        self.poses: list[np.ndarray] = []
        self.views: list = []
        self.renders = 0  # anchor renders made (for tests and benchmarks)

    def anchors(self, scene: BlurScene, wanted: list[np.ndarray]) -> tuple[list, list[np.ndarray]]:
        """(views, the poses they were rendered at) for anchors wanted at poses ``wanted``."""
        if len(wanted) != len(self.poses) or any(self._moved_px(old, new) > self.refresh_px
                                                  for old, new in zip(self.poses, wanted)):
            self.poses = [np.array(pose) for pose in wanted]
            self.views = [scene.rasterizer.forward(scene.gaussians, scene.padded_camera(pose), view=FROZEN_VIEWS + a)
                          for a, pose in enumerate(self.poses)]
            self.renders += len(self.poses)
        return self.views, self.poses

    def _moved_px(self, old: np.ndarray, new: np.ndarray) -> float:
        """Image travel (pixels) from camera ``old`` to ``new`` for points at ``depth`` (as ``exposure_px``)."""
        relative = invert(old) @ new
        angle = np.linalg.norm(so3_log(relative[:3, :3]))
        return float(self.focal * (np.linalg.norm(relative[:3, 3]) / self.depth + angle))


class BlurScene(OnStore):
    """Gaussians rendered at one resolution (``K`` in OpenCV convention; the rasterizer's half-pixel
    shift is applied here). :meth:`step` takes one blurred frame's k-view loss and updates the
    Gaussians (``store``); ``density`` observes the steps and grows and trims them. ``precision``
    "f64" (CPU/CUDA only) serves the finite-difference tests."""

    def __init__(self, splats: Splats, K: np.ndarray, width: int, height: int, precision: str = "f32",
                 sourced: np.ndarray | None = None, warp_margin: int = 0):
        self.K = raster_intrinsics(K)
        self.warp_margin = warp_margin  # [ours] pixels added on each side of the anchor renders of warped steps
        self.width, self.height = width, height
        self.store = GaussianStore(_as_arrays(splats), TRAINED, precision=precision)
        self.rasterizer = Rasterizer(self.store.dtype)
        self.density = DensityControl(self.count)
        dtype = self.gaussians.dtype
        self.frame = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.depth_target = to_device(np.zeros((height, width), np.float32), dtype)
        self.blurred = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.compensated = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_compensated = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_blur = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_view = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_depth = to_device(np.zeros((height, width), np.float32), dtype)
        self.sourced = sourced
        self.l1_pixels, self.ssim_pixels = loss_pixels(sourced, dtype)
        self.step_values = StepValues(dtype)  # what a step's kernels leave for the host, read once per step
        padded = (height + 2 * warp_margin, width + 2 * warp_margin)
        self.padded_depth_target = to_device(np.zeros(padded, np.float32), dtype)
        self.padded_grad_depth = to_device(np.zeros(padded, np.float32), dtype)
        self.warp_depths: list = []  # per anchor (views, H, W): the warp's depths, for its backward
        self.grad_anchor = None  # (H + 2m, W + 2m, 3): dL/d an anchor's colour
        self._rows: dict[bytes, np.ndarray] = {}  # shutter_rows of the readout motions seen, at this height

    def camera(self, cam_to_world: np.ndarray) -> Camera:
        return Camera(self.K, cam_to_world, self.width, self.height)

    def warp_buffers(self, anchors: int, views: int) -> list:
        """[ours] At least ``anchors`` device buffers of the warp's depths, each for at least ``views`` views."""
        dtype = self.gaussians.dtype
        for a in range(anchors):
            if a == len(self.warp_depths) or self.warp_depths[a].shape[0] < views:
                buffer = to_device(np.zeros((views, self.height, self.width), np.float32), dtype)
                self.warp_depths[a:a + 1] = [buffer]
        return self.warp_depths

    def anchor_gradient(self):
        """[ours] The zeroed device buffer of dL/d an anchor render's colour."""
        m = self.warp_margin
        if self.grad_anchor is None:
            self.grad_anchor = to_device(np.zeros((self.height + 2 * m, self.width + 2 * m, 3), np.float32),
                                         self.gaussians.dtype)
        self.grad_anchor.fill(0.0)
        return self.grad_anchor

    def shutter_rows(self, readout_motion: np.ndarray | None) -> np.ndarray | None:
        """[ours] :func:`shutter_rows` at this scene's height (kept for the motions seen), None for a global
        shutter (None or a zero motion)."""
        if readout_motion is None or not np.any(readout_motion):
            return None
        key = np.asarray(readout_motion, dtype=np.float64).tobytes()
        if key not in self._rows:
            self._rows[key] = shutter_rows(readout_motion, self.height)
        return self._rows[key]

    def padded_camera(self, cam_to_world: np.ndarray) -> Camera:
        """The camera with ``warp_margin`` pixels more on every side (an anchor render of a warped step)."""
        m = self.warp_margin
        K = self.K.copy()
        K[0, 2] += m
        K[1, 2] += m
        return Camera(K, cam_to_world, self.width + 2 * m, self.height + 2 * m)

    @profiling.timed("step host work (uploads, fills)")
    def step(self, frame: np.ndarray, depth: np.ndarray, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray,
             k: int, lambda_dssim: float, lambda_depth: float, rates: Rates | None,
             colour: np.ndarray | None = None, anchors: int = 0, fallback_depth: float | None = None,
             observe: bool = True, frozen: FrozenAnchors | None = None,
             readout_motion: np.ndarray | None = None, bend: np.ndarray | None = None) -> BlurStep:
        """Render the frame's k virtual views, average them, apply the frame's affine ``colour``
        transform (3 x 4; None: identity), take (1 - l_B) L1 + l_B D-SSIM against ``frame`` plus
        ``lambda_depth`` times the masked depth L1 of the mid view against ``depth``, back-propagate,
        and (unless ``rates`` is None: scene frozen) apply Adam to the Gaussians, adding the step's positional
        gradients to the densification statistics when ``observe``. [ours] ``anchors`` > 0:
        render that many padded anchor views, rounded up to an odd number (:func:`anchor_groups`), and warp the
        k views from them (``kernels.warp``); the mid view is then the middle anchor, at tau = 1/2, and
        ``fallback_depth`` is the depth where an anchor has no surface (None: :func:`median_depth` of ``depth``).
        ``frozen`` (with ``anchors``, the scene frozen and no depth term: a held-out fit) keeps the anchor
        renders across steps (:class:`FrozenAnchors`); the Gaussians then get no gradients. [ours]
        ``readout_motion`` (with anchors): a rolling shutter, the camera's motion while the rows are read
        (:func:`shutter_rows`); each virtual view's rows are warped from the anchors at their own poses. The
        anchors and the mid view's depth loss stay global-shutter renders. [ours] ``bend``: the exposure's path
        bowed at its middle (:func:`geometry.exposure_twist`; None: straight), its gradient in ``grad_bend``."""
        if frozen is not None and (rates is not None or anchors < 1 or lambda_depth > 0):
            raise ValueError("frozen anchors need a frozen scene (rates None), anchors and no depth term")
        rows = self.shutter_rows(readout_motion)
        if rows is not None and anchors < 1:
            raise ValueError("a rolling shutter (readout_motion) needs warped views (anchors)")
        host_copy.write(self.frame, frame)
        fallback = median_depth(depth) if anchors > 0 and fallback_depth is None else fallback_depth
        while True:  # again when a render's tile slots overflowed its buffers (they are grown: it fits the next time)
            exposure = self._forward_backward(depth, base, d_start, d_end, exposure_taus(k), lambda_dssim,
                                              lambda_depth, colour, anchors, fallback, frozen, rows, bend)
            values = self.step_values.read()  # the step's one host read
            gradients = exposure.pose_gradients(values)
            if gradients is not None:
                break
        grad_taus, pose_grads = gradients
        grad_colour = None if colour is None else affine.matrix_gradient(values["colour"])
        g_start, g_end, g_bend = exposure_pose_gradients(base, d_start, d_end, grad_taus, pose_grads, bend)
        if rates is not None:
            if observe:
                self.density.observe(self.store, virtual_pose(base, d_start, d_end, exposure.mid_tau, bend),
                                     self.K[0, 0])
            self.store.step(vars(rates))
        return BlurStep({"l1": values["l1"], "dssim": values["dssim"], "depth": values.get("depth", 0.0)},
                        float(-10 * np.log10(max(values["mse"], 1e-12))), g_start, g_end, grad_colour, g_bend)

    def _forward_backward(self, depth, base, d_start, d_end, taus, lambda_dssim, lambda_depth, colour, anchors,
                          fallback, frozen, rows, bend=None) -> _RenderedExposure | _WarpedExposure:
        """One pass of :meth:`step` up to the Gaussians' gradients, its renders deferred, its loss values, the
        colour transform's gradient rows ("colour") and the poses' gradient rows left in :attr:`step_values`;
        returns the exposure, whose ``pose_gradients`` of the values read says whether a render's tile slots
        overflowed (then the rest is void and the pass must be run again)."""
        values = self.step_values
        values.clear()
        if anchors > 0:
            exposure = _WarpedExposure(self, base, d_start, d_end, taus, anchors, fallback, frozen, rows,
                                       deferred=True, bend=bend)
        else:
            exposure = _RenderedExposure(self, base, d_start, d_end, taus, deferred=True, bend=bend)
        predicted, grad_predicted = self.blurred, self.grad_blur
        if colour is not None:  # the losses add into grad_compensated; the transform's backward writes grad_blur
            affine.forward(self.blurred, colour, self.compensated)
            predicted, grad_predicted = self.compensated, self.grad_compensated
        grad_predicted.fill(0.0)
        losses.l1_and_clipped_mse(predicted, self.frame, grad_predicted, weight=1.0 - lambda_dssim,
                                  mask=self.l1_pixels, into=values.at("l1", "mse"))
        losses.dssim(predicted, self.frame, grad_predicted, weight=lambda_dssim, mask=self.ssim_pixels,
                     into=values.at("dssim"))
        if colour is not None:
            affine.backward(self.blurred, colour, self.grad_compensated, self.grad_blur,
                            into=values.rows("colour", self.height, affine.N_GRAD_M))
        grad_depth = None
        if lambda_depth > 0:
            target, grad_depth = exposure.depth_buffers(depth)
            losses.masked_depth_l1(exposure.mid_view.depth, target, grad_depth, weight=lambda_depth,
                                   into=values.at("depth"))
        if frozen is None:
            self.gaussians.zero_grad()
        exposure.backward(self.grad_blur, grad_depth, values)
        return exposure

    def error_mass(self, frame: np.ndarray, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, k: int,
                   colour: np.ndarray | None = None) -> np.ndarray:
        """[ours] Each Gaussian's share of one frame's re-blur error: sum over pixels of its blending
        weight in each virtual view times the pixel's absolute error (summed over channels, over the
        sourced pixels), averaged over the k views."""
        views = _RenderedExposure(self, base, d_start, d_end, exposure_taus(k)).views
        predicted = self.blurred
        if colour is not None:
            affine.forward(self.blurred, colour, self.compensated)
            predicted = self.compensated
        error = np.abs(host_copy.read(predicted) - frame).sum(axis=2)
        if self.sourced is not None:
            error = error * self.sourced
        return np.maximum(self._blending_mass(views, error / k), 0.0)

    def blending_weights(self, poses: list[np.ndarray]) -> np.ndarray:
        """[ours] Each Gaussian's blending weight summed over the (sourced) pixels of sharp renders at
        ``poses``: how much of the images it makes (LightGaussian's global significance)."""
        pixels = np.ones((self.height, self.width)) if self.sourced is None else self.sourced
        # rendered one at a time, each just before its backward (the renders share one view buffer)
        renders = (self.rasterizer.forward(self.gaussians, self.camera(pose)) for pose in poses)
        return np.maximum(self._blending_mass(renders, pixels), 0.0)

    def _blending_mass(self, views: Iterable, pixel_weights: np.ndarray) -> np.ndarray:
        """Per Gaussian, the sum over ``views`` and pixels of its blending weight times ``pixel_weights``
        (H, W). Read from backward passes whose colour gradient is those weights, through the degree-0
        colour's gradient (d rgb / d dc = blending weight x SH_C0), summed on the device."""
        host_copy.write(self.grad_view, np.repeat(np.asarray(pixel_weights)[..., None], 3, axis=2))
        self.gaussians.zero_grad()
        self.step_values.clear()
        unread = self.step_values.rows("unread pose", 1, POSE_COLUMNS)  # every view's pose row, never read
        for view in views:
            self.rasterizer.backward(self.gaussians, view, d_rgb=self.grad_view, pose_into=unread)
        self.step_values.clear()
        mass = host_copy.read(self.gaussians.grads["colors"], self.count)[:, 0].sum(axis=1) / (3 * SH_C0)
        self.gaussians.zero_grad()
        return mass

    def depth_instant_step(self, depth: np.ndarray, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray,
                           shift: np.ndarray, weight: float, bend: np.ndarray | None = None
                           ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """[ours] ``weight`` times the masked depth L1 against ``depth`` of a depth-and-alpha render at the pose the
        frame's depth shows: its mid-exposure pose (with the exposure's ``bend``) moved by the twist ``shift``
        (``exposures.DepthMoments``), and its gradients with respect to the exposure's start and end offsets and its
        bend: (loss, dL/d d_start, dL/d d_end, dL/d bend). Its Gaussian gradients are added to theirs (a held-out
        fit leaves them unused)."""
        d_start, d_end = np.asarray(d_start) + shift, np.asarray(d_end) + shift  # their middle: the depth's pose
        camera = self.camera(virtual_pose(base, d_start, d_end, 0.5, bend))
        view = self.rasterizer.forward(self.gaussians, camera, view=DEPTH_INSTANT_VIEW, with_colour=False)
        host_copy.write(self.depth_target, depth)
        self.grad_depth.fill(0.0)
        values = self.step_values
        values.clear()
        losses.masked_depth_l1(view.depth, self.depth_target, self.grad_depth, weight=weight, into=values.at("depth"))
        pose = values.rows("pose", 1, POSE_COLUMNS)
        self.rasterizer.backward(self.gaussians, view, d_depth=self.grad_depth, pose_into=pose)  # a checked render
        read = values.read()
        g_start, g_end, g_bend = exposure_pose_gradients(base, d_start, d_end, [0.5], [read["pose"][0, :6]], bend)
        return weight * read["depth"], g_start, g_end, g_bend  # the kernel gives the unweighted mean

    def render(self, cam_to_world: np.ndarray, min_alpha: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """Sharp colour (H, W, 3) and depth (H, W) at one pose, as NumPy; the depth is the blended z
        divided by alpha (the expected depth of what the pixel sees), 0 where alpha < ``min_alpha``."""
        rgb, depth, alpha = self.rasterizer.forward(self.gaussians, self.camera(cam_to_world)).to_numpy()
        return rgb, np.where(alpha >= min_alpha, depth / np.maximum(alpha, min_alpha), 0.0).astype(np.float32)

    def coverage(self, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth, alpha) at one pose as NumPy: depth as :meth:`render` gives it, alpha the accumulated opacity."""
        _, depth, alpha = self.rasterizer.forward(self.gaussians, self.camera(cam_to_world), with_colour=False).to_numpy()
        return np.where(alpha >= 0.01, depth / np.maximum(alpha, 0.01), 0.0), alpha

    def add_gaussians(self, means: np.ndarray, rgb: np.ndarray, radius: np.ndarray, opacity: float) -> None:
        """Append isotropic Gaussians (centres (M, 3), colours (M, 3) in [0, 1], radii (M,) metres) with
        zero Adam moments and statistics; higher SH bands start at 0."""
        m = len(means)
        sh = np.zeros((m,) + self.gaussians.params["colors"].shape[1:], np.float32)
        sh[:, 0] = rgb_to_sh_dc(np.clip(rgb, 0.0, 1.0))
        self.store.append({
            "means": np.asarray(means, np.float32), "quats": np.tile(np.float32([1, 0, 0, 0]), (m, 1)),
            "log_scales": np.repeat(np.log(np.asarray(radius, np.float32))[:, None], 3, axis=1),
            "opacity_logits": np.full(m, logit(opacity), np.float32), "colors": sh})
        self.density.appended(m)

    def render_blurred(self, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, k: int,
                       readout_motion: np.ndarray | None = None, fallback_depth: float = 1.0,
                       bend: np.ndarray | None = None) -> np.ndarray:
        """The k-view average (H, W, 3) over an exposure (bowed by ``bend``, see :meth:`step`), as NumPy. [ours]
        With a rolling shutter (``readout_motion``, see :meth:`step`; the scene needs a ``warp_margin``) each view's
        rows are warped from a render at the view's pose (``fallback_depth`` where that render has no surface)."""
        taus = exposure_taus(k)
        rows = self.shutter_rows(readout_motion)
        if rows is not None and self.warp_margin < 1:
            raise ValueError("a rolling shutter's re-blurred render needs a scene with a warp_margin")
        if rows is None:
            _RenderedExposure(self, base, d_start, d_end, taus, bend=bend)
        else:
            _WarpedExposure(self, base, d_start, d_end, taus, k, fallback_depth, rows=rows, bend=bend)
        return host_copy.read(self.blurred).astype(np.float32)

    def order_in_space(self) -> None:
        """[ours] Put the Gaussians (with their moments and statistics) in Morton order of their centres."""
        order = morton_order(self.store.array("means"))
        self.store.reorder(order)
        self.density.reorder(order)

    def arrays(self) -> dict[str, np.ndarray]:
        """Parameters as NumPy, trimmed to the live Gaussians."""
        return self.store.arrays()

    def splats(self) -> Splats:
        a = self.arrays()
        return Splats(a["means"], a["quats"], a["log_scales"], a["opacity_logits"], a["colors"])

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume: parameters, Adam moments and step, densification statistics."""
        return {**self.store.state(), **self.density.state()}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.store.load_state(state)
        self.density.load_state(state)


def _as_arrays(splats: Splats) -> dict[str, np.ndarray]:
    return {"means": splats.means, "quats": splats.quats, "log_scales": splats.log_scales,
            "opacity_logits": splats.opacity_logits, "colors": splats.sh}


class _RenderedExposure:
    """The method's blur: all k virtual views of one exposure rendered, their mean in ``scene.blurred``."""

    def __init__(self, scene: BlurScene, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, taus: np.ndarray,
                 deferred: bool = False, bend: np.ndarray | None = None):
        self.scene, self.taus = scene, taus
        self.views = [scene.rasterizer.forward(scene.gaussians,
                                               scene.camera(virtual_pose(base, d_start, d_end, tau, bend)),
                                               view=j, deferred=deferred) for j, tau in enumerate(taus)]
        blur.average([v.rgb for v in self.views], scene.blurred)
        mid = int(np.argmin(np.abs(taus - 0.5)))
        self.mid_view, self.mid_tau = self.views[mid], float(taus[mid])

    def depth_buffers(self, depth: np.ndarray) -> tuple:
        """(target, zeroed gradient) device buffers of the mid view's depth loss, the target holding ``depth``."""
        host_copy.write(self.scene.depth_target, depth)
        self.scene.grad_depth.fill(0.0)
        return self.scene.depth_target, self.scene.grad_depth

    def backward(self, grad_blurred, grad_depth, values: StepValues) -> None:
        """Back-propagate dL/d mean view (and the mid view's depth gradient, or None) into the Gaussians'
        gradient buffers; the k views' pose rows wait in ``values`` (:meth:`pose_gradients`)."""
        scene = self.scene
        blur.spread(grad_blurred, len(self.taus), scene.grad_view)
        rows = values.rows("render poses", len(self.views), POSE_COLUMNS)
        for j, v in enumerate(self.views):
            scene.rasterizer.backward(scene.gaussians, v, d_rgb=scene.grad_view,
                                      d_depth=grad_depth if v is self.mid_view else None, pose_into=rows.row(j))

    def pose_gradients(self, values: dict) -> tuple[np.ndarray, list[np.ndarray]] | None:
        """(exposure fractions, world left-perturbation pose gradients) from the step's values read; None when a
        deferred render overflowed (see ``Rasterizer.pose_gradients``)."""
        poses = self.scene.rasterizer.pose_gradients(values["render poses"])
        return None if poses is None else (self.taus, list(poses))


class _WarpedExposure:
    """[ours] One exposure's k virtual views warped from a few padded anchor renders, their mean in
    ``scene.blurred``; the same interface as :class:`_RenderedExposure`. With ``rows`` (:func:`shutter_rows`)
    each view's image rows are warped from its poses along a rolling shutter's readout; a left perturbation of
    a view moves all its rows alike, so the pose gradients chain as for a global shutter."""

    def __init__(self, scene: BlurScene, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, taus: np.ndarray,
                 anchors: int, fallback_depth: float, frozen: FrozenAnchors | None = None,
                 rows: np.ndarray | None = None, deferred: bool = False, bend: np.ndarray | None = None):
        self.scene, self.taus, self.frozen = scene, taus, frozen
        self.groups = anchor_groups(len(taus), anchors)
        self.anchor_taus = np.array([float(np.mean(taus[g])) for g in self.groups])
        poses = [virtual_pose(base, d_start, d_end, tau, bend) for tau in taus]
        wanted = [virtual_pose(base, d_start, d_end, tau, bend) for tau in self.anchor_taus]
        if frozen is None:
            rast, gs = scene.rasterizer, scene.gaussians
            self.anchor_poses = wanted
            self.anchor_views = [rast.forward(gs, scene.padded_camera(pose), view=ANCHOR_VIEWS + a, deferred=deferred)
                                 for a, pose in enumerate(wanted)]
        else:
            self.anchor_views, self.anchor_poses = frozen.anchors(scene, wanted)
        self.relative = [np.stack([invert(self.anchor_poses[a]) @ poses[i] for i in group])
                         for a, group in enumerate(self.groups)]
        if rows is not None:  # rolling shutter: (views, H, 4, 4), row v of view i read at poses[i] @ rows[v]
            self.relative = [relative[:, None] @ rows[None] for relative in self.relative]
        mid = len(self.groups) // 2  # the middle run's anchor, at tau = 1/2 (anchor_groups)
        self.mid_view, self.mid_tau = self.anchor_views[mid], float(self.anchor_taus[mid])
        self.depths = scene.warp_buffers(len(self.groups), max(len(g) for g in self.groups))
        for a, anchor in enumerate(self.anchor_views):
            warp.accumulate(anchor.rgb, anchor.depth, anchor.transmittance, self.relative[a], scene.K,
                            scene.warp_margin, fallback_depth, 1.0 / len(taus), scene.blurred, self.depths[a],
                            first=a == 0)

    def depth_buffers(self, depth: np.ndarray) -> tuple:
        """(target, zeroed gradient) of the mid anchor's depth loss: ``depth`` padded with invalid (0) pixels."""
        scene = self.scene
        host_copy.write(scene.padded_depth_target, np.pad(np.asarray(depth, np.float32), scene.warp_margin))
        scene.padded_grad_depth.fill(0.0)
        return scene.padded_depth_target, scene.padded_grad_depth

    def backward(self, grad_blurred, grad_depth, values: StepValues) -> None:
        """As :meth:`_RenderedExposure.backward`: each anchor's warp leaves its per-row pose gradients in
        ``values``, and its render (unless frozen) its pose row."""
        scene = self.scene
        rendered = None if self.frozen is not None else values.rows("render poses", len(self.anchor_views),
                                                                     POSE_COLUMNS)
        for a, view in enumerate(self.anchor_views):  # the groups are consecutive runs of the k views, in order
            grad_anchor = scene.anchor_gradient() if self.frozen is None else None
            warp.backward(grad_blurred, view.rgb, self.depths[a], self.relative[a], scene.K, scene.warp_margin,
                          1.0 / len(self.taus), grad_anchor,
                          into=values.rows(f"warp {a}", warp.pose_rows(scene.height, len(self.groups[a])),
                                           warp.N_POSE))
            if rendered is not None:
                scene.rasterizer.backward(scene.gaussians, view, d_rgb=grad_anchor,
                                          d_depth=grad_depth if view is self.mid_view else None,
                                          pose_into=rendered.row(a))

    def pose_gradients(self, values: dict) -> tuple[list[float], list[np.ndarray]] | None:
        """As :meth:`_RenderedExposure.pose_gradients`; the gradients come for the k views (through their warps)
        and for the anchors (through the warps and their renders). Frozen anchors are fixed renders, not
        functions of the exposure: the gradients come for the k views alone, and none reach the Gaussians."""
        view_grads, anchor_grads = [], []
        for a, group in enumerate(self.groups):
            g_relative = warp.pose_sums(values[f"warp {a}"], len(group))
            g_views, g_anchor = relative_pose_gradients(self.anchor_poses[a], g_relative)
            view_grads.extend(g_views)
            anchor_grads.append(g_anchor)
        if self.frozen is not None:
            return self.taus, view_grads
        rendered = self.scene.rasterizer.pose_gradients(values["render poses"])
        if rendered is None:  # a deferred anchor render overflowed
            return None
        return [*self.taus, *self.anchor_taus], [*view_grads, *(np.asarray(anchor_grads) + rendered)]
