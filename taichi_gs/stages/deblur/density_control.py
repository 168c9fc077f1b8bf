"""3DGS's adaptive density control as a policy over a :class:`GaussianStore`.

The policy keeps per-Gaussian positional-gradient statistics (``observe``), and its operations
(clone, split, prune, opacity reset) go through the store, which carries the Adam moments along
with the parameters. Stage 3 drives it with :meth:`DensityControl.step` on 3DGS's schedule.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ... import profiling
from ...gaussian_store import GaussianStore
from ...geometry import quat_to_rotmat
from ...render import density_stats
from ...splats import logit

SPLIT_SHRINK = 1.6  # a split Gaussian's two halves are this much smaller (3DGS)
RESET_OPACITY = 0.01  # 3DGS's opacity reset value


@dataclass(frozen=True)
class DensitySchedule:
    """When and how to densify: iterations, thresholds (image-plane pixels), sizes (metres)."""

    densify_from: int
    densify_until: int
    densify_every: int
    grad_threshold_px: float  # mean image-plane positional gradient above which a Gaussian grows
    split_scale: float  # clone below, split above this largest scale
    prune_opacity: float
    prune_scale: float  # drop Gaussians whose largest scale exceeds this
    max_gaussians: int
    reset_opacity_every: int = 0  # 0 = never
    # [ours] also split (not clone) Gaussians wider than split_px pixels seen from the nearest of the
    # camera centres, at focal length focal (0 = off: the world-size rule split_scale alone)
    split_px: float = 0.0
    centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)), compare=False)
    focal: float = 0.0

    def densifies(self, done: int) -> bool:
        """True when ``done`` iterations end a densification interval inside the window."""
        return self.densify_from <= done <= self.densify_until and done % self.densify_every == 0

    def last_densification(self, done: int) -> bool:
        """True when ``done`` iterations end the window's last densification interval."""
        return self.densifies(done) and done + self.densify_every > self.densify_until

    def observes(self, done: int) -> bool:
        """True while the statistics of the step that ends at ``done`` iterations can still feed a
        densification (after the window nobody reads them)."""
        return done <= self.densify_until

    def split_limit(self, means: np.ndarray) -> float | np.ndarray:
        """The largest scale each Gaussian may keep and be cloned rather than split (metres)."""
        if self.split_px <= 0:
            return self.split_scale
        return np.minimum(self.split_scale, footprint_limit(means, self.centres, self.focal, self.split_px))


