"""GPU primitives on i32 ndarrays: multi-level exclusive prefix sums, a stable LSD radix sort of
(key, value) pairs, and a multi-level row sum. Block-structured (256 threads, shared memory,
``block.sync``), so they compile on CUDA, Vulkan and Metal only, never on Taichi's CPU backend.

- scan: each block scans 256 elements in shared memory (Hillis-Steele, 8 steps) and writes its
  total; the totals are scanned the same way (recursively) and added back.
- radix sort, 8-bit digits, one pass per digit: per-block digit histograms (shared-memory atomics)
  written digit-major, one exclusive scan of that table gives every (digit, block) its output base,
  then each block scatters its elements in index order, ranking equal digits among the 256
  elements of a round by counting them in shared memory (stable, no global atomics).
Python drives the levels and passes (a few launches each); buffers live in a :class:`Scratch`.
"""


import functools
import math
from types import SimpleNamespace

import taichi as ti

from . import runtime

BLOCK = 256
LOG_BLOCK = 8
ITEMS = 4  # elements per thread in the radix passes
CHUNK = BLOCK * ITEMS
DIGIT_BITS = 8
RADIX = 1 << DIGIT_BITS

_ind = ti.types.ndarray(dtype=ti.i32, ndim=1)


class Scratch:
    """Named device buffers, grown geometrically and reused between calls."""

    def __init__(self) -> None:
        self.buffers: dict[str, ti.Ndarray] = {}

    def get(self, name: str, rows: int, dtype=ti.i32, tail: tuple = ()) -> "ti.Ndarray":
        buf = self.buffers.get(name)
        if buf is None or buf.shape[0] < rows or tuple(buf.shape[1:]) != tail or buf.dtype != dtype:
            row_bytes = math.prod(tail) * (8 if dtype in (ti.f64, ti.i64) else 4)
            runtime.check_buffer(rows * row_bytes, f"{name} ({rows} x {tail or 1})")
            limit = runtime.current().max_buffer_bytes if runtime.current() else 0
            size = max(int(rows * 1.25), 16)
            if limit:
                size = max(rows, min(size, limit // row_bytes))
            buf = ti.ndarray(dtype, (size,) + tail)
            self.buffers[name] = buf
        return buf


@functools.cache
def _kernels() -> SimpleNamespace:
    sync = ti.simt.block.sync

    @ti.kernel
    def block_scan(
        src: _ind,  # (>= n,)
        dst: _ind,  # output (n + 1,)
        sums: _ind,  # output (n // BLOCK + 1,) block totals
        n: ti.i32,
    ):
        """dst[i] = sum of src[block start .. i) for i <= n (src[n] counts as 0); sums[b] = block total."""
        n_blocks = (n + BLOCK) // BLOCK
        ti.loop_config(block_dim=BLOCK)
        for i in range(n_blocks * BLOCK):
            tid = i % BLOCK
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            buf = ti.simt.block.SharedArray((2 * BLOCK,), ti.i32)
            x = 0
            if i < n:
                x = src[i]
            buf[tid] = x
            sync()
            for k in ti.static(range(LOG_BLOCK)):
                v = buf[(k % 2) * BLOCK + tid]
                if tid >= (1 << k):
                    v += buf[(k % 2) * BLOCK + tid - (1 << k)]
                buf[((k + 1) % 2) * BLOCK + tid] = v
                sync()
            inclusive = buf[(LOG_BLOCK % 2) * BLOCK + tid]
            if i <= n:
                dst[i] = inclusive - x
            if tid == BLOCK - 1:
                sums[i // BLOCK] = inclusive

    @ti.kernel
    def add_block_offsets(
        dst: _ind,  # (n + 1,) block-local scans, made global in place (output)
        offsets: _ind,  # (n // BLOCK + 1,) exclusive scan of the block totals
        n: ti.i32,
    ):
        for i in range(n + 1):
            dst[i] = dst[i] + offsets[i // BLOCK]

    @ti.kernel
    def digit_histogram(
        keys: _ind,  # (>= n,)
        n: ti.i32,
        shift: ti.i32,  # the digit's lowest bit
        n_blocks: ti.i32,  # ceil(n / CHUNK)
        table: _ind,  # output (RADIX * n_blocks,), digit-major
    ):
        """table[d * n_blocks + b] = how many keys of block b have digit d at ``shift``."""
        ti.loop_config(block_dim=BLOCK)
        for i in range(n_blocks * BLOCK):
            tid = i % BLOCK
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            b = i // BLOCK
            hist = ti.simt.block.SharedArray((RADIX,), ti.i32)
            hist[tid] = 0
            sync()
            for k in range(ITEMS):
                e = b * CHUNK + k * BLOCK + tid
                if e < n:
                    ti.atomic_add(hist[(keys[e] >> shift) & (RADIX - 1)], 1)
            sync()
            table[tid * n_blocks + b] = hist[tid]

    @ti.kernel
    def scatter(
        keys: _ind,  # (>= n,)
        vals: _ind,  # (>= n,)
        n: ti.i32,
        shift: ti.i32,
        n_blocks: ti.i32,
        base: _ind,  # (RADIX * n_blocks + 1,) exclusive scan of digit_histogram's table
        out_keys: _ind,  # output (>= n,)
        out_vals: _ind,  # output (>= n,)
    ):
        """Stable scatter of block b's pairs to base[d * n_blocks + b] + rank among equal digits."""
        ti.loop_config(block_dim=BLOCK)
        for i in range(n_blocks * BLOCK):
            tid = i % BLOCK
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            b = i // BLOCK
            digits = ti.simt.block.SharedArray((BLOCK,), ti.i32)
            running = ti.simt.block.SharedArray((RADIX,), ti.i32)
            round_count = ti.simt.block.SharedArray((RADIX,), ti.i32)
            running[tid] = base[tid * n_blocks + b]
            round_count[tid] = 0
            for k in range(ITEMS):
                e = b * CHUNK + k * BLOCK + tid
                d, key, val = -1, 0, 0
                if e < n:
                    key, val = keys[e], vals[e]
                    d = (key >> shift) & (RADIX - 1)
                digits[tid] = d
                sync()
                if d >= 0:
                    rank = 0
                    for other in range(tid):
                        if digits[other] == d:
                            rank += 1
                    pos = running[d] + rank
                    out_keys[pos] = key
                    out_vals[pos] = val
                    ti.atomic_add(round_count[d], 1)
                sync()
                running[tid] = running[tid] + round_count[tid]
                round_count[tid] = 0
                sync()

    return SimpleNamespace(block_scan=block_scan, add_block_offsets=add_block_offsets,
                           digit_histogram=digit_histogram, scatter=scatter)


def exclusive_scan(src: ti.Ndarray, dst: ti.Ndarray, n: int, scratch: Scratch, level: int = 0) -> None:
    """dst[0..n] = exclusive prefix sums of src[0..n), dst[n] = the total (dst holds n + 1)."""
    k = _kernels()
    n_blocks = n // BLOCK + 1
    sums = scratch.get(f"scan_sums{level}", n_blocks)
    k.block_scan(src, dst, sums, n)
    if n_blocks > 1:
        offsets = scratch.get(f"scan_offsets{level}", n_blocks + 1)
        exclusive_scan(sums, offsets, n_blocks, scratch, level + 1)
        k.add_block_offsets(dst, offsets, n)


def radix_sort(keys: ti.Ndarray, vals: ti.Ndarray, n: int, bits: int, scratch: Scratch,
               name: str = "sort") -> tuple[ti.Ndarray, ti.Ndarray]:
    """Stable sort of the first n (key, value) pairs by the low ``bits`` bits of the (non-negative)
    keys. Returns the arrays that hold the result: (keys, vals) or the scratch pair."""
    k = _kernels()
    n_blocks = max(1, -(-n // CHUNK))
    other = (scratch.get(f"{name}_keys", n), scratch.get(f"{name}_vals", n))
    table = scratch.get(f"{name}_table", RADIX * n_blocks)
    base = scratch.get(f"{name}_base", RADIX * n_blocks + 1)
    src = (keys, vals)
    for shift in range(0, bits, DIGIT_BITS):
        dst = other if src[0] is keys else (keys, vals)
        k.digit_histogram(src[0], n, shift, n_blocks, table)
        exclusive_scan(table, base, RADIX * n_blocks, scratch)
        k.scatter(src[0], src[1], n, shift, n_blocks, base, dst[0], dst[1])
        src = dst
    return src
