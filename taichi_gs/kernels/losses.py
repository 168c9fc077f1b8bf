"""Image and regularisation losses with their gradients, on device.

Each function ADDS ``weight * dL/d(input)`` into the given gradient ndarray, so several terms can share one
gradient buffer before a backward pass, and returns the loss value (a Python float: one host read), or with
``into`` (a :class:`~taichi_gs.kernels.step_values.Slot` of a training step's
:class:`~taichi_gs.kernels.step_values.StepValues`) leaves it on the device, where the step's values wait
for one read per step.
- :func:`l1`: mean over pixels and channels of ``|pred - target|`` (H, W, C).
  The image losses take an optional :class:`PixelWeights` mask: the mean is then over its pixels
  (e.g. only pixels the camera saw, not the unsourced border of an undistorted frame).
- :func:`l1_and_clipped_mse`: the same, and the mean of ``(clip(pred, 0, 1) - target)^2`` (for PSNR).
- :func:`masked_depth_l1`: mean over pixels with ``target > 0`` of ``|pred - target|`` (H, W).
- :func:`normalised_depth_l1_and_coverage`: stage 2's terms, the mean ``|depth / alpha - target|`` over
  pixels with depth and enough opacity, and the mean ``1 - alpha`` over pixels with depth; gradients
  w.r.t. the blended depth and alpha.
- :func:`dssim`: ``1 - mean SSIM`` with an 11x11 Gaussian window (sigma 1.5, zero padding),
  C1 = 0.01^2, C2 = 0.03^2, as 3DGS; gradient w.r.t. ``pred`` only.
- :func:`opacity_binarization`: ``sum_j o_j^2 (1 - o_j)^2`` with ``o = sigmoid(logit)``,
  gradient w.r.t. the logits.
Passes loop over row spans (:mod:`taichi_gs.kernels.row_spans`: whole rows on the CPU, a few pixels
per thread on GPUs); reductions sum each span, then each row's spans, then the rows, in order, so
values are deterministic.
"""

import functools
import math
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np
import taichi as ti

from .. import profiling
from . import row_spans, runtime
from .splat import to_device
from .step_values import Slot, StepValues

SSIM_C1 = 0.01**2
SSIM_C2 = 0.03**2
SSIM_RADIUS = 5
SSIM_SIGMA = 1.5


def _window() -> list[float]:
    w = [math.exp(-((i - SSIM_RADIUS) ** 2) / (2 * SSIM_SIGMA**2)) for i in range(2 * SSIM_RADIUS + 1)]
    return [x / sum(w) for x in w]