class DensityControl:
    """Positional-gradient statistics of a store's Gaussians and the operations they drive.

    The statistics accumulate on the device (``observe``: a launch, no read); :attr:`grad_sum` and
    :attr:`grad_count` read them back (once, when densifying, pruning, reordering or saving) and are then
    the host's (float64 arrays, changed in place or replaced freely) until the next ``observe`` writes them
    back."""

    def __init__(self, count: int):
        self._device = density_stats.GradientStatistics()
        self._host: tuple[np.ndarray, np.ndarray] | None = (np.zeros(count), np.zeros(count))
        self._count = count  # Gaussians the statistics are kept for

    @property
    def grad_sum(self) -> np.ndarray:
        """Each Gaussian's sum of image-plane gradients (pixels) over the steps that saw it."""
        return self._on_host()[0]

    @grad_sum.setter
    def grad_sum(self, values: np.ndarray) -> None:
        self._set(np.asarray(values, np.float64), self.grad_count)

    @property
    def grad_count(self) -> np.ndarray:
        """How many steps saw each Gaussian (a positional gradient not exactly 0)."""
        return self._on_host()[1]

    @grad_count.setter
    def grad_count(self, values: np.ndarray) -> None:
        self._set(self.grad_sum, np.asarray(values, np.float64))

    def _on_host(self) -> tuple[np.ndarray, np.ndarray]:
        """The statistics as host arrays, read from the device if steps were observed since."""
        if self._host is None:
            self._host = self._device.read(self._count)
        return self._host

    def _set(self, sums: np.ndarray, counts: np.ndarray) -> None:
        self._host, self._count = (sums, counts), len(sums)

    def _reset(self, count: int) -> None:
        """Start the statistics again at zero for ``count`` Gaussians."""
        self._set(np.zeros(count), np.zeros(count))

    @profiling.timed("densification statistics")
    def observe(self, store: GaussianStore, cam_to_world: np.ndarray, focal: float) -> None:
        """Add each Gaussian's positional gradient of this step, in image-plane pixels (|g| z / f), on the device."""
        if self._host is not None:  # the host's statistics (changed or not) go back first
            self._device.write(*self._host)
            self._host = None
        params, grads = store.gaussians.params, store.gaussians.grads
        self._device.add(params["means"], grads["means"], store.count, cam_to_world, focal)

    def reorder(self, order: np.ndarray) -> None:
        """Follow the store's :meth:`GaussianStore.reorder` with the statistics."""
        self._set(self.grad_sum[order], self.grad_count[order])

    def appended(self, count: int) -> None:
        """Statistics for ``count`` Gaussians appended to the store by someone else (start at zero)."""
        zeros = np.zeros(count)
        self._set(np.concatenate([self.grad_sum, zeros]), np.concatenate([self.grad_count, zeros]))

    def step(self, done: int, store: GaussianStore, schedule: DensitySchedule, rng: np.random.Generator,
             also: np.ndarray | None = None) -> None:
        """3DGS's schedule after ``done`` iterations: densify and prune every ``densify_every`` in the
        window (``also``: rows to grow besides those the gradient picks); reset opacities every
        ``reset_opacity_every`` inside it."""
        if schedule.densifies(done):
            self.densify_and_prune(store, schedule.grad_threshold_px, schedule.split_limit(store.array("means")),
                                   schedule.prune_opacity, schedule.prune_scale, schedule.max_gaussians, rng, also)
        if schedule.reset_opacity_every and done % schedule.reset_opacity_every == 0 and done < schedule.densify_until:
            reset_opacity(store, RESET_OPACITY)

    @profiling.timed("densify / prune / fill")
    def densify_and_prune(self, store: GaussianStore, grad_threshold_px: float, split_scale: float | np.ndarray,
                          min_opacity: float, max_scale: float, max_gaussians: int,
                          rng: np.random.Generator, also: np.ndarray | None = None) -> tuple[int, int]:
        """Gaussians whose mean image-plane gradient exceeds ``grad_threshold_px`` (and the rows in
        ``also``, after them and in their order) are cloned (largest scale <= ``split_scale``: one value
        or one per Gaussian) or split in two samples of themselves with scales / 1.6; then those with
        opacity < ``min_opacity`` or a scale > ``max_scale`` are dropped. Never grows past
        ``max_gaussians``. Resets the statistics. Returns (added, removed)."""
        mean_grad = self.grad_sum / np.maximum(self.grad_count, 1)
        grow = np.flatnonzero(mean_grad > grad_threshold_px)
        room = max(max_gaussians - store.count, 0)
        if len(grow) > room:
            grow = grow[np.argsort(-mean_grad[grow])[:room]]
        if also is not None:  # in the given order of priority, while there is room
            also = np.asarray(also, np.int64)
            grow = np.concatenate([grow, also[~np.isin(also, grow)][:max(room - len(grow), 0)]])
        limit = np.broadcast_to(np.asarray(split_scale, np.float64), (store.count,))[grow]
        big = store.array("log_scales")[grow].max(axis=1) > np.log(limit)
        split, clone = grow[big], grow[~big]
        new_rows = clone_rows(store, clone)
        halves = split_rows(store, split, rng)
        store.append({name: np.concatenate([new_rows[name], halves[name]]) for name in store.fields})
        removed = prune(store, min_opacity, max_scale)
        self._reset(store.count)
        return len(grow), removed

    def drop_lightest(self, store: GaussianStore, weights: np.ndarray, share: float) -> int:
        """[ours] Drop the Gaussians of least blending weight (``weights``, one per Gaussian, e.g. summed over
        the training views: LightGaussian's global significance) that together carry at most ``share`` of
        the total; resets the statistics. Returns how many were dropped."""
        keep = heavier_than_share(weights, share)
        if keep.all():
            return 0
        store.keep(keep)
        self._reset(store.count)
        return int((~keep).sum())

    def split_oversized(self, store: GaussianStore, max_scale: np.ndarray, max_gaussians: int,
                        rng: np.random.Generator) -> int:
        """[ours] Split every Gaussian whose largest scale exceeds its ``max_scale`` (metres, one per
        Gaussian), repeatedly until none does or ``max_gaussians`` is reached (the largest relative to
        their limit first); the children start with zero Adam moments and statistics. Returns how
        many Gaussians were added."""
        added = 0
        limit = np.asarray(max_scale, np.float64)
        while True:
            excess = store.array("log_scales").max(axis=1) - np.log(limit)
            split = np.flatnonzero(excess > 0)
            split = split[np.argsort(-excess[split])[: max(max_gaussians - store.count, 0)]]
            if len(split) == 0:
                return added
            store.append(split_rows(store, split, rng))
            limit = np.concatenate([limit, limit[split]])
            added += len(split)
            self._reset(store.count)

    def state(self) -> dict[str, np.ndarray]:
        return {"grad_sum": self.grad_sum, "grad_count": self.grad_count}

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        self._set(state["grad_sum"].copy(), state["grad_count"].copy())


