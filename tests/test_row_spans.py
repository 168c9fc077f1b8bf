"""Row spans (taichi_gs.kernels.row_spans): every pixel of an image lies in exactly one span, in its
own row, for whole rows (the CPU's split) and for GPU-sized spans, widths that they divide or not.
The GPU split of the losses and the colour transform themselves runs in tests/test_gpu_backend.py."""

import numpy as np
import pytest
import taichi as ti

from taichi_gs.kernels import row_spans, runtime


def span_cover(h: int, w: int, span: int) -> tuple[np.ndarray, int]:
    """How many spans cover each pixel of an h x w image (misplaced rows count as -1000), and the
    number of spans."""
    runtime.init("cpu")

    @ti.kernel
    def cover(counts: ti.types.ndarray(dtype=ti.i32, ndim=2), span: ti.template()) -> ti.i32:
        n = row_spans.span_count(counts.shape[0], counts.shape[1], span)
        for j in range(n):
            v, u0, u1 = row_spans.span_at(j, counts.shape[1], span)
            for u in range(u0, u1):
                ti.atomic_add(counts[v, u], 1)
            if span > 0 and (u1 - u0 > span or u1 <= u0 or j // row_spans.per_row(counts.shape[1], span) != v):
                ti.atomic_add(counts[v, u0], -1000)
        return n

    counts = ti.ndarray(ti.i32, (h, w))
    counts.fill(0)
    n = cover(counts, span)
    return counts.to_numpy(), n


@pytest.mark.parametrize("span", [0, 1, 4, 5])
@pytest.mark.parametrize("h, w", [(7, 3), (37, 45), (192, 256)])
def test_spans_cover_every_pixel_once(span: int, h: int, w: int) -> None:
    counts, n = span_cover(h, w, span)
    np.testing.assert_array_equal(counts, np.ones((h, w), np.int32))
    assert n == h * (1 if span == 0 else -(-w // span))


def test_the_cpu_runs_whole_rows() -> None:
    runtime.init("cpu")
    assert row_spans.span_length() == 0
    assert row_spans.spans_per_row(257) == 1
