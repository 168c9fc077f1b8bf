"""Tile binning: which 16x16 tiles each Gaussian touches, and each tile's list sorted by depth.

Layout of the intersection ("slot") arrays:
- slots are Gaussian-major: Gaussian g owns slots ``offsets[g] .. offsets[g + 1]`` (one per tile it
  touches); ``slot_gid[s]`` and ``slot_tile[s]`` say whose slot it is and for which tile;
- the tile-major list ``order`` holds slot ids grouped by tile (tile t owns
  ``tile_start[t] .. tile_start[t + 1]``), each group sorted front to back by (depth, slot).
The backward pass writes per-slot gradients, so a Gaussian's gradient is a contiguous segmented
sum without atomics.
"""

import functools
from types import SimpleNamespace

import taichi as ti

Array = ti.template()  # an ndarray argument of a ti.func (passed by reference)

TILE = 16
INSERTION_RUN = 16


@ti.func
def tile_box(rect: Array, g):
    """Inclusive tile range (tx0, ty0, tx1, ty1) of Gaussian g's pixel box."""
    return ti.Vector([rect[g, 0] // TILE, rect[g, 1] // TILE, rect[g, 2] // TILE, rect[g, 3] // TILE])


@ti.func
def tile_count(rect: Array, g):
    """Number of tiles Gaussian g touches (0 when culled)."""
    n = 0
    if rect[g, 0] <= rect[g, 2]:
        b = tile_box(rect, g)
        n = (b[2] - b[0] + 1) * (b[3] - b[1] + 1)
    return n


@ti.func
def emit_slots(g, rect: Array, offsets: Array, slot_gid: Array, slot_tile: Array, tiles_x):
    """Fill Gaussian g's slots with its id and their tile ids."""
    if rect[g, 0] <= rect[g, 2]:
        b = tile_box(rect, g)
        s = offsets[g]
        for ty in range(b[1], b[3] + 1):
            for tx in range(b[0], b[2] + 1):
                slot_gid[s] = g
                slot_tile[s] = ty * tiles_x + tx
                s += 1


@functools.cache
def make(dt) -> SimpleNamespace:
    """Per-tile depth sort for float key type ``dt``."""

    @ti.func
    def before(ka, va, kb, vb):
        return ka < kb or (ka == kb and va < vb)

    @ti.func
    def merge(src_k: Array, src_v: Array, dst_k: Array, dst_v: Array, lo, mid, hi):
        i, j = lo, mid
        for out in range(lo, hi):
            if j >= hi or (i < mid and not before(src_k[j], src_v[j], src_k[i], src_v[i])):
                dst_k[out] = src_k[i]
                dst_v[out] = src_v[i]
                i += 1
            else:
                dst_k[out] = src_k[j]
                dst_v[out] = src_v[j]
                j += 1

    @ti.func
    def sort_segment(keys: Array, vals: Array, tmp_k: Array, tmp_v: Array, lo, hi):
        """Sort keys[lo:hi] (with vals) by (key, val): insertion-sorted runs, then bottom-up
        merges ping-ponging through tmp_k / tmp_v."""
        n = hi - lo
        n_runs = (n + INSERTION_RUN - 1) // INSERTION_RUN
        for r in range(n_runs):
            a = lo + r * INSERTION_RUN
            b = ti.min(a + INSERTION_RUN, hi)
            for i in range(a + 1, b):
                k, v = keys[i], vals[i]
                j = i - 1
                while j >= a and before(k, v, keys[j], vals[j]):
                    keys[j + 1] = keys[j]
                    vals[j + 1] = vals[j]
                    j -= 1
                keys[j + 1] = k
                vals[j + 1] = v
        width = INSERTION_RUN
        in_tmp = False
        while width < n:
            for r in range((n + 2 * width - 1) // (2 * width)):
                a = lo + r * 2 * width
                mid = ti.min(a + width, hi)
                b = ti.min(a + 2 * width, hi)
                if in_tmp:
                    merge(tmp_k, tmp_v, keys, vals, a, mid, b)
                else:
                    merge(keys, vals, tmp_k, tmp_v, a, mid, b)
            in_tmp = not in_tmp
            width *= 2
        if in_tmp:
            for i in range(lo, hi):
                keys[i] = tmp_k[i]
                vals[i] = tmp_v[i]

    return SimpleNamespace(sort_segment=sort_segment)
