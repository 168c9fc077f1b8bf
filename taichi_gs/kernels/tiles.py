"""Tile binning: which 16x16 tiles each Gaussian touches, and each tile's list sorted by depth.

Layout of the intersection ("slot") arrays:
- slots are Gaussian-major: Gaussian g owns slots ``offsets[g] .. offsets[g + 1]`` (one per tile it
  touches); ``slot_gid[s]`` and ``slot_tile[s]`` say whose slot it is and for which tile;
- the tile-major list ``order`` holds slot ids grouped by tile (tile t owns
  ``tile_start[t] .. tile_start[t + 1]``), each group sorted front to back by (depth, slot).
The backward pass writes per-slot gradients, so a Gaussian's gradient is a contiguous segmented
sum without atomics.
"""

import taichi as ti

Array = ti.template()  # an ndarray argument of a ti.func (passed by reference)

TILE = 16
INSERTION_RUN = 16


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """(tiles_x, tiles_y): the TILE x TILE tiles that cover a width x height image."""
    return -(-width // TILE), -(-height // TILE)


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


SLOT_BITS = 32  # a sort key's low bits: the slot id; the high bits: the float32 depth's bit pattern


@ti.func
def depth_bits(depth):
    """The bit pattern of ``depth`` as a float32: positive floats order as these integers do (both paths'
    depth sort keys)."""
    return ti.bit_cast(ti.cast(depth, ti.f32), ti.i32)


@ti.func
def depth_slot_key(depth, slot):
    """A slot's 64-bit sort key: its :func:`depth_bits` above its slot id, so sorting the keys as integers
    sorts by (float32 depth, slot)."""
    return (ti.cast(depth_bits(depth), ti.i64) << SLOT_BITS) | ti.cast(slot, ti.i64)


@ti.func
def run_bounds(run, runs, n):
    """(first, end) of run ``run`` of ``runs`` consecutive runs that split 0..n."""
    length = (n + runs - 1) // runs
    return run * length, ti.min(n, (run + 1) * length)


@ti.func
def key_slot(key):
    """The slot id of a :func:`depth_slot_key`."""
    return ti.cast(key & ti.i64((1 << SLOT_BITS) - 1), ti.i32)


@ti.func
def merge(src: Array, dst: Array, lo, mid, hi):
    """Merge the sorted runs src[lo:mid] and src[mid:hi] into dst[lo:hi]."""
    i, j = lo, mid
    for out in range(lo, hi):
        if j >= hi or (i < mid and src[i] <= src[j]):
            dst[out] = src[i]
            i += 1
        else:
            dst[out] = src[j]
            j += 1


@ti.func
def sort_segment(keys: Array, tmp: Array, lo, hi):
    """Sort keys[lo:hi] (distinct integers): insertion-sorted runs, then bottom-up merges ping-ponging
    through tmp."""
    n = hi - lo
    n_runs = (n + INSERTION_RUN - 1) // INSERTION_RUN
    for r in range(n_runs):
        a = lo + r * INSERTION_RUN
        b = ti.min(a + INSERTION_RUN, hi)
        for i in range(a + 1, b):
            k = keys[i]
            j = i - 1
            while j >= a and k < keys[j]:
                keys[j + 1] = keys[j]
                j -= 1
            keys[j + 1] = k
    width = INSERTION_RUN
    in_tmp = False
    while width < n:
        for r in range((n + 2 * width - 1) // (2 * width)):
            a = lo + r * 2 * width
            mid = ti.min(a + width, hi)
            b = ti.min(a + 2 * width, hi)
            if in_tmp:
                merge(tmp, keys, a, mid, b)
            else:
                merge(keys, tmp, a, mid, b)
        in_tmp = not in_tmp
        width *= 2
    if in_tmp:
        for i in range(lo, hi):
            keys[i] = tmp[i]
