"""The rasterizer's GPU structure (CUDA, Vulkan, Metal): block per tile, thread per pixel.

Same image formation, projection maths and outputs as the CPU path (:mod:`.splat`), different
loops:

forward
  1. project every Gaussian (one thread each); key = its depth's f32 bit pattern (monotone for
     depth > 0), value = its index; LSD radix sort of the N pairs (4 passes of 8 bits);
  2. per depth-sorted Gaussian, its tile count, then (same launch) an exclusive multi-level
     scan -> slot offsets (no atomics) and each Gaussian's slots' tile ids in depth order, in buffers
     of the Rasterizer's slot capacity C (the count S stays on the device; the C - S unused slots are
     keyed to the last tile, after its own; S > C: no slots, the view renders nothing); a stable
     radix sort by tile id (1-2 passes) of the C slots leaves every tile's slots front to back, ties
     broken by Gaussian index (the CPU order); tile ranges come from neighbouring keys; records are
     gathered tile-ordered; each scan and each whole radix sort is one kernel launch;
  3. blend: one 256-thread block per 16x16 tile, one thread per pixel, the tile's records loaded
     in batches of 256 into shared memory between ``block.sync()``s, per-pixel state in
     registers; the block stops once every pixel is saturated (a shared counter read between
     barriers, so the exit is uniform).
backward
  4. the same block layout replays each pixel back to front from its final transmittance and
     last contributor (batches from the back, starting at the tile's largest last index); each
     pixel's contribution to a record's 10 screen-space gradients is added atomically to that
     slot's row (Taichi 1.7's SPIR-V backend has no float atomics on shared memory, so there is
     no shared-memory pre-reduction yet: see docs/notebook/benchmarks-2026-11.md, "GPU kernels (block per tile)");
  5. per Gaussian (one thread each, depth order): sum of its slots' rows, projection backward,
     its pose term; the pose terms are summed by a multi-level block reduction (a launch per level)
     into the view's pose row, with S and whether S > C.
"""

import functools
import math
from types import SimpleNamespace

import taichi as ti

from . import project, rasterize, runtime, scan, tiles
from .project import (
    ALPHA_MIN, P_COLOR, P_CONIC_A, P_CONIC_B, P_CONIC_C, P_CUTOFF, P_DEPTH, P_MEAN_X, P_MEAN_Y, P_OPACITY, P_WIDTH,
)
from .rasterize import E_WIDTH, MAX_ALPHA, MIN_TRANSMITTANCE, N_SLOT_GRADS
from .tiles import TILE

PIXELS = TILE * TILE  # threads per block = pixels per tile = records per shared batch
DEPTH_KEY_BITS = 31  # f32 bit pattern of a positive depth; culled Gaussians get +inf's
INF_BITS = 0x7F800000
POSE_BLOCK = 256


