"""Front-to-back alpha blending of one 16x16 tile, and its hand-written backward.

One thread per tile walks the tile's depth-sorted list (records gathered in that order, so reads
are sequential); for each Gaussian it visits only the pixels of its support ellipse, row by row
(so work follows covered pixels, not tile area). Per pixel:
``alpha = min(0.99, o exp(power))``, skipped below 1/255 or beyond the support cut-off; blending
stops (without the Gaussian that would do it) once transmittance would fall under 1e-4, as in
3DGS. Outputs: colour ``sum T_i a_i c_i + T bg``, depth ``sum T_i a_i z_i`` (not normalised),
alpha ``1 - T``, and the local index of the last contributor for the backward replay.

The backward replays each tile back to front from the stored final transmittance, recovering
``T_i = T_{i+1} / (1 - a_i)``, and writes per-slot gradients of (mean2d, conic, depth, opacity,
colour) — single writer per slot, no atomics. A pixel's image gradients (colour g_c, depth g_z,
alpha g_A) are constant along its replay, so what lies behind Gaussian i enters dL/d a_i only through
the scalar ``S_i = T_final (g_c . bg - g_A) + sum_{k > i} w_k (g_c . c_k + g_z z_k)``:
``dL/d a_i = T_i (g_c . c_i + g_z z_i) - S_i / (1 - a_i)``. The replay carries that one running sum
per pixel instead of the colour and depth behind and the final transmittance. A pixel whose image gradients
are all zero (stage 3's padded anchor renders: the margin a warped view does not sample) would add exact zeros, so
it is not replayed, nor is a row none of whose pixels reaches the entry.
"""

import functools
from types import SimpleNamespace

import taichi as ti

from .project import (
    ALPHA_MIN,
    N_GRADS,
    P_COLOR,
    P_CONIC_A,
    P_CONIC_B,
    P_CONIC_C,
    P_CUTOFF,
    P_DEPTH,
    P_MEAN_X,
    P_MEAN_Y,
    P_OPACITY,
    P_WIDTH,
)
from .tiles import TILE

Array = ti.template()  # an ndarray argument of a ti.func (passed by reference)

# A tile-ordered entry record: the projection's screen record (columns 0..P_WIDTH-1) followed by the
# Gaussian's pixel box u0, v0, u1, v1, gathered once after sorting so blending reads sequentially.
E_BOX = P_WIDTH
E_WIDTH = P_WIDTH + 4
MAX_ALPHA = 0.99
MIN_TRANSMITTANCE = 1e-4
# Columns of a slot's gradient record (same order as the projection's screen record).
N_SLOT_GRADS = N_GRADS
# Per-pixel forward state: transmittance (negated once finished), colour, depth, last contributor.
F_TRANS, F_RGB, F_DEPTH, F_LAST = 0, 1, 4, 5
F_WIDTH = 6
# Per-pixel backward state: running T, the running sum S behind (module docstring), d(rgb, depth), last
# contributor.
B_TRANS, B_BEHIND, B_GRAD, B_LAST = 0, 1, 2, 6
B_WIDTH = 7


