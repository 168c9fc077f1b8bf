"""[ours] Virtual views by depth warping (stage 3's ``warp_views``): sharp views at poses near an
*anchor* view's pose are made by sampling the anchor's render where each of their pixels' surface lands,
instead of rasterising them again. The anchor is rendered with a ``margin`` of extra pixels on every
side (principal point shifted by the margin), so views moved by up to about that many pixels sample
rendered content, not a clamped edge. One kernel launch warps all the views of one anchor.

Pixel p of a target view (rasterizer convention: pixel u samples image coordinate u + 0.5) looks along
ray r(p) = K^-1 (p + 0.5, 1). Its depth z comes from a short fixed-point iteration on the anchor's
surface: start with the anchor's depth at p, land the point z r(p) in the anchor (X_a = R z r(p) + t,
the view's ``target_to_anchor`` = [R | t]), read the anchor's surface depth there (nearest pixel,
blended z / alpha where alpha >= 1/2, else ``fallback`` metres), and take that surface point's depth
in the target camera. The view is the anchor's colour at the projection q of X_a, interpolated by
Catmull-Rom (bilinear's low pass, trained through, made the scene over-sharpen; q is clamped so that
every tap lies in the padded image). Exact for rotations at any depth up to the interpolation; for
translations it misplaces what the anchor does not see (disocclusions). A view at the anchor's own pose
(the middle view of an odd group of views) lands every pixel on a knot, where the interpolation is the pixel
itself and its derivative a central difference: the host flags it (``IDENTITY``) and the kernels read one
pixel instead of 16 taps, forward and backward.

Backward (z held fixed: the fixed point's nearest-pixel lookups are piecewise constant): dL/d anchor
colour (the interpolation weights' transpose, added into the caller's buffer) and, per view, dL/d
epsilon, the 6-vector [translation, rotation] of a left perturbation ``exp(epsilon) target_to_anchor``
in the anchor's camera frame (summed per image row, then in float64 on the host: the rows can wait in a
training step's values, :mod:`~taichi_gs.kernels.step_values`, for its one read);
``geometry.relative_pose_gradients`` turns it into the two cameras' world perturbations.

Loop structure: the CPU runs a task per image row, and its backward scatters without atomics (slow
there): each thread's band of rows adds into a private copy of the colour gradient, and a second loop
sums the copies. Per row and view the backward makes two passes, the pose gradient (reads only), then
the scatter (writes): a write among the reads would make every later read reload the arrays' addresses
and shapes. GPU backends run a thread per pixel and add atomically.
"""

import functools
from types import SimpleNamespace

import numpy as np
import taichi as ti

from .. import profiling
from . import host_copy, runtime, scan
from .step_values import Slot, StepValues

FIXED_POINT_STEPS = 1  # depth refinements after the first guess (none are needed for a pure rotation)
MIN_ALPHA = 0.5  # anchor pixels with less accumulated opacity have no surface: the fallback depth is used
MIN_Z = 1e-6
N_POSE = 6
IDENTITY = 12  # the column of a view's transform row that flags the anchor's own pose (R = I, t = 0)
IDENTITY_TOLERANCE = 1e-9  # largest |entry - identity's| of a transform taken as the anchor's own pose
TAPS = 4  # interpolation taps per axis (Catmull-Rom)
LANE_SPREAD = 1024  # loop indices per lane: a loop this long is spread over the CPU's threads


