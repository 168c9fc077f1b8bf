"""A driver canary: loops whose iterations contain an atomic must all run.

Debian bookworm's lavapipe (Mesa 22.3.6) drops most such iterations (it counted 8 of 400000
below), which silently breaks tile binning. :func:`atomic_loop_counts` runs two small kernels,
fixed and data-dependent trip counts, and returns (counted, expected) for each.
"""

import functools

import numpy as np
import taichi as ti

_ind = ti.types.ndarray(dtype=ti.i32, ndim=1)


@functools.cache
def _kernels():
    @ti.kernel
    def fixed_loops(
        hist: _ind,  # output (M,) counts, added to
        n: ti.i32,
    ):
        for _ in range(4):
            for j in range(n):
                ti.atomic_add(hist[j % hist.shape[0]], 1)

    @ti.kernel
    def ragged_loops(
        counts: _ind,  # (G,) loop length per outer iteration
        hist: _ind,  # output (M,) counts, added to
    ):
        for g in range(counts.shape[0]):
            for t in range(counts[g]):
                ti.atomic_add(hist[(g + t) % hist.shape[0]], 1)

    return fixed_loops, ragged_loops


def atomic_loop_counts() -> list[tuple[int, int]]:
    """[(counted, expected)] for a fixed 4 x 100000 loop and 10000 loops of 0..7 iterations."""
    fixed_loops, ragged_loops = _kernels()
    hist = ti.ndarray(ti.i32, (1000,))
    hist.fill(0)
    fixed_loops(hist, 100_000)
    results = [(int(hist.to_numpy().sum()), 400_000)]
    counts = np.random.default_rng(0).integers(0, 8, 10_000).astype(np.int32)
    dev_counts = ti.ndarray(ti.i32, counts.shape)
    dev_counts.from_numpy(counts)
    hist.fill(0)
    ragged_loops(dev_counts, hist)
    results.append((int(hist.to_numpy().sum()), int(counts.sum())))
    return results