def clone_rows(store: GaussianStore, rows: np.ndarray) -> dict[str, np.ndarray]:
    """Copies of the Gaussians ``rows``, to append."""
    return {name: value[rows] for name, value in store.arrays().items()}


def split_rows(store: GaussianStore, rows: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Split the Gaussians ``rows`` in two samples of themselves, mirrored about the centre, with
    scales / 1.6: the originals move to one sample in the store (keeping their Adam moments), the
    returned second halves are to append."""
    arrays = store.arrays()
    halves = {name: value[rows] for name, value in arrays.items()}
    if len(rows) == 0:
        return halves
    scales = np.exp(arrays["log_scales"][rows])
    offsets = np.einsum("nij,nj->ni", quat_to_rotmat(arrays["quats"][rows]), rng.normal(size=scales.shape) * scales)
    halves["means"] += offsets
    halves["log_scales"] -= np.log(SPLIT_SHRINK)
    arrays["means"][rows] -= offsets
    arrays["log_scales"][rows] -= np.log(SPLIT_SHRINK)
    store.gaussians.upload(means=arrays["means"], log_scales=arrays["log_scales"])
    return halves


def prune(store: GaussianStore, min_opacity: float, max_scale: float = np.inf) -> int:
    """Drop Gaussians with opacity below ``min_opacity`` or a largest scale above ``max_scale``;
    returns how many (none are dropped if all would be)."""
    keep = store.array("opacity_logits") >= logit(min_opacity)
    if np.isfinite(max_scale):
        keep &= store.array("log_scales").max(axis=1) <= np.log(max_scale)
    if keep.all() or not keep.any():
        return 0
    store.keep(keep)
    return int((~keep).sum())


def heavier_than_share(weights: np.ndarray, share: float) -> np.ndarray:
    """Mask of the rows to keep: all but the lightest ones (ties broken by index) whose weights sum to at
    most ``share`` of the total; at least one row is kept."""
    weights = np.maximum(np.asarray(weights, np.float64), 0.0)
    total = weights.sum()
    if total <= 0:
        return np.ones(len(weights), bool)
    order = np.argsort(weights, kind="stable")
    light = np.cumsum(weights[order]) <= share * total
    light[-1:] = False
    keep = np.ones(len(weights), bool)
    keep[order[light]] = False
    return keep


def reset_opacity(store: GaussianStore, opacity: float) -> None:
    """Clamp every opacity to at most ``opacity`` and forget its Adam moments (3DGS's reset)."""
    store.reset("opacity_logits", np.minimum(store.array("opacity_logits"), logit(opacity)))


def footprint_limit(means: np.ndarray, centres: np.ndarray, focal: float, pixels: float) -> np.ndarray:
    """Per Gaussian, the world size (metres) that ``pixels`` pixels span at its distance from the
    nearest camera centre (``centres`` (C, 3), ``focal`` in pixels)."""
    nearest = np.full(len(means), np.inf)
    for c in np.asarray(centres, np.float64):
        nearest = np.minimum(nearest, np.linalg.norm(np.asarray(means, np.float64) - c, axis=1))
    return pixels * np.maximum(nearest, 1e-6) / focal
