"""Per-Gaussian densification statistics on the device: each step adds the length of every Gaussian's
positional gradient in image-plane pixels, ``|dL/dmean| z / f`` (z the depth along the camera's axis), to
its sum, and 1 to its count, in a device buffer (:class:`GradientStatistics`) that the host reads only
when it densifies, prunes or saves: no read per step, none that grows with the Gaussian count.

The sums are float64 where the backend has it (CPU, CUDA): the step's value is computed in the
Gaussians' float type and added in float64, as a host accumulation of the step's values in float64
would. Elsewhere (Vulkan, Metal) they are float32."""

import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from . import host_copy, runtime

NOT_SEEN = -1.0  # image_plane_gradient of a Gaussian whose positional gradient is exactly 0 this step
SUM, COUNT = 0, 1  # the columns of a statistics row


@functools.cache
def _kernels(dt, acc) -> SimpleNamespace:
    vec3 = ti.types.vector(3, dt)
    nd = lambda ndim: ti.types.ndarray(dtype=dt, ndim=ndim)  # noqa: E731

    @ti.kernel
    def accumulate(means: nd(2), grad_means: nd(2), n: ti.i32, centre: vec3, axis: vec3, focal: dt,
                   stats: ti.types.ndarray(dtype=acc, ndim=2)):
        for g in range(n):
            grad = vec3(grad_means[g, 0], grad_means[g, 1], grad_means[g, 2])
            length = grad.norm()
            if length > 0:
                z = ti.abs((vec3(means[g, 0], means[g, 1], means[g, 2]) - centre).dot(axis))
                pixels = length * z / focal
                stats[g, SUM] += ti.cast(pixels, acc)
                stats[g, COUNT] += 1.0

    return SimpleNamespace(accumulate=accumulate)


def sum_type():
    """The float type of the sums: float64 where the backend has it, else float32."""
    backend = runtime.init()
    return ti.f64 if backend.has_f64 else ti.f32


class GradientStatistics:
    """Each Gaussian's sum of image-plane positional gradients and its count of steps that saw it, in one
    (capacity, 2) device buffer (a row per Gaussian: sum, count), grown with the Gaussian count."""

    def __init__(self) -> None:
        self.dtype = sum_type()
        self.stats: ti.Ndarray | None = None

    def write(self, sums: np.ndarray, counts: np.ndarray) -> None:
        """Replace the statistics with ``sums`` and ``counts`` (one per Gaussian; a host write)."""
        n = len(sums)
        if self.stats is None or self.stats.shape[0] < n:
            self.stats = ti.ndarray(self.dtype, (max(int(n * 1.25), 16), 2))
        rows = np.zeros(self.stats.shape)
        rows[:n, SUM], rows[:n, COUNT] = sums, counts
        host_copy.write(self.stats, rows)

    def add(self, means: ti.Ndarray, grad_means: ti.Ndarray, n: int, cam_to_world: np.ndarray,
            focal: float) -> None:
        """Add the first n Gaussians' ``|dL/dmean| z / focal`` (pixels) to their sums and 1 to their counts,
        skipping those whose gradient is exactly 0 (they took no part in the step). Launch only."""
        if self.stats is None or self.stats.shape[0] < n:
            raise ValueError(f"statistics for {0 if self.stats is None else self.stats.shape[0]} Gaussians, "
                             f"not {n}: write them first")
        cam = np.asarray(cam_to_world, np.float64)
        _kernels(means.dtype, self.dtype).accumulate(
            means, grad_means, n, ti.Vector(cam[:3, 3].tolist(), dt=means.dtype),
            ti.Vector(cam[:3, 2].tolist(), dt=means.dtype), float(focal), self.stats)

    def read(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(sums, counts) of the first n Gaussians as float64 NumPy, in one read."""
        rows = host_copy.read(self.stats, n).astype(np.float64)
        return rows[:, SUM].copy(), rows[:, COUNT].copy()


def image_plane_gradient(means: ti.Ndarray, grad_means: ti.Ndarray, n: int, cam_to_world: np.ndarray,
                         focal: float) -> np.ndarray:
    """One step's statistic alone (tests, tools): for the first n Gaussians ``|dL/dmean| z / focal``
    (pixels) as float64 NumPy, with -1 where the gradient is exactly 0."""
    stats = GradientStatistics()
    stats.write(np.zeros(n), np.zeros(n))
    stats.add(means, grad_means, n, cam_to_world, focal)
    sums, counts = stats.read(n)
    return np.where(counts > 0, sums, NOT_SEEN)