@functools.cache
def _kernels(dt) -> SimpleNamespace:
    img3 = ti.types.ndarray(dtype=dt, ndim=3)
    img2 = ti.types.ndarray(dtype=dt, ndim=2)
    flat = ti.types.ndarray(dtype=dt, ndim=1)
    vec3 = ti.types.vector(3, dt)
    vec4 = ti.types.vector(4, dt)
    spread = runtime.loop_spread()  # image rows x spread indices (see runtime.loop_spread)

    @ti.func
    def surface_depth(depth: ti.template(), trans: ti.template(), sx, sy, fallback):
        """Depth of the anchor's surface at the pixel nearest index coordinates (sx, sy), clamped."""
        hp, wp = depth.shape[0], depth.shape[1]
        iu = ti.cast(ti.min(ti.max(sx + 0.5, 0.0), wp - 0.5), ti.i32)  # nearest: truncation of non-negatives
        iv = ti.cast(ti.min(ti.max(sy + 0.5, 0.0), hp - 0.5), ti.i32)
        alpha = 1.0 - trans[iv, iu]
        z = fallback
        if alpha >= MIN_ALPHA:
            z = depth[iv, iu] / alpha
        return z

    @ti.func
    def target_ray(u, v, intr):
        """K^-1 (u + 0.5, v + 0.5, 1): target pixel (u, v)'s ray at unit depth."""
        return vec3((u + 0.5 - intr[2]) / intr[0], (v + 0.5 - intr[3]) / intr[1], 1.0)

    @ti.func
    def land(rotated_ray, z, t, intr, margin):
        """(X_a, 1 / its clamped depth, sx, sy): the target point at depth z along a ray (already rotated
        into the anchor's axes: R r) in the anchor's camera, and its anchor index coordinates (image
        coordinate - 0.5, margin included)."""
        X = z * rotated_ray + t
        inv_z = 1.0 / ti.max(X[2], MIN_Z)
        sx = intr[0] * X[0] * inv_z + intr[2] + margin - 0.5
        sy = intr[1] * X[1] * inv_z + intr[3] + margin - 0.5
        return X, inv_z, sx, sy

    @ti.func
    def target_depth(z, rotated_ray, depth: ti.template(), trans: ti.template(), R, t, intr, margin, fallback):
        """The fixed point's depth of a target pixel whose first guess is z (the anchor's surface depth at
        the same pixel; see the module docstring). The surface point seen at the landing (sx, sy) is
        zs K^-1 (sx + 0.5 - margin, sy + 0.5 - margin, 1) = zs / X_a.z X_a."""
        for _ in ti.static(range(FIXED_POINT_STEPS)):
            X, inv_z, sx, sy = land(rotated_ray, z, t, intr, margin)
            zs = surface_depth(depth, trans, sx, sy, fallback)
            surface = zs * vec3(X[0] * inv_z, X[1] * inv_z, 1.0) - t
            z = ti.max(R[0, 2] * surface[0] + R[1, 2] * surface[1] + R[2, 2] * surface[2], MIN_Z)  # (R^T s)_z
        return z

    @ti.func
    def interpolation_weights(f):
        """Catmull-Rom weights of the taps at -1, 0, 1, 2 for a sample at fraction f past tap 0, and their
        derivatives in f."""
        f2 = f * f
        f3 = f2 * f
        w = ti.Vector([0.5 * (-f3 + 2.0 * f2 - f), 0.5 * (3.0 * f3 - 5.0 * f2 + 2.0),
                       0.5 * (-3.0 * f3 + 4.0 * f2 + f), 0.5 * (f3 - f2)], dt=dt)
        dw = ti.Vector([0.5 * (-3.0 * f2 + 4.0 * f - 1.0), 0.5 * (9.0 * f2 - 10.0 * f),
                        0.5 * (-9.0 * f2 + 8.0 * f + 1.0), 0.5 * (3.0 * f2 - 2.0 * f)], dt=dt)
        return w, dw

    @ti.func
    def cell(s, n):
        """(first tap, f, inside) of a sample at index coordinate s of an axis of n pixels: s is clamped so
        that every tap lies in the image (the margin keeps that rare); the taps are first .. first + TAPS - 1,
        f the fraction past tap TAPS / 2 - 1; inside is 0 where s was clamped (no gradient)."""
        c = ti.min(ti.max(s, ti.cast(TAPS // 2 - 1, dt)), ti.cast(n - TAPS // 2, dt))
        i0 = ti.min(ti.cast(c, ti.i32), n - TAPS // 2 - 1)
        return i0 - (TAPS // 2 - 1), c - i0, ti.cast(c == s, dt)

    @ti.func
    def sample_at(rotated_ray, z, t, intr, margin, hp, wp):
        """(X_a, first tap x, y, Catmull-Rom weights and their derivatives along x and y, inside x, y) of the
        target point at depth z along ``rotated_ray`` (see :func:`land`) in an anchor of hp x wp pixels."""
        X, _inv_z, sx, sy = land(rotated_ray, z, t, intr, margin)
        x0, fx, inside_x = cell(sx, wp)
        y0, fy, inside_y = cell(sy, hp)
        wx, dwx = interpolation_weights(fx)
        wy, dwy = interpolation_weights(fy)
        return X, x0, y0, wx, dwx, wy, dwy, inside_x, inside_y

    @ti.func
    def rgb_at(image: ti.template(), y, x):
        """The 3 channels of pixel (y, x) of an (H, W, 3) array."""
        return vec3(image[y, x, 0], image[y, x, 1], image[y, x, 2])

    @ti.func
    def transform_row(view, v, rows_per_view):
        """The row of ``transforms`` that holds view ``view``'s transform for target image row v: one per view
        (``rows_per_view`` 1), or one per view and image row (a rolling shutter: ``rows_per_view`` = H)."""
        return view * rows_per_view + ti.min(v, rows_per_view - 1)

    @ti.func
    def view_transform(transforms: ti.template(), i):
        """(R, t) from row i of ``transforms`` (R row-major, then t)."""
        R = ti.Matrix([[transforms[i, 3 * r + c] for c in ti.static(range(3))] for r in ti.static(range(3))], dt=dt)
        return R, vec3(transforms[i, 9], transforms[i, 10], transforms[i, 11])

    @ti.func
    def pixel_forward(u, v, anchor_rgb: ti.template(), anchor_depth: ti.template(), anchor_trans: ti.template(),
                      transforms: ti.template(), n_views, rows_per_view, intr, margin, fallback, weight, keep,
                      out: ti.template(), z_out: ti.template()):
        """Target pixel (u, v) of every view: its depths into ``z_out``, the weighted sum into ``out``."""
        hp, wp = anchor_rgb.shape[0], anchor_rgb.shape[1]
        total = vec3(0.0, 0.0, 0.0)
        ray = target_ray(u, v, intr)
        z_anchor = surface_depth(anchor_depth, anchor_trans, ti.cast(u + margin, dt), ti.cast(v + margin, dt),
                                 fallback)
        for view in range(n_views):
            row = transform_row(view, v, rows_per_view)
            if transforms[row, IDENTITY] > 0.5:  # the view is the anchor's own: its pixel, no interpolation
                z_out[view, v, u] = ti.max(z_anchor, MIN_Z)
                total += rgb_at(anchor_rgb, v + margin, u + margin)
            else:
                R, t = view_transform(transforms, row)
                rotated_ray = R @ ray
                z = target_depth(z_anchor, rotated_ray, anchor_depth, anchor_trans, R, t, intr, margin, fallback)
                z_out[view, v, u] = z
                _X, x0, y0, wx, _dwx, wy, _dwy, _inside_x, _inside_y = sample_at(rotated_ray, z, t, intr, margin,
                                                                                 hp, wp)
                for b in ti.static(range(TAPS)):
                    tap_row = vec3(0.0, 0.0, 0.0)
                    for a in ti.static(range(TAPS)):
                        tap_row += wx[a] * rgb_at(anchor_rgb, y0 + b, x0 + a)
                    total += wy[b] * tap_row
        for c in ti.static(range(3)):
            out[v, u, c] = keep * out[v, u, c] + weight * total[c]

    @ti.kernel
    def forward(
        anchor_rgb: img3,  # (Hp, Wp, 3) the anchor's render, Hp = H + 2 margin
        anchor_depth: img2,  # (Hp, Wp) its blended z
        anchor_trans: img2,  # (Hp, Wp) its final transmittance
        transforms: img2,  # (>= V x rows_per_view, 13) each view's target -> anchor transform and identity flag
        n_views: ti.i32,  # V
        rows_per_view: ti.i32,  # 1, or H: a transform per image row (rolling shutter)
        intr: vec4,  # target fx, fy, cx, cy (rasterizer pixel centres)
        margin: ti.i32,
        fallback: dt,  # metres, where the anchor has no surface
        weight: dt,
        keep: dt,  # out = keep * out + weight * (sum of the V warped views)
        out: img3,  # out (H, W, 3)
        z_out: img3,  # out (>= V, H, W): the fixed point's depths, for the backward
    ):
        if ti.static(spread > 1):  # CPU: a task per image row
            for i in range(out.shape[0] * spread):
                if i % spread == 0:
                    for u in range(out.shape[1]):
                        pixel_forward(u, i // spread, anchor_rgb, anchor_depth, anchor_trans, transforms, n_views,
                                      rows_per_view, intr, margin, fallback, weight, keep, out, z_out)
        else:  # GPU: a thread per pixel
            for v, u in ti.ndrange(out.shape[0], out.shape[1]):
                pixel_forward(u, v, anchor_rgb, anchor_depth, anchor_trans, transforms, n_views, rows_per_view, intr,
                              margin, fallback, weight, keep, out, z_out)

    @ti.func
    def pixel_sample(u, v, z_in: ti.template(), view, R, t, intr, margin, hp, wp):
        """:func:`sample_at` of target pixel (u, v) in one view, at the depth the forward found."""
        return sample_at(R @ target_ray(u, v, intr), z_in[view, v, u], t, intr, margin, hp, wp)

    @ti.func
    def pose_of(X, x0, y0, wx, dwx, wy, dwy, inside_x, inside_y, g, anchor_rgb: ti.template(), intr):
        """dL/d epsilon of one sample (:func:`pixel_sample`) whose colour gradient is g (reads only)."""
        g_sx = ti.cast(0.0, dt)
        g_sy = ti.cast(0.0, dt)
        for b in ti.static(range(TAPS)):
            for a in ti.static(range(TAPS)):
                dot = g.dot(rgb_at(anchor_rgb, y0 + b, x0 + a))
                g_sx += dwx[a] * wy[b] * dot
                g_sy += wx[a] * dwy[b] * dot
        return pose_from_image_gradient(X, g_sx * inside_x, g_sy * inside_y, intr)

    @ti.func
    def pose_at_identity(u, v, z, g, anchor_rgb: ti.template(), intr, margin):
        """:func:`pose_of` for a view that is the anchor's own (R = I, t = 0): the sample sits on pixel
        (u + margin, v + margin), where Catmull-Rom's weights are (0, 1, 0, 0) and their derivatives
        (-1/2, 0, 1/2, 0), a central difference."""
        x, y = u + margin, v + margin
        g_sx = 0.5 * (g.dot(rgb_at(anchor_rgb, y, x + 1)) - g.dot(rgb_at(anchor_rgb, y, x - 1)))
        g_sy = 0.5 * (g.dot(rgb_at(anchor_rgb, y + 1, x)) - g.dot(rgb_at(anchor_rgb, y - 1, x)))
        return pose_from_image_gradient(z * target_ray(u, v, intr), g_sx, g_sy, intr)

    @ti.func
    def pose_from_image_gradient(X, g_sx, g_sy, intr):
        """dL/d epsilon of a sample at anchor point X whose loss changes by (g_sx, g_sy) per pixel of its image
        position."""
        pose = ti.Vector.zero(dt, N_POSE)
        if X[2] > MIN_Z:
            inv_z = 1.0 / X[2]
            g_X = vec3(g_sx * intr[0] * inv_z, g_sy * intr[1] * inv_z,
                       -(g_sx * intr[0] * X[0] + g_sy * intr[1] * X[1]) * inv_z * inv_z)
            g_rot = X.cross(g_X)
            for c in ti.static(range(3)):
                pose[c] = g_X[c]
                pose[3 + c] = g_rot[c]
        return pose

    @ti.func
    def add_to_lane(copies: ti.template(), lane, y, x, hp, wp, g):
        """Add colour gradient g to pixel (y, x) of lane ``lane`` of the flat private copies (see :func:`scatter`)."""
        base = ((lane * hp + y) * wp + x) * 3
        for c in ti.static(range(3)):
            copies[base + c] = copies[base + c] + g[c]  # not +=, which Taichi compiles to an atomic add

    @ti.func
    def scatter(x0, y0, wx, wy, g, hp, wp, grad_anchor: ti.template(), lane, private: ti.template()):
        """Add one sample's share of dL/d anchor colour (colour gradient g): without atomics into lane
        ``lane`` of ``grad_anchor``, the flat (lanes, Hp, Wp, 3) copies, when ``private`` (four runs of 12
        consecutive floats from one base index each); else atomically into ``grad_anchor`` (Hp, Wp, 3)."""
        for b in ti.static(range(TAPS)):
            y = y0 + b
            g_row = wy[b] * g
            base = ((lane * hp + y) * wp + x0) * 3  # the private copy's flat index of tap (x0, y)
            for a in ti.static(range(TAPS)):
                for c in ti.static(range(3)):
                    share = wx[a] * g_row[c]
                    if ti.static(private):  # not +=, which Taichi compiles to an atomic add
                        grad_anchor[base + 3 * a + c] = grad_anchor[base + 3 * a + c] + share
                    else:
                        ti.atomic_add(grad_anchor[y, x0 + a, c], share)

    @ti.func
    def pixel_pose(u, v, grad_out: ti.template(), anchor_rgb: ti.template(), z_in: ti.template(), view, R, t,
                   intr, margin, weight, identity):
        """Target pixel (u, v)'s dL/d epsilon in one view (reads only; the CPU backward's first pass)."""
        g = weight * rgb_at(grad_out, v, u)
        pose = ti.Vector.zero(dt, N_POSE)
        if identity:
            pose = pose_at_identity(u, v, z_in[view, v, u], g, anchor_rgb, intr, margin)
        else:
            X, x0, y0, wx, dwx, wy, dwy, inside_x, inside_y = pixel_sample(u, v, z_in, view, R, t, intr, margin,
                                                                           anchor_rgb.shape[0], anchor_rgb.shape[1])
            pose = pose_of(X, x0, y0, wx, dwx, wy, dwy, inside_x, inside_y, g, anchor_rgb, intr)
        return pose

    @ti.func
    def pixel_scatter(u, v, grad_out: ti.template(), z_in: ti.template(), view, R, t, intr, margin, weight,
                      hp, wp, grad_anchor: ti.template(), lane, private: ti.template(), identity):
        """Target pixel (u, v)'s share of dL/d anchor colour in one view (the CPU backward's second pass, into
        lane ``lane`` of the private copies)."""
        g = weight * rgb_at(grad_out, v, u)
        if identity:  # one tap, weight 1
            add_to_lane(grad_anchor, lane, v + margin, u + margin, hp, wp, g)
        else:
            _X, x0, y0, wx, _dwx, wy, _dwy, _inside_x, _inside_y = pixel_sample(u, v, z_in, view, R, t, intr,
                                                                                margin, hp, wp)
            scatter(x0, y0, wx, wy, g, hp, wp, grad_anchor, lane, private)

    @ti.kernel
    def backward_atomic(
        grad_out: img3,  # (H, W, 3) dL/d out
        anchor_rgb: img3,  # (Hp, Wp, 3)
        z_in: img3,  # (>= V, H, W) from forward
        transforms: img2,  # (>= V x rows_per_view, 13)
        n_views: ti.i32,  # V
        rows_per_view: ti.i32,
        intr: vec4,
        margin: ti.i32,
        weight: dt,
        with_anchor: ti.i32,  # 0: dL/d epsilon only (grad_anchor untouched)
        grad_anchor: img3,  # out, added to (Hp, Wp, 3)
        out: flat,  # out: dL/d epsilon per image row and view, (H V, N_POSE) row-major from out[at]
        at: ti.i32,
    ):
        for i in range(grad_out.shape[0] * n_views * N_POSE):  # the rows zeroed (a loop runs after the one before)
            out[at + i] = 0.0
        for v, u in ti.ndrange(grad_out.shape[0], grad_out.shape[1]):  # GPU: a thread per pixel
            for view in range(n_views):
                g = weight * rgb_at(grad_out, v, u)
                pose = ti.Vector.zero(dt, N_POSE)
                row = transform_row(view, v, rows_per_view)
                if transforms[row, IDENTITY] > 0.5:
                    pose = pose_at_identity(u, v, z_in[view, v, u], g, anchor_rgb, intr, margin)
                    if with_anchor:
                        for c in ti.static(range(3)):
                            ti.atomic_add(grad_anchor[v + margin, u + margin, c], g[c])
                else:
                    R, t = view_transform(transforms, row)
                    hp, wp = anchor_rgb.shape[0], anchor_rgb.shape[1]
                    X, x0, y0, wx, dwx, wy, dwy, inside_x, inside_y = pixel_sample(u, v, z_in, view, R, t, intr,
                                                                                   margin, hp, wp)
                    pose = pose_of(X, x0, y0, wx, dwx, wy, dwy, inside_x, inside_y, g, anchor_rgb, intr)
                    if with_anchor:
                        scatter(x0, y0, wx, wy, g, hp, wp, grad_anchor, 0, False)
                for c in ti.static(range(N_POSE)):
                    ti.atomic_add(out[at + (v * n_views + view) * N_POSE + c], pose[c])

    @ti.kernel
    def backward_lanes(
        grad_out: img3,
        anchor_rgb: img3,
        z_in: img3,
        transforms: img2,
        n_views: ti.i32,
        rows_per_view: ti.i32,
        intr: vec4,
        margin: ti.i32,
        weight: dt,
        with_anchor: ti.i32,  # 0: dL/d epsilon only (no scatter; grad_anchor untouched)
        lanes: ti.i32,
        private: ti.types.ndarray(dtype=dt, ndim=1),  # scratch (lanes, Hp, Wp, 3) flat, zero on entry and on exit
        grad_anchor: img3,  # out, added to (Hp, Wp, 3)
        out: flat,
        at: ti.i32,
    ):
        h = grad_out.shape[0]
        for i in range(lanes * LANE_SPREAD):
            if i % LANE_SPREAD == 0:
                lane = i // LANE_SPREAD
                for v in range(lane * h // lanes, (lane + 1) * h // lanes):
                    for view in range(n_views):
                        row = transform_row(view, v, rows_per_view)
                        R, t = view_transform(transforms, row)
                        identity = transforms[row, IDENTITY] > 0.5
                        acc = ti.Vector.zero(dt, N_POSE)  # the row's reads, then its writes (module docstring)
                        for u in range(grad_out.shape[1]):
                            acc += pixel_pose(u, v, grad_out, anchor_rgb, z_in, view, R, t, intr, margin, weight,
                                              identity)
                        if with_anchor:
                            for u in range(grad_out.shape[1]):
                                pixel_scatter(u, v, grad_out, z_in, view, R, t, intr, margin, weight,
                                              anchor_rgb.shape[0], anchor_rgb.shape[1], private, lane, True, identity)
                        for c in ti.static(range(N_POSE)):
                            out[at + (v * n_views + view) * N_POSE + c] = acc[c]
        for i in range(grad_anchor.shape[0] * spread * with_anchor):
            if i % spread == 0:
                y = i // spread
                for x in range(grad_anchor.shape[1]):
                    for c in ti.static(range(3)):
                        total = grad_anchor[y, x, c]
                        for lane in range(lanes):
                            k = ((lane * grad_anchor.shape[0] + y) * grad_anchor.shape[1] + x) * 3 + c
                            total += private[k]
                            private[k] = 0.0
                        grad_anchor[y, x, c] = total

    return SimpleNamespace(forward=forward, backward_atomic=backward_atomic, backward_lanes=backward_lanes)


_scratch = scan.Scratch()
_lane_buffers: dict[str, ti.Ndarray] = {}  # the CPU backward's private gradients, zeroed when made


def _args(transforms: np.ndarray, K: np.ndarray, margin: int, height: int, dtype) -> tuple:
    """(V, rows per view, device rows [R row-major, t, identity flag] of the views' 4x4 target -> anchor
    transforms, the intrinsics vector). ``transforms`` is (V, 4, 4), or (V, H, 4, 4) with one transform per
    target image row (a rolling shutter, ``stages.deblur.model``). A transform within ``IDENTITY_TOLERANCE`` of the
    identity is the anchor's own pose (the middle view of an odd group, ``stages.deblur.model.anchor_groups``): it
    is flagged, and the kernels read its pixels instead of interpolating them (with a margin, so that the
    central differences of its pose gradient stay in the image)."""
    M = np.array(transforms, dtype=np.float64)  # a copy: the caller's stay as given
    if M.ndim == 4 and M.shape[1] != height:
        raise ValueError(f"{M.shape[1]} row transforms per view for an image of {height} rows")
    views, rows_per_view = (M.shape[0], M.shape[1]) if M.ndim == 4 else (len(M.reshape(-1, 4, 4)), 1)
    M = M.reshape(-1, 4, 4)
    identity = np.abs(M[:, :3, :] - np.eye(4)[:3]).max(axis=(1, 2)) <= IDENTITY_TOLERANCE
    identity &= margin >= 1
    M[identity] = np.eye(4)
    rows = np.concatenate([M[:, :3, :3].reshape(-1, 9), M[:, :3, 3], identity[:, None]], axis=1)
    device = _scratch.get(f"warp transforms {dtype}", len(rows), dtype, (IDENTITY + 1,))
    padded = np.zeros(device.shape, rows.dtype)
    padded[: len(rows)] = rows
    host_copy.write(device, padded)
    K = np.asarray(K, dtype=np.float64)
    return views, rows_per_view, device, ti.Vector([K[0, 0], K[1, 1], K[0, 2], K[1, 2]], dt=dtype)


def _check(anchor_rgb: ti.Ndarray, image: ti.Ndarray, margin: int, z: ti.Ndarray, views: int) -> None:
    hp, wp = anchor_rgb.shape[:2]
    h, w = image.shape[:2]
    if (hp, wp) != (h + 2 * margin, w + 2 * margin) or anchor_rgb.dtype != image.dtype or min(hp, wp) < TAPS:
        raise ValueError(f"anchor of shape {tuple(anchor_rgb.shape)} ({anchor_rgb.dtype}) does not pad an image of "
                         f"shape {tuple(image.shape)} ({image.dtype}) by {margin} px")
    if z.shape[0] < views or tuple(z.shape[1:]) != (h, w):
        raise ValueError(f"depth buffer of shape {tuple(z.shape)} for {views} views of {h} x {w}")


@profiling.timed("warped views (device)")
def accumulate(anchor_rgb: ti.Ndarray, anchor_depth: ti.Ndarray, anchor_trans: ti.Ndarray,
               targets_to_anchor: np.ndarray, K: np.ndarray, margin: int, fallback_depth: float, weight: float,
               out: ti.Ndarray, z_out: ti.Ndarray, first: bool = False) -> None:
    """Add ``weight`` x the sum of V target views warped from the anchor's padded render (``anchor_rgb``
    (H + 2m, W + 2m, 3), its blended depth and transmittance) into ``out`` (H, W, 3); ``first``
    overwrites instead. ``targets_to_anchor``: (V, 4, 4) from each target camera to the anchor's; ``K``:
    the targets' intrinsics in the rasterizer's convention (the anchor's are the same, shifted by the
    margin). ``targets_to_anchor`` may instead be (V, H, 4, 4), a transform for each image row of each view
    (the rows of a rolling shutter, read at different poses). ``z_out`` (>= V, H, W) receives each pixel's
    depth for :func:`backward`."""
    views, rows_per_view, transforms, intr = _args(targets_to_anchor, K, margin, out.shape[0], out.dtype)
    _check(anchor_rgb, out, margin, z_out, views)
    _kernels(out.dtype).forward(anchor_rgb, anchor_depth, anchor_trans, transforms, views, rows_per_view, intr,
                                margin, fallback_depth, weight, 0.0 if first else 1.0, out, z_out)


@profiling.timed("warped views (device)")
def backward(grad_out: ti.Ndarray, anchor_rgb: ti.Ndarray, z: ti.Ndarray, targets_to_anchor: np.ndarray,
             K: np.ndarray, margin: int, weight: float, grad_anchor: ti.Ndarray | None,
             into: Slot | None = None) -> np.ndarray | None:
    """Given dL/d out of :func:`accumulate`'s term (``grad_out`` (H, W, 3); the term is ``weight`` x the
    sum of the warped views), add dL/d anchor colour into ``grad_anchor`` (None: not wanted, the anchor is
    a constant) and return dL/d epsilon (V, 6) [translation, rotation] for ``exp(epsilon) @
    targets_to_anchor[i]``, epsilon in the anchor's frame. With a transform per image row (V, H, 4, 4), the
    perturbation moves every row of view i alike: ``exp(epsilon) @ targets_to_anchor[i, v]``. ``into`` (a slot
    of :func:`pose_rows` (H, V) rows of a step's values): leave the per-row sums there and return None;
    :func:`pose_sums` of the rows read is then the return value."""
    dtype, height = grad_out.dtype, grad_out.shape[0]
    views, rows_per_view, transforms, intr = _args(targets_to_anchor, K, margin, height, dtype)
    _check(anchor_rgb, grad_out, margin, z, views)
    own = _own_values(dtype)
    slot = into or own.rows("warp rows", pose_rows(height, views), N_POSE)
    if slot.size != pose_rows(height, views) * N_POSE:
        raise ValueError(f"a slot of {slot.size} values for {height} x {views} rows of the warp's pose gradient")
    kernels = _kernels(dtype)
    backend = runtime.current()
    with_anchor = int(grad_anchor is not None)
    grad_anchor = anchor_rgb if grad_anchor is None else grad_anchor  # any (Hp, Wp, 3) array: not written
    if backend.gpu_kernels:
        kernels.backward_atomic(grad_out, anchor_rgb, z, transforms, views, rows_per_view, intr, margin, weight,
                                with_anchor, grad_anchor, slot.values, slot.at)
    else:
        lanes = max(backend.cpu_threads, 1)
        private = _private_gradients(lanes, tuple(anchor_rgb.shape), dtype)
        kernels.backward_lanes(grad_out, anchor_rgb, z, transforms, views, rows_per_view, intr, margin, weight,
                               with_anchor, lanes, private, grad_anchor, slot.values, slot.at)
    if into is not None:
        return None
    return pose_sums(own.read()["warp rows"], views)


def pose_rows(height: int, views: int) -> int:
    """Rows of N_POSE values a :func:`backward` of ``views`` views of ``height`` rows leaves: one per image row
    and view."""
    return height * views


def pose_sums(rows: np.ndarray, views: int) -> np.ndarray:
    """dL/d epsilon (V, 6) from the rows a :func:`backward` left (float64 (H V, N_POSE)), summed over the image
    rows in float64."""
    return np.asarray(rows, np.float64).reshape(-1, views, N_POSE).sum(axis=0)


@functools.cache
def _own_values(dtype) -> StepValues:
    """Where a :func:`backward` without ``into`` leaves its rows before they are read."""
    return StepValues(dtype)


def _private_gradients(lanes: int, shape: tuple, dtype) -> ti.Ndarray:
    """The CPU backward's per-lane gradient copies, flat (lanes x Hp x Wp x 3: one index computation per run
    of taps), zero between calls: the kernel zeroes what it adds."""
    key = f"{lanes} {shape} {dtype}"
    if key not in _lane_buffers:
        _lane_buffers[key] = ti.ndarray(dtype, (lanes * int(np.prod(shape)),))
        _lane_buffers[key].fill(0.0)
    return _lane_buffers[key]
