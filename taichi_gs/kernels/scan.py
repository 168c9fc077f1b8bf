"""GPU primitives on i32 ndarrays: exclusive prefix sums and a stable LSD radix sort of (key, value)
pairs, each one kernel launch. Block-structured (256 threads, shared memory, ``block.sync``), so they
compile on CUDA, Vulkan and Metal only, never on Taichi's CPU backend.

- scan: each block scans 256 elements in shared memory (Hillis-Steele, 8 steps) and writes its
  total; the totals are scanned the same way, as many levels deep as the size needs (:func:`scan_levels_for`:
  1 level up to 255 elements, 2 up to 65,279, at most 4 for any i32 count; a compile-time count), and
  added back level by level. Every level is a top-level loop of one kernel, so the levels cost the
  runtime's task launches (GPU dispatches), not Python's kernel calls (~50 us and ~10 us per ndarray each).
- radix sort, 8-bit digits, one pass per digit: per-block digit histograms (shared-memory atomics)
  written digit-major, one exclusive scan of that table gives every (digit, block) its output base,
  then each block scatters its elements in index order, ranking equal digits among the 256
  elements of a round by counting them in shared memory (stable, no global atomics). All passes
  run in one kernel, ping-ponging between the input and a scratch pair.
Buffers live in a :class:`Scratch`.
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


def scan_levels_for(n: int) -> int:
    """Levels of block scans an n-element scan needs: each level scans the block totals of the one below
    until a single block (n + 1 outputs) holds them."""
    levels = 1
    while n >= BLOCK:
        n = n // BLOCK + 1
        levels += 1
    return levels


def scan_work_size(n: int) -> int:
    """Elements of scan work space :func:`scan_levels` needs for an n-element scan."""
    size = 0
    for _ in range(scan_levels_for(n)):
        n = n // BLOCK + 1  # the level's block totals, then their n + 1 scanned values
        size += 2 * n + 1
    return size


def digit_table_size(n: int) -> int:
    """Entries of the radix sort's digit table for n pairs (one per digit per block of CHUNK pairs)."""
    return RADIX * max(1, -(-n // CHUNK))


def radix_work_size(n: int) -> int:
    """Elements of work space the radix sort of n pairs needs: digit table, its scan, scan levels."""
    table = digit_table_size(n)
    return 2 * table + 1 + scan_work_size(table)


@functools.cache
def funcs() -> SimpleNamespace:
    """The scan as a ``ti.func`` (``scan_levels``) for kernels that fuse it with their own loops."""
    sync = ti.simt.block.sync

    @ti.func
    def block_scan(src: ti.template(), src_at, dst: ti.template(), dst_at, sums: ti.template(), sums_at, n):
        """dst[i] = sum of src[block start .. i) for i <= n (src[n] counts as 0); sums[b] = block total."""
        n_blocks = (n + BLOCK) // BLOCK
        ti.loop_config(block_dim=BLOCK)
        for i in range(n_blocks * BLOCK):
            tid = i % BLOCK
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            buf = ti.simt.block.SharedArray((2 * BLOCK,), ti.i32)
            x = 0
            if i < n:
                x = src[src_at + i]
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
                dst[dst_at + i] = inclusive - x
            if tid == BLOCK - 1:
                sums[sums_at + i // BLOCK] = inclusive

    @ti.func
    def add_block_offsets(dst: ti.template(), dst_at, offsets: ti.template(), offsets_at, n):
        """dst[i] += offsets[i // BLOCK] for i <= n: block-local scans made global."""
        for i in range(n + 1):
            dst[dst_at + i] = dst[dst_at + i] + offsets[offsets_at + i // BLOCK]

    @ti.func
    def scan_levels(src: ti.template(), src_at, dst: ti.template(), dst_at, work: ti.template(), work_at, n,
                    levels: ti.template()):
        """dst[dst_at + i] = sum of src[src_at .. src_at + i) for i <= n, through ``work`` (at least
        scan_work_size(n) elements from work_at), in ``levels`` = scan_levels_for(n) levels (or more). Level l
        keeps its block totals, then their scan."""
        sizes = ti.Vector([0] * levels)  # elements scanned at each level
        totals = ti.Vector([0] * levels)  # where each level's block totals start in work
        scanned = ti.Vector([0] * levels)  # where their scan starts (level l scans totals[l - 1])
        at, m = work_at, n
        for level in ti.static(range(levels)):
            sizes[level] = m
            m = m // BLOCK + 1
            totals[level] = at
            scanned[level] = at + m
            at += 2 * m + 1
        block_scan(src, src_at, dst, dst_at, work, totals[0], n)
        for level in ti.static(range(1, levels)):
            block_scan(work, totals[level - 1], work, scanned[level - 1], work, totals[level], sizes[level])
        for level in ti.static(range(levels - 2, 0, -1)):
            add_block_offsets(work, scanned[level - 1], work, scanned[level], sizes[level])
        if ti.static(levels > 1):  # one level: its single block is the whole scan
            add_block_offsets(dst, dst_at, work, scanned[0], n)

    @ti.func
    def digit_histogram(keys: ti.template(), n, shift, n_blocks, table: ti.template(), table_at):
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
            table[table_at + tid * n_blocks + b] = hist[tid]

    @ti.func
    def scatter(keys: ti.template(), vals: ti.template(), n, shift, n_blocks, base: ti.template(), base_at,
                out_keys: ti.template(), out_vals: ti.template()):
        """Stable scatter of block b's pairs to base[d * n_blocks + b] + rank among equal digits."""
        ti.loop_config(block_dim=BLOCK)
        for i in range(n_blocks * BLOCK):
            tid = i % BLOCK
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            b = i // BLOCK
            digits = ti.simt.block.SharedArray((BLOCK,), ti.i32)
            running = ti.simt.block.SharedArray((RADIX,), ti.i32)
            round_count = ti.simt.block.SharedArray((RADIX,), ti.i32)
            running[tid] = base[base_at + tid * n_blocks + b]
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

    @ti.func
    def radix_pass(keys: ti.template(), vals: ti.template(), out_keys: ti.template(), out_vals: ti.template(), n,
                   shift, work: ti.template(), levels: ti.template()):
        n_blocks = ti.max(1, (n + CHUNK - 1) // CHUNK)
        table = RADIX * n_blocks
        digit_histogram(keys, n, shift, n_blocks, work, 0)
        scan_levels(work, 0, work, table, work, 2 * table + 1, table, levels)
        scatter(keys, vals, n, shift, n_blocks, work, table, out_keys, out_vals)

    return SimpleNamespace(scan_levels=scan_levels, radix_pass=radix_pass)


@functools.cache
def _kernels() -> SimpleNamespace:
    f = funcs()

    @ti.kernel
    def exclusive_scan_kernel(src: _ind, dst: _ind, work: _ind, n: ti.i32, levels: ti.template()):
        f.scan_levels(src, 0, dst, 0, work, 0, n, levels)

    @ti.kernel
    def radix_sort_kernel(
        keys: _ind, vals: _ind,  # (>= n,) the pairs; the result after an even number of passes
        other_keys: _ind, other_vals: _ind,  # (>= n,) scratch; the result after an odd number
        work: _ind,  # (>= radix_work_size(n),)
        n: ti.i32,
        passes: ti.template(),
        levels: ti.template(),  # scan levels of the digit table (scan_levels_for)
    ):
        for p in ti.static(range(passes)):
            if ti.static(p % 2 == 0):
                f.radix_pass(keys, vals, other_keys, other_vals, n, p * DIGIT_BITS, work, levels)
            else:
                f.radix_pass(other_keys, other_vals, keys, vals, n, p * DIGIT_BITS, work, levels)

    return SimpleNamespace(exclusive_scan=exclusive_scan_kernel, radix_sort=radix_sort_kernel)


def exclusive_scan(src: ti.Ndarray, dst: ti.Ndarray, n: int, scratch: Scratch) -> None:
    """dst[0..n] = exclusive prefix sums of src[0..n), dst[n] = the total (dst holds n + 1)."""
    _kernels().exclusive_scan(src, dst, scratch.get("scan_work", scan_work_size(n)), n, scan_levels_for(n))


def radix_sort(keys: ti.Ndarray, vals: ti.Ndarray, n: int, bits: int, scratch: Scratch,
               name: str = "sort") -> tuple[ti.Ndarray, ti.Ndarray]:
    """Stable sort of the first n (key, value) pairs by the low ``bits`` bits of the (non-negative)
    keys. Returns the arrays that hold the result: (keys, vals) or the scratch pair."""
    passes = -(-bits // DIGIT_BITS)
    other = (scratch.get(f"{name}_keys", n), scratch.get(f"{name}_vals", n))
    _kernels().radix_sort(keys, vals, *other, scratch.get(f"{name}_work", radix_work_size(n)), n, passes,
                          scan_levels_for(digit_table_size(n)))
    return (keys, vals) if passes % 2 == 0 else other
