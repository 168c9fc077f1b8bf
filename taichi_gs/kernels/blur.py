"""Blur model: a blurred frame is the mean of k sharp renders; its backward hands each render
``dL/dblur / k``. The mean takes one launch for up to :data:`VIEWS_PER_LAUNCH` views."""

import functools
from collections.abc import Sequence
from types import SimpleNamespace

import taichi as ti

from .. import profiling
from . import runtime

VIEWS_PER_LAUNCH = 16  # image arguments of one launch; unused ones get a placeholder


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    spread = runtime.loop_spread()  # image rows x spread indices (see runtime.loop_spread)
    image = ti.types.ndarray(dtype=dt, ndim=3)

    @ti.kernel
    def scale_add(dst: image, src: image, scale: dt, keep: dt):
        for i in range(dst.shape[0] * spread):
            if i % spread == 0:
                v = i // spread
                for u in range(dst.shape[1]):
                    for c in range(dst.shape[2]):
                        dst[v, u, c] = keep * dst[v, u, c] + scale * src[v, u, c]

    @ti.func
    def add_scaled(acc, src: ti.template(), j: ti.template(), count, scale, v, u, c):
        if j < count:
            acc = acc + scale * src[v, u, c]
        return acc

    @ti.kernel
    def scale_add_views(dst: image, s0: image, s1: image, s2: image, s3: image, s4: image, s5: image, s6: image,
                        s7: image, s8: image, s9: image, s10: image, s11: image, s12: image, s13: image, s14: image,
                        s15: image, count: ti.i32, scale: dt, keep: dt):
        """dst = keep * dst + scale * (s0 + ... + s[count - 1]), added in that order."""
        for i in range(dst.shape[0] * spread):
            if i % spread == 0:
                v = i // spread
                for u in range(dst.shape[1]):
                    for c in range(dst.shape[2]):
                        acc = keep * dst[v, u, c]
                        for j, src in ti.static(enumerate((s0, s1, s2, s3, s4, s5, s6, s7, s8, s9, s10, s11, s12,
                                                           s13, s14, s15))):
                            acc = add_scaled(acc, src, j, count, scale, v, u, c)
                        dst[v, u, c] = acc

    return SimpleNamespace(scale_add=scale_add, scale_add_views=scale_add_views)


@functools.cache
def _placeholder(dt) -> ti.Ndarray:
    """A 1 x 1 x 1 image standing in for an unused view argument (never read)."""
    return ti.ndarray(dt, (1, 1, 1))


@profiling.timed("k-view average / spread")
def average(views: Sequence[ti.Ndarray], out: ti.Ndarray) -> ti.Ndarray:
    """Write the mean of the k same-shaped (H, W, C) images ``views`` into ``out`` and return it."""
    if not views:
        raise ValueError("need at least one view to average")
    for i, img in enumerate(views):
        if img.shape != out.shape:
            raise ValueError(f"view {i} has shape {img.shape}, expected {out.shape}")
    k = _kernels(out.dtype)
    for first in range(0, len(views), VIEWS_PER_LAUNCH):
        batch = list(views[first:first + VIEWS_PER_LAUNCH])
        padding = [_placeholder(out.dtype)] * (VIEWS_PER_LAUNCH - len(batch))
        k.scale_add_views(out, *batch, *padding, len(batch), 1.0 / len(views), 0.0 if first == 0 else 1.0)
    return out


@profiling.timed("k-view average / spread")
def spread(grad_blurred: ti.Ndarray, k: int, out: ti.Ndarray) -> ti.Ndarray:
    """Gradient of each of the k averaged (H, W, C) views: ``out = grad_blurred / k`` (share it across views)."""
    _kernels(out.dtype).scale_add(out, grad_blurred, 1.0 / k, 0.0)
    return out
