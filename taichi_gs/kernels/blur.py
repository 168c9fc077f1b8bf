"""Blur model: a blurred frame is the mean of k sharp renders; its backward hands each render
``dL/dblur / k``."""

import functools
from collections.abc import Sequence
from types import SimpleNamespace

import taichi as ti

from .. import profiling
from . import runtime


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    spread = runtime.loop_spread()  # image rows x spread indices (see runtime.loop_spread)

    @ti.kernel
    def scale_add(dst: ti.types.ndarray(dtype=dt, ndim=3), src: ti.types.ndarray(dtype=dt, ndim=3), scale: dt,
                  keep: dt):
        for i in range(dst.shape[0] * spread):
            if i % spread == 0:
                v = i // spread
                for u in range(dst.shape[1]):
                    for c in range(dst.shape[2]):
                        dst[v, u, c] = keep * dst[v, u, c] + scale * src[v, u, c]

    return SimpleNamespace(scale_add=scale_add)


@profiling.timed("k-view average / spread")
def average(views: Sequence[ti.Ndarray], out: ti.Ndarray) -> ti.Ndarray:
    """Write the mean of the k same-shaped (H, W, C) images ``views`` into ``out`` and return it."""
    if not views:
        raise ValueError("need at least one view to average")
    for i, img in enumerate(views):
        if img.shape != out.shape:
            raise ValueError(f"view {i} has shape {img.shape}, expected {out.shape}")
        _kernels(out.dtype).scale_add(out, img, 1.0 / len(views), 0.0 if i == 0 else 1.0)
    return out


@profiling.timed("k-view average / spread")
def spread(grad_blurred: ti.Ndarray, k: int, out: ti.Ndarray) -> ti.Ndarray:
    """Gradient of each of the k averaged (H, W, C) views: ``out = grad_blurred / k`` (share it across views)."""
    _kernels(out.dtype).scale_add(out, grad_blurred, 1.0 / k, 0.0)
    return out