@functools.cache
def make(dt) -> SimpleNamespace:
    """Kernels of the GPU path for float type ``dt``."""
    proj_f = project.make(dt)
    blend_f = rasterize.make(dt)
    mat4, vec4, vec3, fnd, ind, _ = runtime.kernel_types(dt)
    sync = ti.simt.block.sync
    scan_f = scan.funcs()

    @ti.kernel
    def project_keys(
        means: fnd(2),  # (N, 3)
        quats: fnd(2),  # (N, 4)
        log_scales: fnd(2),  # (N, 3), (N, 1) when isotropic
        logits: fnd(1),  # (N,)
        sh: fnd(3),  # (N, >= n_sh, 3)
        n: ti.i32,
        n_sh: ti.i32,
        cam: mat4,  # camera-to-world
        intr: vec4,  # fx, fy, cx, cy
        width: ti.i32,
        height: ti.i32,
        proj: fnd(2),  # output (N, P_WIDTH) screen records
        rect: ind(2),  # output (N, 4) pixel boxes
        depth_keys: ind(1),  # output (N,) f32 bits of the depth, INF_BITS when culled
        ids: ind(1),  # output (N,) 0 .. N-1
        isotropic: ti.template(),
        view_dependent: ti.template(),  # more than one SH coefficient
    ):
        for g in range(n):
            proj_f.project_one(
                g, means, quats, log_scales, logits, sh, n_sh, cam, intr, width, height, proj, rect, isotropic,
                view_dependent,
            )
            key = INF_BITS
            if rect[g, 0] <= rect[g, 2]:
                key = tiles.depth_bits(proj[g, P_DEPTH])
            depth_keys[g] = key
            ids[g] = g

    @ti.kernel
    def bin_slots(
        n: ti.i32,
        cap: ti.i32,  # C: slots the buffers hold (the view overflows, and renders nothing, when S > C)
        n_tiles: ti.i32,
        tiles_x: ti.i32,
        order: ind(1),  # (N,) Gaussian ids in depth order
        rect: ind(2),  # (N, 4)
        counts: ind(1),  # output (N,): tiles touched by order[i]
        offsets: ind(1),  # output (N + 1,): exclusive scan of counts, offsets[N] = the slot count S
        work: ind(1),  # (>= scan.scan_work_size(N),) scan levels
        tile_keys: ind(1),  # output (C,) tile id of each slot; past the S slots the last tile's (sorted after its own)
        slot_ids: ind(1),  # output (C,) 0 .. C-1
        slot_gid: ind(1),  # output (C,) Gaussian id of each slot
        levels: ti.template(),  # scan.scan_levels_for(N)
    ):
        """Slot offsets (each Gaussian's tile count, scanned), then each Gaussian's slots in depth order."""
        for i in range(n):
            counts[i] = tiles.tile_count(rect, order[i])
        scan_f.scan_levels(counts, 0, offsets, 0, work, 0, n, levels)
        for i in range(n):
            g = order[i]
            if offsets[n] <= cap and rect[g, 0] <= rect[g, 2]:
                b = tiles.tile_box(rect, g)
                s = offsets[i]
                for ty in range(b[1], b[3] + 1):
                    for tx in range(b[0], b[2] + 1):
                        tile_keys[s] = ty * tiles_x + tx
                        slot_ids[s] = s
                        slot_gid[s] = g
                        s += 1
        for s in range(cap):
            if s >= ti.select(offsets[n] <= cap, offsets[n], 0):
                tile_keys[s] = n_tiles - 1
                slot_ids[s] = s
                slot_gid[s] = 0

    @ti.kernel
    def ranges_and_gather(
        n_slots: ti.i32,  # C
        n_tiles: ti.i32,
        sorted_tiles: ind(1),  # (C,) tile ids, sorted
        order: ind(1),  # (C,) slot ids in the same order (those from S on are no slot: after their tile's slots)
        slot_gid: ind(1),  # (S,)
        proj: fnd(2),  # (N, P_WIDTH)
        rect: ind(2),  # (N, 4)
        tile_range: ind(2),  # output (T, 2): [start, end) of each tile's records, [0, 0) if none
        entries: fnd(2),  # output (S, E_WIDTH): records in tile order
        offsets: ind(1),  # (N + 1,) from bin_slots: S = offsets[N] (0 when it overflowed C)
        n: ti.i32,  # N
    ):
        for t, end in ti.ndrange(n_tiles, 2):
            tile_range[t, end] = 0
        for j in range(n_slots):
            live = ti.select(offsets[n] <= n_slots, offsets[n], 0)
            if order[j] < live:
                t = sorted_tiles[j]
                if j == 0 or sorted_tiles[j - 1] != t:
                    tile_range[t, 0] = j
                if j == n_slots - 1 or sorted_tiles[j + 1] != t or order[j + 1] >= live:
                    tile_range[t, 1] = j + 1
                blend_f.gather_entry(j, order, slot_gid, proj, rect, entries)

    @ti.func
    def pixel_of(t, tid, tiles_x):
        return (t % tiles_x) * TILE + tid % TILE, (t // tiles_x) * TILE + tid // TILE

    @ti.kernel
    def blend_forward(
        tiles_x: ti.i32,
        n_tiles: ti.i32,
        width: ti.i32,
        height: ti.i32,
        tile_range: ind(2),  # (T, 2)
        entries: fnd(2),  # (S, E_WIDTH)
        bg: vec3,
        out_rgb: fnd(3),  # output (H, W, 3)
        out_depth: fnd(2),  # output (H, W) blended depth (not normalised)
        out_trans: fnd(2),  # output (H, W) final transmittance
        out_last: ind(2),  # output (H, W) tile-local index of the last contributor, -1 for none
    ):
        ti.loop_config(block_dim=PIXELS)
        for i in range(n_tiles * PIXELS):
            t, tid = i // PIXELS, i % PIXELS
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            u, v = pixel_of(t, tid, tiles_x)
            inside = u < width and v < height
            batch = ti.simt.block.SharedArray((PIXELS, P_WIDTH), dt)
            n_done = ti.simt.block.SharedArray((1,), ti.i32)
            if tid == 0:
                n_done[0] = 0
            sync()
            done = not inside
            if done:
                ti.atomic_add(n_done[0], 1)
            start, end = tile_range[t, 0], tile_range[t, 1]
            trans = ti.cast(1.0, dt)
            rgb = vec3(0.0)
            depth = ti.cast(0.0, dt)
            last = -1
            for b in range((end - start + PIXELS - 1) // PIXELS):
                sync()  # n_done is final for the previous batch and nobody writes it before the next sync
                if n_done[0] == PIXELS:
                    break
                base = start + b * PIXELS
                if base + tid < end:
                    for c in ti.static(range(P_WIDTH)):
                        batch[tid, c] = entries[base + tid, c]
                sync()
                if not done:
                    for k in range(ti.min(PIXELS, end - base)):
                        dx = batch[k, P_MEAN_X] - (u + 0.5)
                        dy = batch[k, P_MEAN_Y] - (v + 0.5)
                        power = (-0.5 * (batch[k, P_CONIC_A] * dx * dx + batch[k, P_CONIC_C] * dy * dy)
                                 - batch[k, P_CONIC_B] * dx * dy)
                        if power >= batch[k, P_CUTOFF]:
                            alpha = ti.min(dt(MAX_ALPHA), batch[k, P_OPACITY] * ti.exp(power))
                            if alpha >= dt(ALPHA_MIN):
                                next_trans = trans * (1.0 - alpha)
                                if next_trans < dt(MIN_TRANSMITTANCE):
                                    done = True
                                    ti.atomic_add(n_done[0], 1)
                                    break
                                w = alpha * trans
                                for c in ti.static(range(3)):
                                    rgb[c] += w * batch[k, P_COLOR + c]
                                depth += w * batch[k, P_DEPTH]
                                trans = next_trans
                                last = b * PIXELS + k
            if inside:
                for c in ti.static(range(3)):
                    out_rgb[v, u, c] = rgb[c] + trans * bg[c]
                out_depth[v, u] = depth
                out_trans[v, u] = trans
                out_last[v, u] = last

    @ti.kernel
    def blend_backward(
        tiles_x: ti.i32,
        n_tiles: ti.i32,
        width: ti.i32,
        height: ti.i32,
        tile_range: ind(2),  # (T, 2)
        order: ind(1),  # (S,) slot id of each tile-ordered record
        entries: fnd(2),  # (S, E_WIDTH)
        bg: vec3,
        out_trans: fnd(2),  # (H, W) from blend_forward
        out_last: ind(2),  # (H, W) from blend_forward
        d_rgb: fnd(3),  # (H, W, 3) dL/d image
        d_depth: fnd(2),  # (H, W)
        d_alpha: fnd(2),  # (H, W)
        n_slots: ti.i32,
        slot_grad: fnd(2),  # output (S, N_SLOT_GRADS) dL/d(screen record) per slot
        subgroup: ti.template(),  # pre-sum over the subgroup before the atomics (Vulkan)
    ):
        for j, c in ti.ndrange(n_slots, N_SLOT_GRADS):
            slot_grad[j, c] = 0.0
        ti.loop_config(block_dim=PIXELS)
        for i in range(n_tiles * PIXELS):
            t, tid = i // PIXELS, i % PIXELS
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            u, v = pixel_of(t, tid, tiles_x)
            inside = u < width and v < height
            batch = ti.simt.block.SharedArray((PIXELS, P_WIDTH), dt)
            batch_slot = ti.simt.block.SharedArray((PIXELS,), ti.i32)
            max_last = ti.simt.block.SharedArray((1,), ti.i32)
            if tid == 0:
                max_last[0] = -1
            sync()
            final_trans = ti.cast(0.0, dt)
            last = -1
            g_rgb = vec3(0.0)
            g_depth = ti.cast(0.0, dt)
            g_alpha = ti.cast(0.0, dt)
            if inside:
                final_trans = out_trans[v, u]
                last = out_last[v, u]
                g_rgb = vec3(d_rgb[v, u, 0], d_rgb[v, u, 1], d_rgb[v, u, 2])
                g_depth = d_depth[v, u]
                g_alpha = d_alpha[v, u]
                ti.atomic_max(max_last[0], last)
            sync()
            count = max_last[0] + 1
            start = tile_range[t, 0]
            trans = final_trans
            behind = vec3(0.0)
            behind_depth = ti.cast(0.0, dt)
            for b in range((count + PIXELS - 1) // PIXELS):
                hi = count - b * PIXELS
                lo = ti.max(0, hi - PIXELS)
                if lo + tid < hi:
                    for c in ti.static(range(P_WIDTH)):
                        batch[tid, c] = entries[start + lo + tid, c]
                    batch_slot[tid] = order[start + lo + tid]
                sync()
                for k in range(hi - lo):
                    local = hi - 1 - k
                    r = local - lo
                    acc = ti.Vector.zero(dt, N_SLOT_GRADS)
                    hit = False
                    if local <= last:
                        dx = batch[r, P_MEAN_X] - (u + 0.5)
                        dy = batch[r, P_MEAN_Y] - (v + 0.5)
                        ca, cb, cc = batch[r, P_CONIC_A], batch[r, P_CONIC_B], batch[r, P_CONIC_C]
                        power = -0.5 * (ca * dx * dx + cc * dy * dy) - cb * dx * dy
                        if power >= batch[r, P_CUTOFF]:
                            opacity = batch[r, P_OPACITY]
                            gauss = ti.exp(power)
                            alpha = ti.min(dt(MAX_ALPHA), opacity * gauss)
                            if alpha >= dt(ALPHA_MIN):
                                hit = True
                                color = vec3(batch[r, P_COLOR], batch[r, P_COLOR + 1], batch[r, P_COLOR + 2])
                                depth = batch[r, P_DEPTH]
                                inv_keep = 1.0 / (1.0 - alpha)  # T_i = T_{i+1} / (1 - alpha_i)
                                trans = trans * inv_keep
                                w = alpha * trans
                                grad_alpha = (
                                    g_rgb.dot(color * trans - (behind + final_trans * bg) * inv_keep)
                                    + g_depth * (depth * trans - behind_depth * inv_keep)
                                    + g_alpha * final_trans * inv_keep
                                )
                                for c in ti.static(range(3)):
                                    acc[P_COLOR + c] = g_rgb[c] * w
                                acc[P_DEPTH] = g_depth * w
                                behind += color * w
                                behind_depth += depth * w
                                if opacity * gauss <= dt(MAX_ALPHA):
                                    acc[P_OPACITY] = grad_alpha * gauss
                                    g_power = grad_alpha * alpha
                                    acc[P_MEAN_X] = -g_power * (ca * dx + cb * dy)
                                    acc[P_MEAN_Y] = -g_power * (cb * dx + cc * dy)
                                    acc[P_CONIC_A] = -0.5 * g_power * dx * dx
                                    acc[P_CONIC_B] = -g_power * dx * dy
                                    acc[P_CONIC_C] = -0.5 * g_power * dy * dy
                    slot = batch_slot[r]
                    if ti.static(subgroup):
                        # sum over the subgroup's pixels first: one atomic per subgroup, not per pixel
                        if ti.simt.subgroup.reduce_max(ti.cast(hit, ti.i32)) > 0:  # any_true is a TODO in Taichi 1.7
                            for c in ti.static(range(N_SLOT_GRADS)):
                                acc[c] = ti.simt.subgroup.reduce_add(acc[c])
                            if ti.simt.subgroup.elect():
                                for c in ti.static(range(N_SLOT_GRADS)):
                                    ti.atomic_add(slot_grad[slot, c], acc[c])
                    elif hit:
                        for c in ti.static(range(N_SLOT_GRADS)):
                            ti.atomic_add(slot_grad[slot, c], acc[c])
                sync()  # the batch is read by everyone before the next one overwrites it

    @ti.kernel
    def gaussian_backward(
        n: ti.i32,
        n_sh: ti.i32,
        width: ti.i32,
        height: ti.i32,
        cam: mat4,
        intr: vec4,
        means: fnd(2),  # (N, 3)
        quats: fnd(2),  # (N, 4)
        log_scales: fnd(2),  # (N, 3) or (N, 1)
        logits: fnd(1),  # (N,)
        sh: fnd(3),  # (N, >= n_sh, 3)
        order: ind(1),  # (N,) depth order: Gaussian order[i] owns slots offsets[i] .. offsets[i + 1]
        offsets: ind(1),  # (N + 1,)
        cap: ti.i32,  # C, as the forward ran (an overflowed view has no slots: no gradients)
        slot_grad: fnd(2),  # (S, N_SLOT_GRADS)
        d_means: fnd(2),  # output (N, 3), added to
        d_quats: fnd(2),  # output (N, 4), added to
        d_log_scales: fnd(2),  # output (N, 3), added to
        d_logits: fnd(1),  # output (N,), added to
        d_sh: fnd(3),  # output (N, >= n_sh, 3), added to
        pose_part: fnd(2),  # output (N, 6): row i = the pose gradient of Gaussian order[i]
        isotropic: ti.template(),
        view_dependent: ti.template(),
    ):
        for i in range(n):
            pose = ti.Vector.zero(dt, 6)
            if offsets[n] <= cap:
                pose = proj_f.slots_vjp(
                    order[i], offsets[i], offsets[i + 1], slot_grad, means, quats, log_scales, logits, sh, n_sh,
                    cam, intr, width, height, isotropic, view_dependent, d_means, d_quats, d_log_scales, d_logits,
                    d_sh,
                )
            for c in ti.static(range(6)):
                pose_part[i, c] = pose[c]

    @ti.kernel
    def sum_rows(
        src: fnd(2),  # (n, 6)
        n: ti.i32,
        dst: fnd(2),  # output rows max(1, ceil(n / POSE_BLOCK)), 6 columns (not the last level)
        pose_out: fnd(1),  # the last level's output: a pose row (splat.POSE_COLUMNS values) from pose_at
        pose_at: ti.i32,
        offsets: ind(1),  # (N + 1,) slot offsets (last level: S = offsets[N] goes to the pose row's value 6)
        n_gaussians: ti.i32,  # N
        cap: ti.i32,  # C (last level: value 7 = 1 when S > C)
        last: ti.template(),  # the last level: one block, its sum the pose row
    ):
        """dst[b] = sum of src rows [b * POSE_BLOCK, (b + 1) * POSE_BLOCK) (6 columns), tree in shared memory (one
        row of zeros for n = 0); on the last level the one sum goes to the pose row instead."""
        ti.loop_config(block_dim=POSE_BLOCK)
        for i in range(ti.max(1, (n + POSE_BLOCK - 1) // POSE_BLOCK) * POSE_BLOCK):
            tid = i % POSE_BLOCK
            sync()  # a block may run several iterations (grid-stride): let the last one finish
            buf = ti.simt.block.SharedArray((POSE_BLOCK, 6), dt)
            for c in ti.static(range(6)):
                buf[tid, c] = 0.0
                if i < n:
                    buf[tid, c] = src[i, c]
            sync()
            for k in ti.static(range(int(math.log2(POSE_BLOCK)))):
                half = POSE_BLOCK >> (k + 1)
                if tid < half:
                    for c in ti.static(range(6)):
                        buf[tid, c] = buf[tid, c] + buf[tid + half, c]  # (+= would be an atomic)
                sync()
            if tid == 0:
                if ti.static(last):
                    for c in ti.static(range(6)):
                        pose_out[pose_at + c] = buf[0, c]
                    pose_out[pose_at + 6] = ti.cast(offsets[n_gaussians], dt)
                    pose_out[pose_at + 7] = ti.cast(offsets[n_gaussians] > cap, dt)
                else:
                    for c in ti.static(range(6)):
                        dst[i // POSE_BLOCK, c] = buf[0, c]

    return SimpleNamespace(
        project_keys=project_keys, bin_slots=bin_slots, ranges_and_gather=ranges_and_gather,
        blend_forward=blend_forward, blend_backward=blend_backward, gaussian_backward=gaussian_backward,
        sum_rows=sum_rows,
    )


class GpuPipeline:
    """Runs the GPU kernels for :class:`~taichi_gs.kernels.splat.Rasterizer` (one per dtype).
    Per-view buffers live in ``view.scratch`` so k views can be alive at once."""

    def __init__(self, dtype) -> None:
        self.dtype = dtype
        self.k = make(dtype)
        self.scratch = scan.Scratch()  # backward buffers, shared by all views
        # Vulkan: pre-sum gradients over each subgroup (Taichi exposes subgroup ops there only)
        self.subgroup = runtime.current().arch == "vulkan"

    def forward(self, view, gaussians, cam, intr, width: int, height: int, bg, clock, cap: int) -> None:
        """Fill ``view``'s images and what its backward replays, in buffers of ``cap`` slots; the slot count
        stays on the device."""
        s = view.scratch
        n = gaussians.n
        p = gaussians.params
        view.proj = s.get("proj", n, self.dtype, (P_WIDTH,))
        view.rect = s.get("rect", n, ti.i32, (4,))
        keys, ids = s.get("depth_keys", n), s.get("ids", n)
        self.k.project_keys(
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"], n, gaussians.n_sh,
            cam, intr, width, height, view.proj, view.rect, keys, ids, gaussians.isotropic, gaussians.view_dependent,
        )
        _, view.depth_order = scan.radix_sort(keys, ids, n, DEPTH_KEY_BITS, s, "depth_sort")
        clock("project")
        view.depth_offsets = s.get("offsets", n + 1)
        tiles_x, tiles_y = tiles.tile_grid(width, height)
        n_tiles = tiles_x * tiles_y
        tile_keys, slot_ids, view.slot_gid = s.get("tile_keys", cap), s.get("slot_ids", cap), s.get("slot_gid", cap)
        self.k.bin_slots(n, cap, n_tiles, tiles_x, view.depth_order, view.rect, s.get("counts", n), view.depth_offsets,
                         s.get("scan_work", scan.scan_work_size(n)), tile_keys, slot_ids, view.slot_gid,
                         scan.scan_levels_for(n))
        tile_bits = max(1, int(n_tiles - 1).bit_length())
        sorted_tiles, view.order = scan.radix_sort(tile_keys, slot_ids, cap, tile_bits, s, "tile_sort")
        view.tile_range = s.get("tile_range", n_tiles, ti.i32, (2,))
        view.entries = s.get("entries", cap, self.dtype, (E_WIDTH,))
        self.k.ranges_and_gather(cap, n_tiles, sorted_tiles, view.order, view.slot_gid, view.proj, view.rect,
                                 view.tile_range, view.entries, view.depth_offsets, n)
        clock("sort")
        self.k.blend_forward(tiles_x, n_tiles, width, height, view.tile_range, view.entries, bg,
                             view.rgb, view.depth, view.transmittance, view.last)
        clock("blend")

    def backward(self, view, gaussians, cam, intr, bg, d_rgb, d_depth, d_alpha, pose_out, pose_at: int) -> None:
        """Add parameter gradients into ``gaussians.grads``; the pose gradient, the slot count and whether it
        overflowed go to ``pose_out`` from ``pose_at`` (splat.POSE_COLUMNS values)."""
        width, height = view.size
        n = gaussians.n
        s = self.scratch
        slot_grad = s.get("slot_grad", view.cap, self.dtype, (N_SLOT_GRADS,))
        tiles_x, tiles_y = tiles.tile_grid(width, height)
        n_tiles = tiles_x * tiles_y
        self.k.blend_backward(tiles_x, n_tiles, width, height, view.tile_range, view.order, view.entries, bg,
                              view.transmittance, view.last, d_rgb, d_depth, d_alpha, view.cap, slot_grad,
                              self.subgroup)
        p, g = gaussians.params, gaussians.grads
        rows = s.get("pose_rows0", n, self.dtype, (6,))
        self.k.gaussian_backward(
            n, gaussians.n_sh, width, height, cam, intr,
            p["means"], p["quats"], p["log_scales"], p["opacity_logits"], p["colors"],
            view.depth_order, view.depth_offsets, view.cap, slot_grad,
            g["means"], g["quats"], g["log_scales"], g["opacity_logits"], g["colors"], rows, gaussians.isotropic,
            gaussians.view_dependent,
        )
        level, count = 0, n
        while True:  # one launch per level of 256-row block sums (2 up to 65,536 Gaussians)
            n_out = max(1, -(-count // POSE_BLOCK))
            last = n_out == 1
            out = s.get("pose_rows_last" if last else f"pose_rows{level + 1}", n_out, self.dtype, (6,))
            self.k.sum_rows(rows, count, out, pose_out, pose_at, view.depth_offsets, n, view.cap, last)
            if last:
                return
            rows, count, level = out, n_out, level + 1
