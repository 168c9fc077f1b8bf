"""The CPU path's fused render and backward kernels (one thread per tile; no shared memory, no block sync).

:func:`cpu_kernels` builds, per float type: ``project_and_count`` (projection and per-Gaussian slot offsets),
``bin_and_sort`` (slot emission, counting sort into tiles, per-tile depth sort, gather of tile-ordered records),
``blend`` (front-to-back compositing) and ``backward`` (tile replay, per-Gaussian reduction and projection
backward, pose sum into a pose row). :class:`~taichi_gs.kernels.splat.Rasterizer` launches them; on GPU
backends it uses :mod:`~taichi_gs.kernels.raster_gpu` instead.
"""

import functools
from types import SimpleNamespace

import taichi as ti

from . import project, rasterize, runtime, tiles

POSE_CHUNK = 1024
POSE_COLUMNS = 8  # a pose row: the 6-vector pose gradient, the view's slot count S, 1 when S > C (overflowed)
SCAN_CHUNK = 128
COUNT_RUNS = 16  # runs of slots that the sort's counting pass splits into (fixed: the same result on any machine)


@functools.cache
def cpu_kernels(dt) -> SimpleNamespace:
    """The CPU path's four fused kernels for float type ``dt``: ``project_and_count``, ``bin_and_sort``,
    ``blend`` and ``backward`` (one thread per tile; see the module docstring)."""
    proj_f = project.make(dt)
    blend_f = rasterize.make(dt)
    mat4, vec4, vec3, fnd, ind, kind = runtime.kernel_types(dt)
    spread = runtime.loop_spread()  # per-tile loops: n_tiles x spread indices (see loop_spread)

    # Shapes: N Gaussians, M SH coefficients, S tile slots (one per Gaussian per tile it touches),
    # T tiles, H x W pixels. "out" marks what a kernel writes; "scratch" what it uses and leaves.
    @ti.kernel
    def project_and_count(
        means: fnd(2),  # (N, 3)
        quats: fnd(2),  # (N, 4) w x y z; (1, 4) placeholder when isotropic
        log_scales: fnd(2),  # (N, 3); (N, 1) when isotropic
        logits: fnd(1),  # (N,) opacity logits
        sh: fnd(3),  # (N, M, 3)
        n: ti.i32,  # N
        n_sh: ti.i32,  # M
        cam: mat4,  # camera-to-world
        intr: vec4,  # fx, fy, cx, cy (rasterizer pixel centres)
        width: ti.i32,
        height: ti.i32,
        proj: fnd(2),  # out (N, P_WIDTH): screen-space record per Gaussian (project.P_* columns)
        rect: ind(2),  # out (N, 4): tile rectangle x0, y0, x1, y1 (empty when culled)
        offsets: ind(1),  # out (N + 1,): exclusive prefix sum of tiles touched; offsets[N] = S
        chunk_base: ind(1),  # scratch (N / SCAN_CHUNK + 2,)
        isotropic: ti.template(),
        view_dependent: ti.template(),  # M > 1
    ):
        for g in range(n):
            proj_f.project_one(
                g, means, quats, log_scales, logits, sh, n_sh, cam, intr, width, height, proj, rect, isotropic,
                view_dependent,
            )
        # exclusive prefix sum of the tile counts, in chunks: chunk sums, a short serial scan over
        # chunks, then each chunk's own scan (parallel on CPU and GPU alike)
        n_chunks = (n + SCAN_CHUNK - 1) // SCAN_CHUNK
        for c in range(n_chunks):
            total = 0
            for g in range(c * SCAN_CHUNK, ti.min(n, (c + 1) * SCAN_CHUNK)):
                total += tiles.tile_count(rect, g)
            chunk_base[c] = total
        ti.loop_config(serialize=True)
        for _ in range(1):
            running = 0
            for c in range(n_chunks):
                count = chunk_base[c]
                chunk_base[c] = running
                running += count
            offsets[n] = running
        for c in range(n_chunks):
            running = chunk_base[c]
            for g in range(c * SCAN_CHUNK, ti.min(n, (c + 1) * SCAN_CHUNK)):
                offsets[g] = running
                running += tiles.tile_count(rect, g)

    @ti.func
    def live_slots(offsets: ti.template(), n, cap):
        """The slot count S when it fits the ``cap`` slots of the buffers, else 0 (the view renders nothing)."""
        return ti.select(offsets[n] <= cap, offsets[n], 0)

    @ti.kernel
    def bin_and_sort(
        n: ti.i32,  # N
        cap: ti.i32,  # C: slots the buffers below hold (the view overflows when S > C)
        tiles_x: ti.i32,  # tiles per image row
        n_tiles: ti.i32,  # T
        proj: fnd(2),  # (N, P_WIDTH) from project_and_count
        rect: ind(2),  # (N, 4)
        offsets: ind(1),  # (N + 1,)
        slot_gid: ind(1),  # out (S,): the Gaussian of each slot
        slot_tile: ind(1),  # out (S,): the tile of each slot
        tile_cursor: ind(2),  # scratch (COUNT_RUNS, T)
        tile_start: ind(1),  # out (T + 1,): first sorted slot of each tile; tile_start[T] = S
        keys: kind(1),  # scratch (S,): (depth, slot) keys (tiles.depth_slot_key), sorted within each tile
        tmp_keys: kind(1),  # scratch (S,)
        order: ind(1),  # out (S,): slot index at each sorted position
        entries: fnd(2),  # out (S, E_WIDTH): the sorted slots' screen records and tile boxes
    ):
        for g in range(n):
            if offsets[n] <= cap:
                tiles.emit_slots(g, rect, offsets, slot_gid, slot_tile, tiles_x)
        # stable counting sort of the slots by tile: each of COUNT_RUNS runs of slots counts its tiles in its own
        # row of tile_cursor (no atomics: two threads' atomic counters on a few hundred tiles cost more than the
        # whole pass; docs/notebook/benchmarks-2026-11.md, "The render's sort without atomics"), one thread turns the
        # counts into each run's first position per tile, then the runs place their slots' (depth, slot) keys side
        # by side, in slot order within each tile; each tile's keys are then sorted as integers (a radix sort of their
        # depth bits that keeps that order between equal depths: tiles.sort_segment)
        for i in range(COUNT_RUNS * spread):
            if i % spread == 0:
                c = i // spread
                for t in range(n_tiles):
                    tile_cursor[c, t] = 0
                first, end = tiles.run_bounds(c, COUNT_RUNS, live_slots(offsets, n, cap))
                for s in range(first, end):
                    t = slot_tile[s]
                    tile_cursor[c, t] = tile_cursor[c, t] + 1
        ti.loop_config(serialize=True)
        for _ in range(1):
            running = 0
            for t in range(n_tiles):
                tile_start[t] = running
                for c in range(COUNT_RUNS):
                    count = tile_cursor[c, t]
                    tile_cursor[c, t] = running
                    running += count
            tile_start[n_tiles] = running
        for i in range(COUNT_RUNS * spread):
            if i % spread == 0:
                c = i // spread
                first, end = tiles.run_bounds(c, COUNT_RUNS, live_slots(offsets, n, cap))
                for s in range(first, end):
                    t = slot_tile[s]
                    pos = tile_cursor[c, t]
                    tile_cursor[c, t] = pos + 1
                    keys[pos] = tiles.depth_slot_key(proj[slot_gid[s], project.P_DEPTH], s)
        for i in range(n_tiles * spread):
            if i % spread == 0:
                t = i // spread
                tiles.sort_segment(keys, tmp_keys, tile_start[t], tile_start[t + 1])
        for j in range(cap):
            if j < live_slots(offsets, n, cap):
                order[j] = tiles.key_slot(keys[j])
        for j in range(cap):
            if j < live_slots(offsets, n, cap):
                blend_f.gather_entry(j, order, slot_gid, proj, rect, entries)

    @ti.kernel
    def blend(
        tiles_x: ti.i32,
        n_tiles: ti.i32,  # T
        width: ti.i32,
        height: ti.i32,
        tile_start: ind(1),  # (T + 1,)
        entries: fnd(2),  # (S, E_WIDTH)
        bg: vec3,  # background colour
        state: fnd(1),  # scratch (H W F_WIDTH,): per-pixel running sums
        out_rgb: fnd(3),  # out (H, W, 3)
        out_depth: fnd(2),  # out (H, W): alpha-blended camera z
        out_trans: fnd(2),  # out (H, W): final transmittance (1 - alpha)
        out_last: ind(2),  # out (H, W): index within its tile of the last Gaussian blended (-1: none)
        with_colour: ti.template(),  # False: depth and alpha only (out_rgb black)
    ):
        for i in range(n_tiles * spread):
            if i % spread == 0:
                blend_f.blend_tile_forward(
                    i // spread, tiles_x, width, height, tile_start, entries, bg, state,
                    out_rgb, out_depth, out_trans, out_last, with_colour,
                )

    @ti.kernel
    def backward(
        n: ti.i32,  # N
        n_sh: ti.i32,  # M
        tiles_x: ti.i32,
        n_tiles: ti.i32,  # T
        width: ti.i32,
        height: ti.i32,
        cam: mat4,  # camera-to-world
        intr: vec4,  # fx, fy, cx, cy
        bg: vec3,
        means: fnd(2),  # (N, 3)
        quats: fnd(2),  # (N, 4); (1, 4) when isotropic
        log_scales: fnd(2),  # (N, 3); (N, 1) when isotropic
        logits: fnd(1),  # (N,)
        sh: fnd(3),  # (N, M, 3)
        offsets: ind(1),  # (N + 1,) from project_and_count
        cap: ti.i32,  # C, as the forward ran (an overflowed view has no slots: no gradients)
        tile_start: ind(1),  # (T + 1,) from bin_and_sort
        order: ind(1),  # (S,)
        entries: fnd(2),  # (S, E_WIDTH)
        out_trans: fnd(2),  # (H, W) final transmittance of the forward pass
        out_last: ind(2),  # (H, W) last slot of the forward pass
        d_rgb: fnd(3),  # (H, W, 3) dL/d colour
        d_depth: fnd(2),  # (H, W) dL/d blended depth
        d_alpha: fnd(2),  # (H, W) dL/d alpha
        state: fnd(1),  # scratch (H W B_WIDTH,)
        slot_grad: fnd(2),  # scratch (S, N_SLOT_GRADS): screen-space gradient of each slot
        d_means: fnd(2),  # out, added to (N, 3)
        d_quats: fnd(2),  # out, added to (N, 4)
        d_log_scales: fnd(2),  # out, added to (N, 3)
        d_logits: fnd(1),  # out, added to (N,)
        d_sh: fnd(3),  # out, added to (N, M, 3)
        pose_part: fnd(2),  # scratch (N, 6)
        pose_chunks: fnd(2),  # scratch (N / POSE_CHUNK + 1, 6)
        pose_out: fnd(1),  # out, POSE_COLUMNS values from pose_at: dL/d left perturbation of the camera,
        pose_at: ti.i32,  # [translation, rotation], then the slot count S and 1 when it overflowed (S > C)
        isotropic: ti.template(),
        view_dependent: ti.template(),  # M > 1
        with_colour: ti.template(),  # as the forward was rendered
    ):
        for i in range(n_tiles * spread):
            if i % spread == 0:
                blend_f.blend_tile_backward(
                    i // spread, tiles_x, width, height, tile_start, order, entries, bg,
                    out_trans, out_last, d_rgb, d_depth, d_alpha, state, slot_grad, with_colour,
                )
        for g in range(n):
            pose = ti.Vector.zero(dt, 6)
            if offsets[n] <= cap:
                pose = proj_f.slots_vjp(
                    g, offsets[g], offsets[g + 1], slot_grad, means, quats, log_scales, logits, sh, n_sh, cam, intr,
                    width, height, isotropic, view_dependent, d_means, d_quats, d_log_scales, d_logits, d_sh,
                )
            for c in ti.static(range(6)):
                pose_part[g, c] = pose[c]
        for chunk in range((n + POSE_CHUNK - 1) // POSE_CHUNK):
            acc = ti.Vector.zero(dt, 6)
            for g in range(chunk * POSE_CHUNK, ti.min(n, (chunk + 1) * POSE_CHUNK)):
                for c in ti.static(range(6)):
                    acc[c] += pose_part[g, c]
            for c in ti.static(range(6)):
                pose_chunks[chunk, c] = acc[c]
        ti.loop_config(serialize=True)
        for c in range(6):
            total = ti.cast(0.0, dt)
            for chunk in range((n + POSE_CHUNK - 1) // POSE_CHUNK):
                total += pose_chunks[chunk, c]
            pose_out[pose_at + c] = total
            if c == 0:
                pose_out[pose_at + 6] = ti.cast(offsets[n], dt)
                pose_out[pose_at + 7] = ti.cast(offsets[n] > cap, dt)

    return SimpleNamespace(
        project_and_count=project_and_count, bin_and_sort=bin_and_sort, blend=blend, backward=backward,
    )
