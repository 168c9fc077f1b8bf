"""A frame's affine colour transform on device (see :mod:`taichi_gs.photometric`, whose NumPy
functions are the reference): ``out = image @ M[:, :3].T + M[:, 3]`` for an (H, W, 3) image and a
3 x 4 ``M``, and its backward. Stage 3 applies it to every step's k-view average, which stays on
the device instead of travelling to NumPy and back four times."""

import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from .. import profiling
from . import row_spans, runtime, scan
from .step_values import Slot, StepValues

N_GRAD_M = 12  # dL/dM, row-major, accumulated per row span


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    img = ti.types.ndarray(dtype=dt, ndim=3)
    mat34 = ti.types.matrix(3, 4, dt)
    spread = runtime.loop_spread()  # row spans x spread indices (see row_spans)
    span = row_spans.span_length()

    @ti.kernel
    def forward_kernel(image: img, M: mat34, out: img):
        h, w = image.shape[0], image.shape[1]
        for i in range(row_spans.span_count(h, w, span) * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                for u in range(u0, u1):
                    for c in ti.static(range(3)):
                        acc = M[c, 3]
                        for j in ti.static(range(3)):
                            acc += M[c, j] * image[v, u, j]
                        out[v, u, c] = acc

    @ti.kernel
    def backward_kernel(image: img, M: mat34, grad_out: img, grad_image: img,
                        parts: ti.types.ndarray(dtype=dt, ndim=2), out: ti.types.ndarray(dtype=dt, ndim=1),
                        at: ti.i32):
        h, w = image.shape[0], image.shape[1]
        for i in range(row_spans.span_count(h, w, span) * spread):
            if i % spread == 0:
                v, u0, u1 = row_spans.span_at(i // spread, w, span)
                acc = ti.Vector.zero(dt, N_GRAD_M)
                for u in range(u0, u1):
                    for j in ti.static(range(3)):
                        g = ti.cast(0.0, dt)
                        for c in ti.static(range(3)):
                            g += M[c, j] * grad_out[v, u, c]
                        grad_image[v, u, j] = g
                    for c in ti.static(range(3)):
                        for j in ti.static(range(3)):
                            acc[4 * c + j] += grad_out[v, u, c] * image[v, u, j]
                        acc[4 * c + 3] += grad_out[v, u, c]
                for q in ti.static(range(N_GRAD_M)):
                    if ti.static(span > 0):
                        parts[i // spread, q] = acc[q]
                    else:  # on the CPU a span is a row: its sums are the row's
                        out[at + v * N_GRAD_M + q] = acc[q]
        if ti.static(span > 0):  # on the GPU, fold each row's spans
            n = row_spans.per_row(w, span)
            for v in range(h):
                for q in ti.static(range(N_GRAD_M)):
                    out[at + v * N_GRAD_M + q] = row_spans.row_sum(parts, v, n, q)

    return SimpleNamespace(forward=forward_kernel, backward=backward_kernel)


_scratch = scan.Scratch()


def _matrix(M: np.ndarray, dtype):
    return ti.Matrix(np.asarray(M, dtype=np.float64).tolist(), dt=dtype)


@profiling.timed("colour transform (device)")
def forward(image: ti.Ndarray, M: np.ndarray, out: ti.Ndarray) -> ti.Ndarray:
    """Write ``image`` (H, W, 3) transformed by the 3 x 4 affine ``M`` into ``out`` and return it."""
    _check(image, out)
    _kernels(image.dtype).forward(image, _matrix(M, image.dtype), out)
    return out


@profiling.timed("colour transform (device)")
def backward(image: ti.Ndarray, M: np.ndarray, grad_out: ti.Ndarray, grad_image: ti.Ndarray,
             into: Slot | None = None) -> np.ndarray | None:
    """Given dL/d out of :func:`forward`, overwrite ``grad_image`` with dL/d image and return
    dL/dM (3 x 4, each image row's sum added up in float64). ``into`` (a slot of H rows of N_GRAD_M values of a
    step's values): leave the rows' sums there and return None; :func:`matrix_gradient` of the rows read is then
    the return value."""
    _check(image, grad_out)
    _check(image, grad_image)
    height, dtype = image.shape[0], image.dtype
    own = _own_values(dtype)
    slot = into or own.rows("affine rows", height, N_GRAD_M)
    if slot.size != height * N_GRAD_M:
        raise ValueError(f"a slot of {slot.size} values for {height} rows of the colour transform's gradient")
    parts = _scratch.get(f"affine spans {dtype}", height * row_spans.spans_per_row(image.shape[1]), dtype,
                         (N_GRAD_M,))
    _kernels(dtype).backward(image, _matrix(M, dtype), grad_out, grad_image, parts, slot.values, slot.at)
    if into is not None:
        return None
    return matrix_gradient(own.read()["affine rows"])


def matrix_gradient(rows: np.ndarray) -> np.ndarray:
    """dL/dM (3 x 4) from the rows a :func:`backward` left ((H, N_GRAD_M)), summed in float64."""
    return np.asarray(rows, np.float64).sum(axis=0).reshape(3, 4)


@functools.cache
def _own_values(dtype) -> StepValues:
    """Where a :func:`backward` without ``into`` leaves its rows before they are read."""
    return StepValues(dtype)


def _check(image: ti.Ndarray, other: ti.Ndarray) -> None:
    if tuple(image.shape) != tuple(other.shape) or len(image.shape) != 3 or image.shape[2] != 3:
        raise ValueError(f"colour transform needs two (H, W, 3) images of one shape, got {image.shape} and "
                         f"{other.shape}")
