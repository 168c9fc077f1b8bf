"""Stage 3's trainable scene: full 3D Gaussians (SH colour, opacity, anisotropic scale, rotation,
position) kept on the device, trained against blurred frames through the k-view blur model, with
3DGS-style densification (clone small / split large Gaussians with large positional gradients)
and pruning. Exposure poses live on the host (12 numbers per frame) in :mod:`stages.deblur`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .geometry import quat_to_rotmat, raster_intrinsics
from .photometric import affine_backward, apply_affine
from .render import Adam, Camera, DeviceGaussians, Rasterizer, blur, exposure_pose_gradients, losses, to_device, virtual_pose
from .splats import Splats, logit, rgb_to_sh_dc

TRAINED = ("means", "quats", "log_scales", "opacity_logits", "colors")


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


def exposure_taus(k: int) -> np.ndarray:
    """Exposure fractions of the k virtual views: linspace(0, 1, k), or the middle alone for k = 1."""
    return np.linspace(0.0, 1.0, k) if k > 1 else np.array([0.5])


class BlurScene:
    """Gaussians rendered at one resolution (``K`` in OpenCV convention; the rasterizer's half-pixel
    shift is applied here). :meth:`step` takes one blurred frame's k-view loss and updates the
    Gaussians; :meth:`densify_and_prune` grows and trims them."""

    def __init__(self, splats: Splats, K: np.ndarray, width: int, height: int):
        self.K = raster_intrinsics(K)
        self.width, self.height = width, height
        self.rasterizer = Rasterizer()
        self._build(_as_arrays(splats), moments=None, t=0)
        dtype = self.gaussians.dtype
        self.frame = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.depth_target = to_device(np.zeros((height, width), np.float32), dtype)
        self.blurred = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.compensated = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_compensated = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_blur = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_view = to_device(np.zeros((height, width, 3), np.float32), dtype)
        self.grad_depth = to_device(np.zeros((height, width), np.float32), dtype)
        self.grad_sum = np.zeros(self.count)
        self.grad_count = np.zeros(self.count)

    def _build(self, arrays: dict[str, np.ndarray], moments: dict | None, t: int) -> None:
        self.gaussians = DeviceGaussians.from_numpy(arrays["means"], arrays["quats"], arrays["log_scales"],
                                                    arrays["opacity_logits"], arrays["colors"])
        self.adam = Adam(self.gaussians.params, self.gaussians.grads, {name: 0.0 for name in TRAINED})
        self.adam.t = t
        for name, (m, v) in (moments or {}).items():
            self.adam.moments[name][0].from_numpy(np.ascontiguousarray(m, np.float32))
            self.adam.moments[name][1].from_numpy(np.ascontiguousarray(v, np.float32))

    @property
    def count(self) -> int:
        return self.gaussians.n

    def camera(self, cam_to_world: np.ndarray) -> Camera:
        return Camera(self.K, cam_to_world, self.width, self.height)

    def _render_exposure(self, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, taus: np.ndarray) -> list:
        views = [self.rasterizer.forward(self.gaussians, self.camera(virtual_pose(base, d_start, d_end, tau)), view=j)
                 for j, tau in enumerate(taus)]
        blur.average([v.rgb for v in views], self.blurred)
        return views

    def step(self, frame: np.ndarray, depth: np.ndarray, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray,
             k: int, lambda_dssim: float, lambda_depth: float, rates: Rates | None,
             colour: np.ndarray | None = None) -> BlurStep:
        """Render the frame's k virtual views, average them, apply the frame's affine ``colour``
        transform (3 x 4; None: identity), take (1 - l_B) L1 + l_B D-SSIM against ``frame`` plus
        ``lambda_depth`` times the masked depth L1 of the mid view against ``depth``, back-propagate,
        and (unless ``rates`` is None: scene frozen) apply Adam to the Gaussians."""
        taus = exposure_taus(k)
        mid = int(np.argmin(np.abs(taus - 0.5)))
        self.frame.from_numpy(np.ascontiguousarray(frame, np.float32))
        views = self._render_exposure(base, d_start, d_end, taus)
        self.grad_blur.fill(0.0)
        self.grad_depth.fill(0.0)
        predicted, grad_predicted = self.blurred, self.grad_blur
        if colour is not None:
            blurred = self.blurred.to_numpy()
            self.compensated.from_numpy(np.ascontiguousarray(apply_affine(blurred, colour), np.float32))
            self.grad_compensated.fill(0.0)
            predicted, grad_predicted = self.compensated, self.grad_compensated
        l1 = losses.l1(predicted, self.frame, grad_predicted, weight=1.0 - lambda_dssim)
        dssim = losses.dssim(predicted, self.frame, grad_predicted, weight=lambda_dssim)
        grad_colour = None
        if colour is not None:
            grad_image, grad_colour = affine_backward(blurred, colour, self.grad_compensated.to_numpy())
            self.grad_blur.from_numpy(np.ascontiguousarray(grad_image, np.float32))
        depth_l1 = 0.0
        if lambda_depth > 0:
            self.depth_target.from_numpy(np.ascontiguousarray(depth, np.float32))
            depth_l1 = losses.masked_depth_l1(views[mid].depth, self.depth_target, self.grad_depth, weight=lambda_depth)
        blur.spread(self.grad_blur, k, self.grad_view)
        self.gaussians.zero_grad()
        pose_grads = [self.rasterizer.backward(self.gaussians, v, d_rgb=self.grad_view,
                                               d_depth=self.grad_depth if j == mid and lambda_depth > 0 else None)
                      for j, v in enumerate(views)]
        g_start, g_end = exposure_pose_gradients(base, d_start, d_end, taus, pose_grads)
        if rates is not None:
            self._accumulate_densify_stats(virtual_pose(base, d_start, d_end, taus[mid]))
            self.adam.lrs.update(vars(rates))
            self.adam.step(self.count)
        mse = float(np.mean((np.clip(predicted.to_numpy(), 0, 1) - frame) ** 2))
        return BlurStep({"l1": l1, "dssim": dssim, "depth": depth_l1}, float(-10 * np.log10(max(mse, 1e-12))),
                        g_start, g_end, grad_colour)

    def _accumulate_densify_stats(self, cam_to_world: np.ndarray) -> None:
        """Add each Gaussian's positional gradient, converted to image-plane pixels (|g| z / f)."""
        grad = np.linalg.norm(self.gaussians.grads["means"].to_numpy()[: self.count], axis=1)
        means = self.gaussians.params["means"].to_numpy()[: self.count]
        z = np.abs((means - cam_to_world[:3, 3]) @ cam_to_world[:3, 2])
        seen = grad > 0
        self.grad_sum[seen] += grad[seen] * z[seen] / self.K[0, 0]
        self.grad_count[seen] += 1

    def render(self, cam_to_world: np.ndarray, min_alpha: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
        """Sharp colour (H, W, 3) and depth (H, W) at one pose, as NumPy; the depth is the blended z
        divided by alpha (the expected depth of what the pixel sees), 0 where alpha < ``min_alpha``."""
        rgb, depth, alpha = self.rasterizer.forward(self.gaussians, self.camera(cam_to_world)).to_numpy()
        return rgb, np.where(alpha >= min_alpha, depth / np.maximum(alpha, min_alpha), 0.0).astype(np.float32)

    def coverage(self, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(depth, alpha) at one pose as NumPy: depth as :meth:`render` gives it, alpha the accumulated opacity."""
        _, depth, alpha = self.rasterizer.forward(self.gaussians, self.camera(cam_to_world)).to_numpy()
        return np.where(alpha >= 0.01, depth / np.maximum(alpha, 0.01), 0.0), alpha

    def add_gaussians(self, means: np.ndarray, rgb: np.ndarray, radius: np.ndarray, opacity: float) -> None:
        """Append isotropic Gaussians (centres (M, 3), colours (M, 3) in [0, 1], radii (M,) metres) with
        zero Adam moments; higher SH bands start at 0."""
        a, moments = self.arrays(), self._moments()
        m = len(means)
        sh = np.zeros((m,) + a["colors"].shape[1:], np.float32)
        sh[:, 0] = rgb_to_sh_dc(np.clip(rgb, 0.0, 1.0))
        new = {"means": np.asarray(means, np.float32), "quats": np.tile(np.float32([1, 0, 0, 0]), (m, 1)),
               "log_scales": np.repeat(np.log(np.asarray(radius, np.float32))[:, None], 3, axis=1),
               "opacity_logits": np.full(m, logit(opacity), np.float32), "colors": sh}
        merged = {name: np.concatenate([a[name], new[name].astype(a[name].dtype)]) for name in TRAINED}
        moments = {name: tuple(np.concatenate([mv, np.zeros_like(new[name], dtype=mv.dtype)]) for mv in moments[name])
                   for name in TRAINED}
        self._build(merged, moments, self.adam.t)
        self.grad_sum = np.concatenate([self.grad_sum, np.zeros(m)])
        self.grad_count = np.concatenate([self.grad_count, np.zeros(m)])

    def render_blurred(self, base: np.ndarray, d_start: np.ndarray, d_end: np.ndarray, k: int) -> np.ndarray:
        """The k-view average (H, W, 3) over an exposure, as NumPy."""
        self._render_exposure(base, d_start, d_end, exposure_taus(k))
        return self.blurred.to_numpy().astype(np.float32)

    def arrays(self) -> dict[str, np.ndarray]:
        """Parameters as NumPy, trimmed to the live Gaussians."""
        return self.gaussians.download()

    def splats(self) -> Splats:
        a = self.arrays()
        return Splats(a["means"], a["quats"], a["log_scales"], a["opacity_logits"], a["colors"])

    def _moments(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {name: (m.to_numpy()[: self.count], v.to_numpy()[: self.count]) for name, (m, v) in self.adam.moments.items()}

    def densify_and_prune(self, grad_threshold_px: float, split_scale: float | np.ndarray, min_opacity: float,
                          max_scale: float, max_gaussians: int, rng: np.random.Generator) -> tuple[int, int]:
        """3DGS's adaptive density control: Gaussians whose mean image-plane positional gradient
        exceeds ``grad_threshold_px`` are cloned (largest scale <= ``split_scale``, metres; one value
        or one per Gaussian) or split in two samples of themselves with scales / 1.6; then those with
        opacity < ``min_opacity`` or a scale > ``max_scale`` are dropped. Never grows past
        ``max_gaussians``. Returns (added, removed)."""
        a, moments = self.arrays(), self._moments()
        mean_grad = self.grad_sum / np.maximum(self.grad_count, 1)
        grow = np.flatnonzero(mean_grad > grad_threshold_px)
        room = max(max_gaussians - self.count, 0)
        if len(grow) > room:
            grow = grow[np.argsort(-mean_grad[grow])[:room]]
        limit = np.broadcast_to(np.asarray(split_scale, np.float64), (self.count,))[grow]
        big = a["log_scales"][grow].max(axis=1) > np.log(limit)
        split, clone = grow[big], grow[~big]
        new = {name: np.concatenate([a[name][clone], a[name][split]]) for name in TRAINED}
        _split_in_two(a, new, split, len(clone), rng)
        merged = {name: np.concatenate([a[name], new[name]]) for name in TRAINED}
        keep = (merged["opacity_logits"] >= logit(min_opacity)) & (merged["log_scales"].max(axis=1) <= np.log(max_scale))
        added = len(grow)
        zeros = {name: np.zeros_like(new[name]) for name in TRAINED}
        moments = {name: tuple(np.concatenate([mv, zeros[name]])[keep] for mv in moments[name]) for name in TRAINED}
        self._build({name: merged[name][keep] for name in TRAINED}, moments, self.adam.t)
        self.grad_sum = np.zeros(self.count)
        self.grad_count = np.zeros(self.count)
        return added, int((~keep).sum())

    def split_oversized(self, max_scale: np.ndarray, max_gaussians: int, rng: np.random.Generator) -> int:
        """Split (3DGS's split: two samples, scales / 1.6) every Gaussian whose largest scale exceeds
        its ``max_scale`` (metres, one per Gaussian), repeatedly until none does or ``max_gaussians``
        is reached (the largest relative to their limit first). Adam moments of the children start
        at 0. Returns how many Gaussians were added."""
        added = 0
        limit = np.asarray(max_scale, np.float64)
        while True:
            a, moments = self.arrays(), self._moments()
            excess = a["log_scales"].max(axis=1) - np.log(limit)
            split = np.flatnonzero(excess > 0)
            split = split[np.argsort(-excess[split])[: max(max_gaussians - self.count, 0)]]
            if len(split) == 0:
                return added
            new = {name: a[name][split].copy() for name in TRAINED}
            _split_in_two(a, new, split, 0, rng)
            merged = {name: np.concatenate([a[name], new[name]]) for name in TRAINED}
            moments = {name: tuple(np.concatenate([mv, np.zeros_like(new[name], dtype=mv.dtype)]) for mv in moments[name])
                       for name in TRAINED}
            self._build(merged, moments, self.adam.t)
            limit = np.concatenate([limit, limit[split]])
            added += len(split)
            self.grad_sum = np.zeros(self.count)
            self.grad_count = np.zeros(self.count)

    def reset_opacity(self, opacity: float) -> None:
        """Clamp every opacity to at most ``opacity`` and forget its Adam moments (3DGS's reset)."""
        logits = np.minimum(self.arrays()["opacity_logits"], logit(opacity))
        self.gaussians.upload(opacity_logits=logits.astype(np.float32))
        for moment in self.adam.moments["opacity_logits"]:
            moment.fill(0.0)

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume: parameters, Adam moments and step, densification statistics."""
        out = {f"p_{name}": value for name, value in self.arrays().items()}
        for name, (m, v) in self._moments().items():
            out[f"m_{name}"], out[f"v_{name}"] = m, v
        out.update(adam_t=np.array(self.adam.t), grad_sum=self.grad_sum, grad_count=self.grad_count)
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        moments = {name: (state[f"m_{name}"], state[f"v_{name}"]) for name in TRAINED}
        self._build({name: state[f"p_{name}"] for name in TRAINED}, moments, int(state["adam_t"]))
        self.grad_sum, self.grad_count = state["grad_sum"].copy(), state["grad_count"].copy()


def _split_in_two(a: dict[str, np.ndarray], new: dict[str, np.ndarray], split: np.ndarray, first: int,
                  rng: np.random.Generator) -> None:
    """3DGS's split, in place: Gaussian ``split[j]`` of ``a`` and its copy at row ``first + j`` of ``new``
    move apart by +-one sample of the Gaussian (rotated, scaled noise) and shrink by 1.6."""
    if len(split) == 0:
        return
    scales = np.exp(a["log_scales"][split])
    offsets = np.einsum("nij,nj->ni", quat_to_rotmat(a["quats"][split]), rng.normal(size=scales.shape) * scales)
    rows = slice(first, first + len(split))
    new["means"][rows] += offsets
    a["means"][split] -= offsets
    new["log_scales"][rows] -= np.log(1.6)
    a["log_scales"][split] -= np.log(1.6)


def footprint_limit(means: np.ndarray, centres: np.ndarray, focal: float, pixels: float) -> np.ndarray:
    """Per Gaussian, the world size (metres) that ``pixels`` pixels span at its distance from the
    nearest camera centre (``centres`` (N, 3), ``focal`` in pixels)."""
    nearest = np.full(len(means), np.inf)
    for c in np.asarray(centres, np.float64):
        nearest = np.minimum(nearest, np.linalg.norm(np.asarray(means, np.float64) - c, axis=1))
    return pixels * np.maximum(nearest, 1e-6) / focal


def _as_arrays(splats: Splats) -> dict[str, np.ndarray]:
    return {"means": splats.means, "quats": splats.quats, "log_scales": splats.log_scales,
            "opacity_logits": splats.opacity_logits, "colors": splats.sh}