@functools.cache
def make(dt) -> SimpleNamespace:
    """Tile blending funcs for float type ``dt``."""
    vec3 = ti.types.vector(3, dt)

    @ti.func
    def tile_pixels(t, tiles_x, width, height):
        x0 = (t % tiles_x) * TILE
        y0 = (t // tiles_x) * TILE
        return ti.Vector([x0, y0, ti.min(x0 + TILE, width) - 1, ti.min(y0 + TILE, height) - 1])

    @ti.func
    def pixel_record(v, u, t, box, columns: ti.template()):
        """Flat index of pixel (v, u)'s first value in a per-pixel state of ``columns`` values per pixel, tile t
        (pixel box ``box``) holding TILE x TILE consecutive pixels: a tile's state is one contiguous block."""
        return (t * TILE * TILE + (v - box[1]) * TILE + (u - box[0])) * columns

    @ti.func
    def gather_entry(j, order: Array, slot_gid: Array, proj: Array, rect: Array,
                     entries: Array):
        """Copy the screen record and pixel box of the Gaussian behind sorted entry j (all reads before
        the first write: a write between reads makes the compiler reload each array's address and shape)."""
        g = slot_gid[order[j]]
        record = ti.Vector([proj[g, c] for c in ti.static(range(P_WIDTH))], dt=dt)
        box = ti.Vector([rect[g, c] for c in ti.static(range(4))])
        for c in ti.static(range(P_WIDTH)):
            entries[j, c] = record[c]
        for c in ti.static(range(4)):
            entries[j, E_BOX + c] = ti.cast(box[c], dt)

    @ti.func
    def screen_gaussian(entries: Array, j):
        """(mean x, mean y, conic a, b, c) of entry j."""
        return ti.Vector(
            [entries[j, P_MEAN_X], entries[j, P_MEAN_Y], entries[j, P_CONIC_A], entries[j, P_CONIC_B],
             entries[j, P_CONIC_C]], dt=dt
        )

    @ti.func
    def entry_box(entries: Array, j, box):
        """Entry j's pixel box clipped to the tile box (u0, v0, u1, v1)."""
        return ti.Vector([
            ti.max(ti.cast(entries[j, E_BOX], ti.i32), box[0]),
            ti.max(ti.cast(entries[j, E_BOX + 1], ti.i32), box[1]),
            ti.min(ti.cast(entries[j, E_BOX + 2], ti.i32), box[2]),
            ti.min(ti.cast(entries[j, E_BOX + 3], ti.i32), box[3]),
        ])

    @ti.func
    def splat_at(sg, u, v):
        """(power, dx, dy) of screen Gaussian sg at pixel (u, v); d = mean - pixel centre."""
        dx = sg[0] - (u + 0.5)
        dy = sg[1] - (v + 0.5)
        power = -0.5 * (sg[2] * dx * dx + sg[4] * dy * dy) - sg[3] * dx * dy
        return ti.Vector([power, dx, dy], dt=dt)

    @ti.func
    def row_span(sg, cutoff, v, u_min, u_max):
        """Pixel columns [lo, hi] of row v that may satisfy power >= cutoff (the ellipse's chord,
        widened by 1e-3 px so rounding never drops a pixel), clipped to [u_min, u_max]."""
        dy = sg[1] - (v + 0.5)
        a, b, c = sg[2], sg[3], sg[4]
        disc = b * b * dy * dy - a * (c * dy * dy + 2.0 * cutoff)
        lo, hi = u_max + 1, u_max
        if disc >= 0.0:
            root = ti.sqrt(disc)
            centre = sg[0] - 0.5 + b * dy / a
            lo_f = ti.max(ti.ceil(centre - root / a - 1e-3), ti.cast(u_min, dt))
            hi_f = ti.min(ti.floor(centre + root / a + 1e-3), ti.cast(u_max, dt))
            if lo_f <= hi_f:
                lo, hi = ti.cast(lo_f, ti.i32), ti.cast(hi_f, ti.i32)
        return lo, hi

    @ti.func
    def blend_tile_forward(
        t, tiles_x, width, height, tile_start: Array, entries: Array, bg,
        state: Array, out_rgb: Array, out_depth: Array, out_trans: Array,
        out_last: Array, with_colour: ti.template(),
    ):
        """Blend tile t front to back. ``state`` (flat, F_WIDTH values per pixel, see pixel_record) holds the
        running (T, r, g, b, depth, last) of each pixel, T negated once the pixel is finished. Without
        ``with_colour`` (static) the colour sums are skipped and ``out_rgb`` is written black."""
        box = tile_pixels(t, tiles_x, width, height)
        for v, u in ti.ndrange((box[1], box[3] + 1), (box[0], box[2] + 1)):
            p = pixel_record(v, u, t, box, F_WIDTH)
            state[p + F_TRANS] = 1.0
            for c in ti.static(range(1, F_WIDTH)):
                state[p + c] = 0.0
            state[p + F_LAST] = -1.0
        active = (box[2] - box[0] + 1) * (box[3] - box[1] + 1)
        start = tile_start[t]
        for j in range(start, tile_start[t + 1]):
            if active == 0:
                break
            eb = entry_box(entries, j, box)
            opacity = entries[j, P_OPACITY]
            cutoff = entries[j, P_CUTOFF]
            depth = entries[j, P_DEPTH]
            color = vec3(entries[j, P_COLOR], entries[j, P_COLOR + 1], entries[j, P_COLOR + 2])
            sg = screen_gaussian(entries, j)
            local = ti.cast(j - start, dt)
            for v in range(eb[1], eb[3] + 1):
                lo, hi = row_span(sg, cutoff, v, eb[0], eb[2])
                for u in range(lo, hi + 1):
                    p = pixel_record(v, u, t, box, F_WIDTH)
                    trans = state[p + F_TRANS]
                    if trans > 0.0:
                        power = splat_at(sg, u, v)[0]
                        if power >= cutoff:
                            alpha = ti.min(dt(MAX_ALPHA), opacity * ti.exp(power))
                            if alpha >= dt(ALPHA_MIN):
                                next_trans = trans * (1.0 - alpha)
                                if next_trans < dt(MIN_TRANSMITTANCE):
                                    state[p + F_TRANS] = -trans
                                    active -= 1
                                else:
                                    w = alpha * trans
                                    if ti.static(with_colour):
                                        for c in ti.static(range(3)):
                                            state[p + F_RGB + c] = state[p + F_RGB + c] + w * color[c]
                                    state[p + F_DEPTH] = state[p + F_DEPTH] + w * depth
                                    state[p + F_TRANS] = next_trans
                                    state[p + F_LAST] = local
        for v, u in ti.ndrange((box[1], box[3] + 1), (box[0], box[2] + 1)):
            p = pixel_record(v, u, t, box, F_WIDTH)
            trans = ti.abs(state[p + F_TRANS])
            for c in ti.static(range(3)):
                if ti.static(with_colour):
                    out_rgb[v, u, c] = state[p + F_RGB + c] + trans * bg[c]
                else:
                    out_rgb[v, u, c] = 0.0
            out_depth[v, u] = state[p + F_DEPTH]
            out_trans[v, u] = trans
            out_last[v, u] = ti.cast(state[p + F_LAST], ti.i32)

    @ti.func
    def blend_tile_backward(
        t, tiles_x, width, height, tile_start: Array, order: Array, entries: Array, bg,
        out_trans: Array, out_last: Array, d_rgb: Array, d_depth: Array,
        d_alpha: Array, state: Array, slot_grad: Array, with_colour: ti.template(),
    ):
        """Write dL/d(screen record) of every slot of tile t into slot_grad[slot, :]. ``state`` (flat,
        B_WIDTH values per pixel, see pixel_record) packs each pixel's running T, running sum behind, image
        gradients and last contributor (see the B_* columns). Without ``with_colour`` (static,
        a depth-and-alpha render) the colour terms are skipped and the slots' colour gradients are 0."""
        box = tile_pixels(t, tiles_x, width, height)
        last = -1
        row_last = ti.Vector([-1 for _ in ti.static(range(TILE))])  # the largest pixel_last of each row
        for v, u in ti.ndrange((box[1], box[3] + 1), (box[0], box[2] + 1)):
            p = pixel_record(v, u, t, box, B_WIDTH)
            final_trans = out_trans[v, u]
            g_rgb = vec3(d_rgb[v, u, 0], d_rgb[v, u, 1], d_rgb[v, u, 2])
            g_depth = d_depth[v, u]
            g_alpha = d_alpha[v, u]
            state[p + B_TRANS] = final_trans
            if ti.static(with_colour):  # the background's share of S (module docstring)
                state[p + B_BEHIND] = final_trans * (g_rgb.dot(bg) - g_alpha)
            else:
                state[p + B_BEHIND] = -final_trans * g_alpha
            for c in ti.static(range(3)):
                state[p + B_GRAD + c] = g_rgb[c]
            state[p + B_GRAD + 3] = g_depth
            # a pixel without image gradients adds exact zeros to every slot: it is not replayed
            silent = g_depth == 0.0 and g_alpha == 0.0
            if ti.static(with_colour):
                silent = silent and g_rgb[0] == 0.0 and g_rgb[1] == 0.0 and g_rgb[2] == 0.0
            pixel_last = ti.select(silent, -1, out_last[v, u])
            state[p + B_LAST] = ti.cast(pixel_last, dt)
            last = ti.max(last, pixel_last)
            row_last[v - box[1]] = ti.max(row_last[v - box[1]], pixel_last)
        start = tile_start[t]
        for j in range(start + last + 1, tile_start[t + 1]):
            for c in ti.static(range(N_SLOT_GRADS)):
                slot_grad[order[j], c] = 0.0
        for k in range(last + 1):
            jj = last - k
            j = start + jj
            eb = entry_box(entries, j, box)
            opacity = entries[j, P_OPACITY]
            cutoff = entries[j, P_CUTOFF]
            depth = entries[j, P_DEPTH]
            sg = screen_gaussian(entries, j)
            ca, cb, cc = sg[2], sg[3], sg[4]
            color = vec3(entries[j, P_COLOR], entries[j, P_COLOR + 1], entries[j, P_COLOR + 2])
            local = ti.cast(jj, dt)
            acc = ti.Vector.zero(dt, N_SLOT_GRADS)
            for v in range(eb[1], eb[3] + 1):
                if jj > row_last[v - box[1]]:  # no pixel of the row saw this entry (or has gradients)
                    continue
                lo, hi = row_span(sg, cutoff, v, eb[0], eb[2])
                for u in range(lo, hi + 1):
                    p = pixel_record(v, u, t, box, B_WIDTH)
                    if local <= state[p + B_LAST]:
                        s = splat_at(sg, u, v)
                        power = s[0]
                        if power >= cutoff:
                            gauss = ti.exp(power)
                            alpha = ti.min(dt(MAX_ALPHA), opacity * gauss)
                            if alpha >= dt(ALPHA_MIN):
                                inv_keep = 1.0 / (1.0 - alpha)  # T_i = T_{i+1} / (1 - alpha_i)
                                trans = state[p + B_TRANS] * inv_keep
                                behind = state[p + B_BEHIND]
                                g_depth = state[p + B_GRAD + 3]
                                w = alpha * trans
                                seen = g_depth * depth  # g . (what this Gaussian adds per unit weight)
                                if ti.static(with_colour):
                                    g_rgb = vec3(state[p + B_GRAD], state[p + B_GRAD + 1], state[p + B_GRAD + 2])
                                    seen += g_rgb.dot(color)
                                    for c in ti.static(range(3)):
                                        acc[P_COLOR + c] += g_rgb[c] * w
                                g_alpha = seen * trans - behind * inv_keep
                                acc[P_DEPTH] += g_depth * w
                                state[p + B_BEHIND] = behind + seen * w
                                state[p + B_TRANS] = trans
                                if opacity * gauss <= dt(MAX_ALPHA):
                                    acc[P_OPACITY] += g_alpha * gauss
                                    g_power = g_alpha * alpha
                                    dx, dy = s[1], s[2]
                                    acc[P_MEAN_X] += -g_power * (ca * dx + cb * dy)
                                    acc[P_MEAN_Y] += -g_power * (cb * dx + cc * dy)
                                    acc[P_CONIC_A] += -0.5 * g_power * dx * dx
                                    acc[P_CONIC_B] += -g_power * dx * dy
                                    acc[P_CONIC_C] += -0.5 * g_power * dy * dy
            slot = order[j]
            for c in ti.static(range(N_SLOT_GRADS)):
                slot_grad[slot, c] = acc[c]

    return SimpleNamespace(
        gather_entry=gather_entry, blend_tile_forward=blend_tile_forward, blend_tile_backward=blend_tile_backward
    )
