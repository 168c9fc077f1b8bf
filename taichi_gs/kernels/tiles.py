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
INSERTION_MAX = 32  # segments up to this long are insertion-sorted
RADIX_BITS = 8  # the digit of a radix sort pass
RADIX = 1 << RADIX_BITS


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
def insertion_sort(keys: Array, lo, hi):
    """Sort keys[lo:hi] in place by insertion."""
    for i in range(lo + 1, hi):
        k = keys[i]
        j = i - 1
        while j >= lo and k < keys[j]:
            keys[j + 1] = keys[j]
            j -= 1
        keys[j + 1] = k


@ti.func
def sort_segment(keys: Array, tmp: Array, lo, hi):
    """Sort keys[lo:hi], distinct :func:`depth_slot_key` keys whose slots increase from lo to hi (as the counting
    pass places a tile's), into integer order: a stable LSD radix sort of the 32 depth bits alone (RADIX_BITS a
    pass, ping-ponging through tmp; a pass whose digit all keys share is skipped), so equal depths keep their slot
    order; short segments by insertion."""
    if hi - lo <= INSERTION_MAX:
        insertion_sort(keys, lo, hi)
    else:
        in_tmp = False
        for p in ti.static(range(32 // RADIX_BITS)):  # the depth bits above the slot's
            shift = SLOT_BITS + p * RADIX_BITS
            count = ti.Vector.zero(ti.i32, RADIX)
            for i in range(lo, hi):
                key = tmp[i] if in_tmp else keys[i]
                count[ti.cast(key >> shift, ti.i32) & (RADIX - 1)] += 1
            first_digit = ti.cast((tmp[lo] if in_tmp else keys[lo]) >> shift, ti.i32) & (RADIX - 1)
            if count[first_digit] < hi - lo:
                running = lo
                for d in range(RADIX):
                    c = count[d]
                    count[d] = running
                    running += c
                for i in range(lo, hi):
                    key = tmp[i] if in_tmp else keys[i]
                    d = ti.cast(key >> shift, ti.i32) & (RADIX - 1)
                    if in_tmp:
                        keys[count[d]] = key
                    else:
                        tmp[count[d]] = key
                    count[d] += 1
                in_tmp = not in_tmp
        if in_tmp:
            for i in range(lo, hi):
                keys[i] = tmp[i]
