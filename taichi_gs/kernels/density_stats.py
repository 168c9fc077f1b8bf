"""Per-Gaussian densification statistic on device: the length of a step's positional gradient in
image-plane pixels, ``|dL/dmean| z / f`` (z the depth along the camera's axis), so that only N
numbers, not two (N, 3) arrays, travel to the host each step."""

import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from . import host_copy, scan

NOT_SEEN = -1.0  # a Gaussian whose positional gradient is exactly 0 this step


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    vec3 = ti.types.vector(3, dt)
    nd = lambda ndim: ti.types.ndarray(dtype=dt, ndim=ndim)  # noqa: E731

    @ti.kernel
    def image_plane_gradient(means: nd(2), grad_means: nd(2), n: ti.i32, centre: vec3, axis: vec3, focal: dt,
                             out: nd(1)):
        for g in range(n):
            grad = vec3(grad_means[g, 0], grad_means[g, 1], grad_means[g, 2])
            length = grad.norm()
            out[g] = NOT_SEEN
            if length > 0:
                z = ti.abs((vec3(means[g, 0], means[g, 1], means[g, 2]) - centre).dot(axis))
                out[g] = length * z / focal

    return SimpleNamespace(image_plane_gradient=image_plane_gradient)


_scratch = scan.Scratch()


def image_plane_gradient(means: ti.Ndarray, grad_means: ti.Ndarray, n: int, cam_to_world: np.ndarray,
                         focal: float) -> np.ndarray:
    """For the first n Gaussians, ``|dL/dmean| z / focal`` (pixels) as float64 NumPy, with -1 where the
    gradient is exactly 0 (the Gaussian took no part in the step)."""
    out = _scratch.get(f"image-plane gradient {means.dtype}", n, means.dtype)
    cam = np.asarray(cam_to_world, np.float64)
    _kernels(means.dtype).image_plane_gradient(
        means, grad_means, n, ti.Vector(cam[:3, 3].tolist(), dt=means.dtype),
        ti.Vector(cam[:3, 2].tolist(), dt=means.dtype), float(focal), out)
    return host_copy.read(out, n).astype(np.float64)
