"""How per-pixel image passes split their work on each backend: loops over row spans.

A span is a run of pixels in one image row that one thread walks left to right. On the CPU a span
is a whole row: Taichi's CPU backend runs a range-for over a few hundred rows on one thread, so the
loop iterates over ``spread x rows`` indices and works on every spread-th one
(:func:`~taichi_gs.kernels.runtime.loop_spread`). GPU backends need thousands of threads: a span
there is :data:`GPU_SPAN` pixels and the spread is 1. A reduction writes one partial per span;
:func:`sum_rows` sums each row's partials in order (on the GPU; on the CPU a span's partial is
its row's), so results are deterministic on both.

A kernel loops ``for i in range(span_count(h, w, span) * spread)``, works only where
``i % spread == 0``, and takes its pixels from ``span_at(i // spread, w, span)``; ``span`` comes
from :func:`span_length` when the kernel is built (after ``runtime.init``).
"""

import taichi as ti

from . import runtime

GPU_SPAN = 4  # pixels per thread on GPU backends


def span_length() -> int:
    """Pixels per span on the running backend: 0 for whole rows (CPU), else :data:`GPU_SPAN`."""
    return 0 if runtime.loop_spread() > 1 else GPU_SPAN


def spans_per_row(width: int) -> int:
    """Spans in a row of ``width`` pixels on the running backend (partial buffers hold h x this)."""
    span = span_length()
    return 1 if span == 0 else -(-width // span)


@ti.func
def per_row(w, span: ti.template()):
    """Spans in a row of w pixels (1 for whole rows)."""
    n = 1
    if ti.static(span > 0):
        n = (w + span - 1) // span
    return n


@ti.func
def span_count(h, w, span: ti.template()):
    """Spans in an h x w image."""
    return h * per_row(w, span)


@ti.func
def span_at(j, w, span: ti.template()):
    """Row v and pixel columns [u0, u1) of span j of an image w pixels wide."""
    v, u0, u1 = j, 0, w
    if ti.static(span > 0):
        n = per_row(w, span)
        v = j // n
        u0 = (j - v * n) * span
        u1 = ti.min(u0 + span, w)
    return v, u0, u1


@ti.func
def row_sum(parts: ti.template(), v, n, q: ti.template()):
    """Row v's span partials parts[., q] summed in order (n spans a row)."""
    acc = parts[v * n, q]
    for j in range(v * n + 1, v * n + n):
        acc += parts[j, q]
    return acc


@ti.func
def sum_rows(parts: ti.template(), rows: ti.template(), h, w, span: ti.template(), cols: ti.template()):
    """rows[v, q] = row v's span partials parts[., q] summed in order, for q < cols (a parallel loop
    over the h rows; for GPU spans: on the CPU a span's partial already is its row's)."""
    n = per_row(w, span)
    for v in range(h):
        for q in ti.static(range(cols)):
            rows[v, q] = row_sum(parts, v, n, q)
