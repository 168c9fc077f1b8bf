"""Stage 2's trainable scene: Gaussians of one initial scale whose positions and opacities (and,
for the ablation, scales and rotations) learn from depth, kept on the device between iterations
(NumPy in and out only at the edges)."""

from __future__ import annotations

import numpy as np

from ... import profiling
from ...gaussian_store import GaussianStore, OnStore, morton_order
from ...geometry import raster_intrinsics
from ...render import POSE_COLUMNS, Camera, Rasterizer, Slot, StepValues, host_copy, losses, to_device
from ...splats import logit

FIXED_SCALE = ("means", "opacity_logits")
FREE_SCALE = FIXED_SCALE + ("log_scales", "quats")


class DepthRefiner(OnStore):
    """Gaussians initialised isotropic with one scale. One :meth:`step` renders depth at one or
    more cameras, takes the alpha-normalised masked depth L1 and coverage losses (averaged over the
    cameras) and the opacity-binarisation loss, back-propagates to the Gaussians and the camera poses, and applies
    Adam to the Gaussians. ``free_scale`` also trains anisotropic scales and rotations (ablation).

    ``K`` is in the data's OpenCV convention; the rasterizer's half-pixel shift is applied here.
    ``spatial_order`` ([ours]) keeps the Gaussians in Morton order of their initial centres (pruning keeps
    the order): the same renders, read with fewer cache misses; :meth:`kept_indices` maps back.
    """

    def __init__(self, means: np.ndarray, opacity_logits: np.ndarray, scale: float, K: np.ndarray, width: int,
                 height: int, free_scale: bool = False, min_alpha: float = 0.5, spatial_order: bool = False):
        n = len(means)
        self.kept = morton_order(means) if spatial_order else np.arange(n)
        means, opacity_logits = np.asarray(means)[self.kept], np.asarray(opacity_logits)[self.kept]
        self.free_scale = free_scale
        self.trained = FREE_SCALE if free_scale else FIXED_SCALE
        self.log_scale = float(np.log(scale))
        self.min_alpha = min_alpha
        self.K = raster_intrinsics(K)
        self.width, self.height = width, height
        self.rasterizer = Rasterizer()
        arrays = {"means": np.asarray(means, np.float32), "opacity_logits": np.asarray(opacity_logits, np.float32),
                  "log_scales": np.full((n, 3 if free_scale else 1), self.log_scale, np.float32),
                  "colors": np.zeros((n, 1, 3), np.float32)}
        if free_scale:
            arrays["quats"] = np.tile(np.array([1, 0, 0, 0], np.float32), (n, 1))
        self.store = GaussianStore(arrays, self.trained, isotropic=not free_scale)
        self.target_depth = to_device(np.zeros((height, width), np.float32), self.gaussians.dtype)
        self.grad_depth = to_device(np.zeros((height, width), np.float32), self.gaussians.dtype)
        self.grad_alpha = to_device(np.zeros((height, width), np.float32), self.gaussians.dtype)
        self.step_values = StepValues(self.gaussians.dtype)  # a step's loss values and pose rows, read once

    def _depth_backward(self, target_depth: np.ndarray, cam_to_world: np.ndarray, weight: float,
                        coverage_weight: float, row: int, pose_into: Slot) -> None:
        """Render one camera (deferred), add its weighted loss gradients to the Gaussians, leave dL/dpose at
        ``pose_into`` and the depth and coverage terms in :attr:`step_values` (named by ``row``)."""
        view = self.rasterizer.forward(self.gaussians, Camera(self.K, cam_to_world, self.width, self.height),
                                       with_colour=False, deferred=True)
        host_copy.write(self.target_depth, target_depth)
        self.grad_depth.fill(0.0)
        self.grad_alpha.fill(0.0)
        losses.normalised_depth_l1_and_coverage(
            view.depth, view.transmittance, self.target_depth, self.grad_depth, self.grad_alpha, self.min_alpha,
            weight, coverage_weight, into=self.step_values.at(f"depth {row}", f"coverage {row}"))
        self.rasterizer.backward(self.gaussians, view, d_depth=self.grad_depth, d_alpha=self.grad_alpha,
                                 pose_into=pose_into)

    @profiling.timed("step host work (uploads, fills)")
    def step(self, target_depths: list[np.ndarray], cam_to_worlds: list[np.ndarray], lambda_depth: float,
             lambda_coverage: float, lambda_opacity: float,
             lrs: dict[str, float]) -> tuple[dict[str, float], list[np.ndarray]]:
        """One iteration over one or more cameras; returns the loss values and dL/d(pose) (6,) per camera.

        ``lrs`` maps each trained parameter name to its learning rate (missing names: 0)."""
        n = self.gaussians.n
        views = len(cam_to_worlds)
        while True:  # again when a render's tile slots overflowed its buffers (they are grown: it fits the next time)
            self.gaussians.zero_grad()
            self.step_values.clear()
            poses = self.step_values.rows("poses", views, POSE_COLUMNS)
            for row, (d, T) in enumerate(zip(target_depths, cam_to_worlds)):
                self._depth_backward(d, T, lambda_depth / views, lambda_coverage / views, row, poses.row(row))
            # The method sums both losses; the depth term here is a mean over pixels, so the opacity
            # weight is divided by the pixel count to keep the method's balance between the two sums.
            losses.opacity_binarization(
                self.gaussians.params["opacity_logits"], self.gaussians.grads["opacity_logits"], n,
                weight=lambda_opacity / (self.width * self.height), into=self.step_values.at("opacity"),
            )
            values = self.step_values.read()  # the step's one host read
            pose_grads = self.rasterizer.pose_gradients(values["poses"])
            if pose_grads is not None:
                break
        self.store.step(lrs)
        depth, coverage = (float(np.mean([values[f"{term} {row}"] for row in range(views)]))
                           for term in ("depth", "coverage"))
        return {"depth": depth, "coverage": coverage, "opacity": values["opacity"] / max(n, 1)}, list(pose_grads)

    def params(self) -> dict[str, np.ndarray]:
        """The trained parameters of the live Gaussians as NumPy."""
        return {name: self.store.array(name) for name in self.trained}

    def means(self) -> np.ndarray:
        return self.store.array("means")

    def opacity_logits(self) -> np.ndarray:
        return self.store.array("opacity_logits")

    def log_scales(self) -> np.ndarray:
        """(N, 3) log scales (all equal to the initial one unless ``free_scale``)."""
        if self.free_scale:
            return self.store.array("log_scales")
        return np.full((self.count, 3), self.log_scale, np.float32)

    def quats(self) -> np.ndarray | None:
        """(N, 4) rotations when ``free_scale``, else None (isotropic)."""
        return self.store.array("quats") if self.free_scale else None

    def kept_indices(self) -> np.ndarray:
        """Indices, into the initial Gaussians, of those still alive."""
        return self.kept.copy()

    @profiling.timed("densify / prune / fill")
    def prune(self, min_opacity: float) -> int:
        """Drop Gaussians with opacity below ``min_opacity`` (their survivors keep their Adam state)."""
        keep = self.opacity_logits() >= logit(min_opacity)
        if keep.all() or not keep.any():
            return 0
        self.store.keep(keep)
        self.kept = self.kept[keep]
        return int((~keep).sum())

    @profiling.timed("densify / prune / fill")
    def reset_opacity(self, opacity: float) -> None:
        """Set every opacity to ``opacity`` and forget its Adam moments (as 3DGS's reset does)."""
        self.store.reset("opacity_logits", np.full(self.count, logit(opacity), np.float32))

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume: parameters, kept indices, Adam moments and step."""
        return {**self.store.state(), "kept": self.kept}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self.kept = np.asarray(state["kept"])
        self.store.load_state(state)
