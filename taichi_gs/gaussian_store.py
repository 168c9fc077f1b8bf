"""Gaussians on the device together with their Adam state: the one parameter store of stages 2 and 3.

Parameters, gradients and Adam moments live side by side, and every operation that changes the
rows (``keep``, ``append``) or the values (``reset``) of a parameter does the same to its moments,
so no moment can be left behind by densification, pruning or an opacity reset.
"""

from __future__ import annotations

import numpy as np

from .render import Adam, DeviceGaussians, float_type, host_copy

ISOTROPIC_FIELDS = ("means", "log_scales", "opacity_logits", "colors")
FIELDS = ("means", "quats", "log_scales", "opacity_logits", "colors")


class GaussianStore:
    """N Gaussians (``DeviceGaussians`` layout) of which the ``trained`` parameters take Adam steps.

    ``arrays``: means (N, 3), log_scales (N, 3) or (N,) / (N, 1) when ``isotropic``, opacity_logits
    (N,), colors (N, M, 3) SH coefficients, and quats (N, 4) unless ``isotropic`` (then scales and
    rotations are fixed and quats is not stored). ``precision``: "f32", or "f64" (CPU/CUDA) for tests.
    """

    def __init__(self, arrays: dict[str, np.ndarray], trained: tuple[str, ...], isotropic: bool = False,
                 precision: str = "f32"):
        self.trained = trained
        self.isotropic = isotropic
        self.dtype = float_type(precision)
        self.fields = ISOTROPIC_FIELDS if isotropic else FIELDS
        self._build(arrays, moments=None, t=0)

    def _build(self, arrays: dict[str, np.ndarray], moments: dict[str, tuple[np.ndarray, np.ndarray]] | None,
               t: int) -> None:
        self.gaussians = DeviceGaussians.from_numpy(
            arrays["means"], None if self.isotropic else arrays["quats"], arrays["log_scales"],
            arrays["opacity_logits"], arrays["colors"], isotropic=self.isotropic, dtype=self.dtype)
        self.adam = Adam(self.gaussians.params, self.gaussians.grads, {name: 0.0 for name in self.trained})
        self.adam.t = t
        for name, (m, v) in (moments or {}).items():
            host_copy.write(self.adam.moments[name][0], m)
            host_copy.write(self.adam.moments[name][1], v)

    @property
    def count(self) -> int:
        return self.gaussians.n

    def arrays(self) -> dict[str, np.ndarray]:
        """Every stored parameter as NumPy, trimmed to the live Gaussians."""
        return {name: host_copy.read(self.gaussians.params[name], self.count) for name in self.fields}

    def array(self, name: str) -> np.ndarray:
        """One parameter as NumPy, trimmed to the live Gaussians."""
        return host_copy.read(self.gaussians.params[name], self.count)

    def moments(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Adam's first and second moments of every trained parameter, trimmed to the live Gaussians."""
        return {name: (host_copy.read(m, self.count), host_copy.read(v, self.count))
                for name, (m, v) in self.adam.moments.items()}

    def step(self, lrs: dict[str, float]) -> None:
        """One Adam step of the trained parameters on their accumulated gradients (missing rates: 0)."""
        self.adam.lrs.update({name: lrs.get(name, 0.0) for name in self.trained})
        self.adam.step(self.count)

    def keep(self, mask: np.ndarray) -> None:
        """Keep the Gaussians where ``mask`` is true (their parameters and moments, in order)."""
        self._take(np.asarray(mask, bool))

    def reorder(self, order: np.ndarray) -> None:
        """Put the Gaussians in ``order`` (a permutation of the rows), moments alongside."""
        order = np.asarray(order)
        if order.shape != (self.count,) or not np.array_equal(np.sort(order), np.arange(self.count)):
            raise ValueError("order must be a permutation of the Gaussians")
        self._take(order)

    def _take(self, rows: np.ndarray) -> None:
        """Rebuild the store from the given rows (a mask or an index array) of parameters and moments."""
        moments = {name: (m[rows], v[rows]) for name, (m, v) in self.moments().items()}
        self._build({name: value[rows] for name, value in self.arrays().items()}, moments, self.adam.t)

    def append(self, rows: dict[str, np.ndarray]) -> None:
        """Add Gaussians after the existing ones (every stored field given), with zero Adam moments."""
        current = self.arrays()
        missing = set(self.fields) - set(rows)
        if missing:
            raise ValueError(f"new Gaussians lack {sorted(missing)}")
        merged = {name: np.concatenate([current[name], np.asarray(rows[name], current[name].dtype)
                                        .reshape((-1,) + current[name].shape[1:])]) for name in self.fields}
        added = len(merged["means"]) - self.count
        moments = {name: tuple(np.concatenate([mv, np.zeros((added,) + mv.shape[1:], mv.dtype)]) for mv in pair)
                   for name, pair in self.moments().items()}
        self._build(merged, moments, self.adam.t)

    def reset(self, name: str, values: np.ndarray) -> None:
        """Overwrite one parameter and forget its Adam moments (as 3DGS's opacity reset does)."""
        self.gaussians.upload(**{name: np.asarray(values)})
        if name in self.adam.moments:
            for moment in self.adam.moments[name]:
                moment.fill(0.0)

    def state(self) -> dict[str, np.ndarray]:
        """Everything needed to resume: parameters, Adam moments and step count."""
        out = {f"p_{name}": value for name, value in self.arrays().items()}
        for name, (m, v) in self.moments().items():
            out[f"m_{name}"], out[f"v_{name}"] = m, v
        out["adam_t"] = np.array(self.adam.t)
        return out

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore what :meth:`state` saved."""
        moments = {name: (state[f"m_{name}"], state[f"v_{name}"]) for name in self.trained}
        self._build({name: state[f"p_{name}"] for name in self.fields}, moments, int(state["adam_t"]))


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """The low 10 bits of each value moved to every third bit position (for a 30-bit Morton code)."""
    x = x.astype(np.uint64) & np.uint64(0x3FF)
    for shift, mask in ((16, 0x030000FF), (8, 0x0300F00F), (4, 0x030C30C3), (2, 0x09249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_order(points: np.ndarray) -> np.ndarray:
    """[ours] A permutation putting ``points`` (N, 3) along a Morton (Z-order) curve of their bounding
    box at 1024 cells per axis: Gaussians near in space become near in memory, so the per-tile work
    (which visits a tile's Gaussians) reads their records with fewer cache misses."""
    points = np.asarray(points, np.float64)
    if len(points) == 0:
        return np.zeros(0, np.int64)
    lo, span = points.min(axis=0), np.ptp(points, axis=0)
    cells = np.floor((points - lo) / np.maximum(span, 1e-12) * 1023.999).astype(np.int64)
    code = (_spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << np.uint64(1))
            | (_spread_bits(cells[:, 2]) << np.uint64(2)))
    return np.argsort(code, kind="stable")


class OnStore:
    """A trainable scene whose Gaussians live in ``self.store`` (a :class:`GaussianStore`)."""

    store: GaussianStore

    @property
    def gaussians(self):
        """The device Gaussians (``render.DeviceGaussians``) of the store."""
        return self.store.gaussians

    @property
    def count(self) -> int:
        return self.store.count
