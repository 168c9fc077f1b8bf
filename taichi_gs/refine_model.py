"""Stage 2's trainable scene: fixed-scale isotropic Gaussians whose positions and opacities learn
from depth, kept on the device between iterations (NumPy in and out only at the edges)."""

from __future__ import annotations

import numpy as np

from .geometry import raster_intrinsics
from .kernels import losses
from .kernels.optim import Adam
from .kernels.splat import Camera, DeviceGaussians, Rasterizer, to_device
from .splats import logit

TRAINED = ("means", "opacity_logits")


class DepthRefiner:
    """Isotropic Gaussians of one fixed scale; one :meth:`step` renders depth at a camera, takes
    the masked depth L1 and opacity-binarisation losses, back-propagates to positions, opacities
    and the camera pose, and applies Adam to positions and opacities.

    ``K`` is in the data's OpenCV convention; the rasterizer's half-pixel shift is applied here.
    """

    def __init__(self, means: np.ndarray, opacity_logits: np.ndarray, scale: float, K: np.ndarray, width: int, height: int):
        n = len(means)
        self.log_scale = float(np.log(scale))
        self.K = raster_intrinsics(K)
        self.width, self.height = width, height
        self.rasterizer = Rasterizer()
        self.kept = np.arange(n)
        self._build(np.asarray(means, np.float32), np.asarray(opacity_logits, np.float32), moments=None, t=0)
        self.target = to_device(np.zeros((height, width), np.float32), self.gaussians.dtype)
        self.grad_depth = to_device(np.zeros((height, width), np.float32), self.gaussians.dtype)

    def _build(self, means: np.ndarray, logits: np.ndarray, moments: dict | None, t: int) -> None:
        n = len(means)
        self.gaussians = DeviceGaussians.from_numpy(
            means, None, np.full(n, self.log_scale, np.float32), logits, np.zeros((n, 1, 3), np.float32), isotropic=True,
        )
        self.adam = Adam(self.gaussians.params, self.gaussians.grads, {name: 0.0 for name in TRAINED})
        self.adam.t = t
        if moments:
            for name, (m, v) in moments.items():
                self.adam.moments[name][0].from_numpy(np.ascontiguousarray(m))
                self.adam.moments[name][1].from_numpy(np.ascontiguousarray(v))

    @property
    def count(self) -> int:
        return self.gaussians.n

    def step(self, target_depth: np.ndarray, cam_to_world: np.ndarray, lambda_depth: float, lambda_opacity: float,
             lr_means: float, lr_opacity: float) -> tuple[dict[str, float], np.ndarray]:
        """One iteration at one camera; returns the loss values and dL/d(pose) (6,)."""
        n = self.gaussians.n
        view = self.rasterizer.forward(self.gaussians, Camera(self.K, cam_to_world, self.width, self.height))
        self.gaussians.zero_grad()
        self.grad_depth.fill(0.0)
        self.target.from_numpy(np.ascontiguousarray(target_depth, dtype=np.float32))
        depth_l1 = losses.masked_depth_l1(view.depth, self.target, self.grad_depth, weight=lambda_depth)
        # The method sums both losses; the depth term here is a mean over pixels, so the opacity
        # weight is divided by the pixel count to keep the method's balance between the two sums.
        opacity = losses.opacity_binarization(
            self.gaussians.params["opacity_logits"], self.gaussians.grads["opacity_logits"], n,
            weight=lambda_opacity / (self.width * self.height),
        )
        pose_grad = self.rasterizer.backward(self.gaussians, view, d_depth=self.grad_depth)
        self.adam.lrs.update(means=lr_means, opacity_logits=lr_opacity)
        self.adam.step(n)
        return {"depth": depth_l1, "opacity": opacity / max(n, 1)}, pose_grad

    def render_depth(self, cam_to_world: np.ndarray) -> np.ndarray:
        """Depth (H, W) rendered at a camera, as NumPy."""
        view = self.rasterizer.forward(self.gaussians, Camera(self.K, cam_to_world, self.width, self.height))
        return view.depth.to_numpy().astype(np.float32)

    def means(self) -> np.ndarray:
        return self.gaussians.params["means"].to_numpy()[: self.count]

    def opacity_logits(self) -> np.ndarray:
        return self.gaussians.params["opacity_logits"].to_numpy()[: self.count]

    def kept_indices(self) -> np.ndarray:
        """Indices, into the initial Gaussians, of those still alive."""
        return self.kept.copy()

    def _moments(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        return {name: (m.to_numpy()[: self.count], v.to_numpy()[: self.count]) for name, (m, v) in self.adam.moments.items()}

    def prune(self, min_opacity: float) -> int:
        """Drop Gaussians with opacity below ``min_opacity`` (keeping their survivors' Adam state)."""
        keep = self.opacity_logits() >= logit(min_opacity)
        if keep.all() or not keep.any():
            return 0
        moments = {name: (m[keep], v[keep]) for name, (m, v) in self._moments().items()}
        self.kept = self.kept[keep]
        self._build(self.means()[keep], self.opacity_logits()[keep], moments, self.adam.t)
        return int((~keep).sum())

    def reset_opacity(self, opacity: float) -> None:
        """Set every opacity to ``opacity`` and forget its Adam moments (as 3DGS's reset does)."""
        self.gaussians.upload(opacity_logits=np.full(self.count, logit(opacity), np.float32))
        for moment in self.adam.moments["opacity_logits"]:
            moment.fill(0.0)

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume: parameters, kept indices, Adam moments and step."""
        out = {"means": self.means(), "opacity_logits": self.opacity_logits(), "kept": self.kept, "adam_t": np.array(self.adam.t)}
        for name, (m, v) in self._moments().items():
            out[f"m_{name}"], out[f"v_{name}"] = m, v
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.kept = np.asarray(state["kept"])
        moments = {name: (state[f"m_{name}"], state[f"v_{name}"]) for name in TRAINED}
        self._build(state["means"], state["opacity_logits"], moments, int(state["adam_t"]))