WINDOW = _window()


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    fnd = lambda ndim: ti.types.ndarray(dtype=dt, ndim=ndim)  # noqa: E731
    # Per-pixel passes loop over row spans (see row_spans), then over columns and channels inside: a
    # flat (v, u, k) index would cost two integer divisions per element on the CPU backend, more than
    # a loss's arithmetic.
    spread = runtime.loop_spread()
    span = row_spans.span_length()

    @ti.func
    def total_of(rows: ti.template(), n, cols: ti.template()):
        """Column sums of rows[0:n, :cols], in order (deterministic)."""
        total = ti.Vector.zero(dt, cols)
        ti.loop_config(serialize=True)
        for v in range(n):
            for q in ti.static(range(cols)):
                total[q] += rows[v, q]
        return total

    @ti.func
    def totals(parts: ti.template(), rows: ti.template(), h, w, cols: ti.template()):
        """Column sums of the span partials ``parts`` of an h x w image: each row's spans in order
        (into ``rows``), then the rows in order. On the CPU a span is a row: no first step."""
        out = ti.Vector.zero(dt, cols)
        if ti.static(span > 0):
            row_spans.sum_rows(parts, rows, h, w, span, cols)
            out = total_of(rows, h, cols)
        else:
            out = total_of(parts, h, cols)
        return out

    @ti.kernel
    def l1(pred: fnd(3), target: fnd(3), grad: fnd(3), weight: dt, mask: fnd(2), total: dt, parts: fnd(2),
           rows: fnd(2), values: fnd(1), at: ti.i32):
        h, w, c = pred.shape[0], pred.shape[1], pred.shape[2]
        scale = weight / (total * c)
        for i in range(row_spans.span_count(h, w, span) * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                acc, squared = ti.cast(0.0, dt), ti.cast(0.0, dt)
                for u in range(u0, u1):
                    m = mask[v, u]
                    for k in range(c):
                        diff = pred[v, u, k] - target[v, u, k]
                        acc += m * ti.abs(diff)
                        grad[v, u, k] = grad[v, u, k] + m * scale * (ti.cast(diff > 0, dt) - ti.cast(diff < 0, dt))
                        clipped = ti.min(ti.max(pred[v, u, k], 0.0), 1.0) - target[v, u, k]
                        squared += m * clipped * clipped
                parts[i // spread, 0] = acc
                parts[i // spread, 1] = squared
        sums = totals(parts, rows, h, w, 2)
        values[at] = sums[0] / (total * c)
        values[at + 1] = sums[1] / (total * c)

    @ti.kernel
    def masked_depth_l1(pred: fnd(2), target: fnd(2), grad: fnd(2), weight: dt, parts: fnd(2), rows: fnd(2),
                        values: fnd(1), at: ti.i32):
        h, w = pred.shape[0], pred.shape[1]
        n_spans = row_spans.span_count(h, w, span)
        for i in range(n_spans * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                acc = ti.cast(0.0, dt)
                count = ti.cast(0.0, dt)
                for u in range(u0, u1):
                    if target[v, u] > 0:
                        acc += ti.abs(pred[v, u] - target[v, u])
                        count += 1.0
                parts[i // spread, 0] = acc
                parts[i // spread, 1] = count
        sums = totals(parts, rows, h, w, 2)
        total, count = sums[0], ti.max(sums[1], 1.0)
        for i in range(n_spans * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                for u in range(u0, u1):
                    if target[v, u] > 0:
                        diff = pred[v, u] - target[v, u]
                        grad[v, u] = grad[v, u] + weight / count * (ti.cast(diff > 0, dt) - ti.cast(diff < 0, dt))
        values[at] = total / count

    @ti.func
    def depth_pixel(depth: ti.template(), trans: ti.template(), target: ti.template(), v, u, min_alpha):
        """(has depth, counted in the depth term, alpha where counted else 1, transmittance, blended depth,
        target) of pixel (v, u) of stage 2's terms; branch-free (selects): data-dependent branches per pixel
        cost more than the arithmetic."""
        t, tr, d = target[v, u], trans[v, u], depth[v, u]
        valid = ti.cast(t > 0, dt)
        inside = valid * ti.cast(1.0 - tr >= min_alpha, dt)
        return valid, inside, ti.select(inside > 0, 1.0 - tr, 1.0), tr, d, t

    @ti.kernel
    def normalised_depth_l1_and_coverage(depth: fnd(2), trans: fnd(2), target: fnd(2), grad_depth: fnd(2),
                                         grad_alpha: fnd(2), min_alpha: dt, weight: dt, coverage_weight: dt,
                                         parts: fnd(2), rows: fnd(2), values: fnd(1), at: ti.i32):
        h, w = depth.shape[0], depth.shape[1]
        n_spans = row_spans.span_count(h, w, span)
        for i in range(n_spans * spread):  # sums: |residual|, its pixels, 1 - alpha, pixels with depth
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                acc = ti.Vector.zero(dt, 4)
                for u in range(u0, u1):
                    valid, inside, alpha, tr, d, t = depth_pixel(depth, trans, target, v, u, min_alpha)
                    acc += ti.Vector([inside * ti.abs(d / alpha - t), inside, valid * tr, valid], dt=dt)
                for q in ti.static(range(4)):
                    parts[i // spread, q] = acc[q]
        sums = totals(parts, rows, h, w, 4)
        count, n_valid = ti.max(sums[1], 1.0), ti.max(sums[3], 1.0)
        for i in range(n_spans * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                for u in range(u0, u1):
                    valid, inside, alpha, _tr, d, t = depth_pixel(depth, trans, target, v, u, min_alpha)
                    g_depth0, g_alpha0 = grad_depth[v, u], grad_alpha[v, u]  # reads before the writes
                    residual = d / alpha - t
                    sign = ti.cast(residual > 0, dt) - ti.cast(residual < 0, dt)
                    g_depth = inside * weight / count * sign / alpha
                    grad_depth[v, u] = g_depth0 + g_depth
                    grad_alpha[v, u] = g_alpha0 - g_depth * d / alpha - valid * coverage_weight / n_valid
        values[at] = sums[0] / count
        values[at + 1] = sums[2] / n_valid

    # D-SSIM's four passes check the window's taps against the image edge only near it: rows and columns at
    # least SSIM_RADIUS pixels inside run unchecked (branch-free) sums, adding the taps in the same order.
    # Its scratch records are flat arrays, indexed once per tap (a multi-dimensional ndarray index costs
    # integer arithmetic per access on the CPU backend): 0.64x the kernel's time at 256x192
    # (docs/notebook/benchmarks-2026-11.md, "D-SSIM and the blending passes on flat scratch records").
    # The taps are a loop over the window's weights (a device array), not unrolled: with 11 taps unrolled in each
    # pass and variant the kernel took 27 s to compile from an empty offline cache and 1.8 s to load from a full
    # one (the Python front end unrolls before the cache is consulted); the channels stay unrolled (a channel
    # loop made it 1.1-1.25x slower). docs/notebook/benchmarks-2026-11.md, "Compile time: D-SSIM's window taps as a
    # loop".
    taps = 2 * SSIM_RADIUS + 1

    @ti.func
    def interior(n):
        """[first, last + 1) of the indices of an axis of n whose whole window lies inside it."""
        return ti.min(SSIM_RADIUS, n), ti.max(n - SSIM_RADIUS, SSIM_RADIUS)

    @ti.func
    def row_moments(pred: ti.template(), target: ti.template(), window: ti.template(), v, u, k, w,
                    checked: ti.template()):
        """Horizontal window sums of (x, y, x^2, y^2, xy) at (v, u) of channel k."""
        m = ti.Vector.zero(dt, 5)
        for t in range(taps):
            col = u + t - SSIM_RADIUS
            if not ti.static(checked) or 0 <= col < w:
                x, y = pred[v, col, k], target[v, col, k]
                m += window[t] * ti.Vector([x, y, x * x, y * y, x * y], dt=dt)
        return m

    @ti.func
    def record(v, u, k, w, c: ti.template(), q: ti.template()):
        """Flat index of pixel (v, u)'s channel-k record of q values in a scratch array (row-major pixels)."""
        return ((v * w + u) * c + k) * q

    @ti.func
    def window_sum(src: ti.template(), window: ti.template(), base, stride, at, n, q: ti.template(),
                   checked: ti.template()):
        """Window sums of the q values at flat index ``base`` in ``src``, the window along an axis of n
        indices centred on index ``at``, its neighbours ``stride`` apart (a row: c q; a column: w c q)."""
        acc = ti.Vector.zero(dt, q)
        for i in range(taps):
            x = at + i - SSIM_RADIUS
            if not ti.static(checked) or 0 <= x < n:
                tap = base + (i - SSIM_RADIUS) * stride
                for j in ti.static(range(q)):
                    acc[j] += window[i] * src[tap + j]
        return acc

    @ti.func
    def moments_row(pred: ti.template(), target: ti.template(), window: ti.template(), moments: ti.template(), v,
                    u0, u1, c: ti.template()):
        """Pass 1 on row v's pixels [u0, u1): horizontal window sums into ``moments``."""
        w = pred.shape[1]
        first, last = interior(w)
        for u in range(u0, u1):
            for k in ti.static(range(c)):
                m = ti.Vector.zero(dt, 5)
                if first <= u < last:
                    m = row_moments(pred, target, window, v, u, k, w, False)
                else:
                    m = row_moments(pred, target, window, v, u, k, w, True)
                for j in ti.static(range(5)):
                    moments[record(v, u, k, w, c, 5) + j] = m[j]

    @ti.func
    def ssim_row(moments: ti.template(), window: ti.template(), mask: ti.template(), partial: ti.template(), v, u0,
                 u1, weight, total, c: ti.template(), checked: ti.template()):
        """Pass 2 on row v's pixels [u0, u1): vertical window sums, SSIM and dSSIM/d(mu1, E[x^2], E[xy]);
        returns their masked SSIM sum."""
        h, w = mask.shape[0], mask.shape[1]
        acc = ti.cast(0.0, dt)
        norm = -weight / (total * c)
        for u in range(u0, u1):
            scale = norm * mask[v, u]
            for k in ti.static(range(c)):
                m = window_sum(moments, window, record(v, u, k, w, c, 5), w * c * 5, v, h, 5, checked)
                mu1, mu2 = m[0], m[1]
                s11, s22, s12 = m[2] - mu1 * mu1, m[3] - mu2 * mu2, m[4] - mu1 * mu2
                a1, a2 = 2 * mu1 * mu2 + dt(SSIM_C1), 2 * s12 + dt(SSIM_C2)
                b1, b2 = mu1 * mu1 + mu2 * mu2 + dt(SSIM_C1), s11 + s22 + dt(SSIM_C2)
                inv = 1.0 / (b1 * b2)  # one division: 1 / b1 = b2 inv, 1 / b2 = b1 inv
                ssim = a1 * a2 * inv
                acc += mask[v, u] * ssim
                at = record(v, u, k, w, c, 3)
                partial[at] = scale * inv * (2 * mu2 * (a2 - a1) - 2 * mu1 * ssim * (b2 - b1))
                partial[at + 1] = scale * (-ssim * b1 * inv)
                partial[at + 2] = scale * (2 * a1 * inv)
        return acc

    @ti.func
    def blurred_partial_row(partial: ti.template(), window: ti.template(), blurred_partial: ti.template(), v, u0, u1,
                            w, c: ti.template()):
        """Pass 3 on row v's pixels [u0, u1): the partials' horizontal window sums."""
        first, last = interior(w)
        for u in range(u0, u1):
            for k in ti.static(range(c)):
                m = ti.Vector.zero(dt, 3)
                base = record(v, u, k, w, c, 3)
                if first <= u < last:
                    m = window_sum(partial, window, base, c * 3, u, w, 3, False)
                else:
                    m = window_sum(partial, window, base, c * 3, u, w, 3, True)
                for j in ti.static(range(3)):
                    blurred_partial[base + j] = m[j]

    @ti.func
    def gradient_row(blurred_partial: ti.template(), window: ti.template(), pred: ti.template(), target: ti.template(),
                     grad: ti.template(), v, u0, u1, c: ti.template(), checked: ti.template()):
        """Pass 4 on row v's pixels [u0, u1): the partials' vertical window sums, chained into dL/dpred."""
        h, w = pred.shape[0], pred.shape[1]
        for u in range(u0, u1):
            for k in ti.static(range(c)):
                m = window_sum(blurred_partial, window, record(v, u, k, w, c, 3), w * c * 3, v, h, 3, checked)
                grad[v, u, k] = grad[v, u, k] + m[0] + 2 * pred[v, u, k] * m[1] + target[v, u, k] * m[2]

    @ti.kernel
    def dssim(
        pred: fnd(3), target: fnd(3), grad: fnd(3), weight: dt, mask: fnd(2), total: dt, window: fnd(1),
        moments: fnd(1), partial: fnd(1), blurred_partial: fnd(1), parts: fnd(2), rows: fnd(2), c: ti.template(),
        values: fnd(1), at: ti.i32,
    ):
        h, w = pred.shape[0], pred.shape[1]
        n_spans = row_spans.span_count(h, w, span)
        first, last = interior(h)
        for i in range(n_spans * spread):  # horizontal window sums of x, y, x^2, y^2, xy
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                moments_row(pred, target, window, moments, v, u0, u1, c)
        for i in range(n_spans * spread):  # vertical window sums, SSIM and its partials
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                if first <= v < last:
                    parts[i // spread, 0] = ssim_row(moments, window, mask, partial, v, u0, u1, weight, total,
                                                     c, False)
                else:
                    parts[i // spread, 0] = ssim_row(moments, window, mask, partial, v, u0, u1, weight, total,
                                                     c, True)
        for i in range(n_spans * spread):  # the window is symmetric: the backward blurs the partials again
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                blurred_partial_row(partial, window, blurred_partial, v, u0, u1, w, c)
        for i in range(n_spans * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                if first <= v < last:
                    gradient_row(blurred_partial, window, pred, target, grad, v, u0, u1, c, False)
                else:
                    gradient_row(blurred_partial, window, pred, target, grad, v, u0, u1, c, True)
        values[at] = 1.0 - totals(parts, rows, h, w, 1)[0] / (total * c)

    @ti.kernel
    def opacity_binarization(logits: fnd(1), grad: fnd(1), n: ti.i32, weight: dt, rows: fnd(2), values: fnd(1),
                             at: ti.i32):
        n_chunks = (n + 1023) // 1024
        for c in range(n_chunks * spread):  # a few hundred chunks: spread, or the CPU backend runs them on one thread
            if c % spread == 0:
                chunk = c // spread
                acc = ti.cast(0.0, dt)
                for i in range(chunk * 1024, ti.min(n, chunk * 1024 + 1024)):
                    o = 1.0 / (1.0 + ti.exp(-logits[i]))
                    acc += o * o * (1 - o) * (1 - o)
                    grad[i] = grad[i] + weight * 2 * o * (1 - o) * (1 - 2 * o) * o * (1 - o)
                rows[chunk, 0] = acc
        values[at] = total_of(rows, n_chunks, 1)[0]

    return SimpleNamespace(l1=l1, masked_depth_l1=masked_depth_l1, dssim=dssim,
                           opacity_binarization=opacity_binarization,
                           normalised_depth_l1_and_coverage=normalised_depth_l1_and_coverage)


_scratch: dict[tuple, ti.Ndarray] = {}


def _buffer(name: str, dtype, shape: tuple) -> ti.Ndarray:
    key = (name, dtype, shape)
    if key not in _scratch:
        _scratch[key] = ti.ndarray(dtype, shape)
    return _scratch[key]


def _partials(image: ti.Ndarray, cols: int) -> tuple[ti.Ndarray, ti.Ndarray]:
    """Scratch for a reduction over an image: per-span partials and per-row sums, ``cols`` values each."""
    h, w = image.shape[0], image.shape[1]
    return (_buffer("span_partials", image.dtype, (h * row_spans.spans_per_row(w), cols)),
            _buffer("row_sums", image.dtype, (h, cols)))


@functools.cache
def _window_on_device(dt) -> ti.Ndarray:
    """The D-SSIM window's taps (:data:`WINDOW`) as a device array, read by the kernel's tap loops."""
    return to_device(np.array(WINDOW), dt)


def _checked(pred, target, grad):
    if pred.shape != target.shape or pred.shape != grad.shape:
        raise ValueError(f"shape mismatch: pred {pred.shape}, target {target.shape}, grad {grad.shape}")
    return pred.dtype


@dataclass(frozen=True)
class PixelWeights:
    """Per-pixel weights (H, W) of an image loss on device, and their sum (the loss's normaliser)."""

    weights: ti.Ndarray
    total: float


def pixel_weights(mask: np.ndarray, dtype) -> PixelWeights:
    """:class:`PixelWeights` of a boolean or 0/1 (H, W) mask: the loss averages over its pixels."""
    mask = np.asarray(mask, np.float64)
    if mask.ndim != 2 or not np.any(mask > 0):
        raise ValueError(f"a pixel mask must be a non-empty (H, W) array, got shape {mask.shape}")
    return PixelWeights(to_device(mask, dtype), float(mask.sum()))


@functools.cache
def _every_pixel(dt, h: int, w: int) -> PixelWeights:
    return pixel_weights(np.ones((h, w)), dt)


def _weights_for(pred: ti.Ndarray, mask: PixelWeights | None) -> PixelWeights:
    h, w = pred.shape[0], pred.shape[1]
    if mask is None:
        return _every_pixel(pred.dtype, h, w)
    if tuple(mask.weights.shape) != (h, w) or mask.weights.dtype != pred.dtype:
        raise ValueError(f"pixel mask {tuple(mask.weights.shape)} does not fit an image of {h}x{w}")
    return mask


def _run(kernel, dt, count: int, into: Slot | None, *args) -> tuple[float, ...] | None:
    """Launch a loss kernel that leaves ``count`` values at ``into``; without ``into``, read them (one read)."""
    own = _own_values(dt)
    slot = into or own.rows("values", 1, count)
    if into is not None and into.size != count:
        raise ValueError(f"a slot of {into.size} values for a loss of {count}")
    kernel(*args, slot.values, slot.at)
    if into is not None:
        return None
    return tuple(float(v) for v in own.read()["values"][0])


@functools.cache
def _own_values(dt) -> StepValues:
    """Where a loss called without ``into`` leaves its values before they are read."""
    return StepValues(dt, 16)


def l1(pred: ti.Ndarray, target: ti.Ndarray, grad: ti.Ndarray, weight: float = 1.0,
       mask: PixelWeights | None = None) -> float:
    """Mean absolute error of (H, W, C) images (over ``mask``'s pixels, weighted; None: all);
    adds ``weight * dL/dpred`` to ``grad``."""
    return l1_and_clipped_mse(pred, target, grad, weight, mask)[0]


@profiling.timed("losses (device)")
def l1_and_clipped_mse(pred: ti.Ndarray, target: ti.Ndarray, grad: ti.Ndarray, weight: float = 1.0,
                       mask: PixelWeights | None = None, into: Slot | None = None) -> tuple[float, float] | None:
    """:func:`l1`, and from the same pass the mean of ``(clip(pred, 0, 1) - target)^2`` over the same
    pixels (for PSNR; no gradient). ``into``: leave both on the device there (two slots), return None."""
    dt = _checked(pred, target, grad)
    mask = _weights_for(pred, mask)
    return _run(_kernels(dt).l1, dt, 2, into, pred, target, grad, weight, mask.weights, mask.total,
                *_partials(pred, 2))


@profiling.timed("losses (device)")
def masked_depth_l1(pred: ti.Ndarray, target: ti.Ndarray, grad: ti.Ndarray, weight: float = 1.0,
                    into: Slot | None = None) -> float | None:
    """Mean ``|pred - target|`` over pixels with target > 0 of (H, W) depth maps; adds to ``grad``."""
    dt = _checked(pred, target, grad)
    value = _run(_kernels(dt).masked_depth_l1, dt, 1, into, pred, target, grad, weight, *_partials(pred, 2))
    return None if value is None else value[0]


@profiling.timed("losses (device)")
def normalised_depth_l1_and_coverage(depth: ti.Ndarray, transmittance: ti.Ndarray, target: ti.Ndarray,
                                     grad_depth: ti.Ndarray, grad_alpha: ti.Ndarray, min_alpha: float,
                                     weight: float = 1.0, coverage_weight: float = 1.0,
                                     into: Slot | None = None) -> tuple[float, float] | None:
    """Stage 2's depth terms of one render (H, W): the mean ``|depth / alpha - target|`` over pixels with
    target > 0 and alpha = 1 - transmittance >= ``min_alpha``, and the coverage loss, the mean ``1 - alpha``
    over pixels with target > 0. Adds the gradients of ``weight * depth term + coverage_weight * coverage``
    w.r.t. the blended depth to ``grad_depth`` and w.r.t. alpha to ``grad_alpha``; returns both terms."""
    dt = _checked(depth, target, grad_depth)
    _checked(transmittance, target, grad_alpha)
    return _run(_kernels(dt).normalised_depth_l1_and_coverage, dt, 2, into, depth, transmittance, target,
                grad_depth, grad_alpha, min_alpha, weight, coverage_weight, *_partials(depth, 4))


@profiling.timed("losses (device)")
def dssim(pred: ti.Ndarray, target: ti.Ndarray, grad: ti.Ndarray, weight: float = 1.0,
          mask: PixelWeights | None = None, into: Slot | None = None) -> float | None:
    """``1 - SSIM`` of (H, W, C) images (3DGS window and constants), the SSIM map averaged over
    ``mask``'s pixels (weighted; None: all); adds ``weight * dL/dpred``."""
    dt = _checked(pred, target, grad)
    h, w, c = pred.shape
    mask = _weights_for(pred, mask)
    value = _run(
        _kernels(dt).dssim, dt, 1, into, pred, target, grad, weight, mask.weights, mask.total, _window_on_device(dt),
        _buffer("moments", dt, (h * w * c * 5,)), _buffer("partial", dt, (h * w * c * 3,)),
        _buffer("blurred_partial", dt, (h * w * c * 3,)), *_partials(pred, 1), c,
    )
    return None if value is None else value[0]


@profiling.timed("losses (device)")
def opacity_binarization(logits: ti.Ndarray, grad: ti.Ndarray, n: int, weight: float = 1.0,
                         into: Slot | None = None) -> float | None:
    """``sum o^2 (1 - o)^2`` over the first n logits; adds ``weight * dL/dlogit`` to ``grad``."""
    dt = logits.dtype
    rows = _buffer("chunks", dt, (max(1, -(-n // 1024)), 1))
    value = _run(_kernels(dt).opacity_binarization, dt, 1, into, logits, grad, n, weight, rows)
    return None if value is None else value[0]
