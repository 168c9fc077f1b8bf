"""Per-Gaussian projection: world Gaussian -> screen-space mean, conic, depth, extent and colour.

Image formation (3DGS / gsplat conventions):
- camera-space point ``p = R^T (mean - t)`` for a camera-to-world pose ``[R | t]``;
- EWA splatting ``cov2d = J W cov3d W^T J^T + 0.3 I`` with the perspective Jacobian ``J`` taken at
  ``x/z, y/z`` clamped to 1.3x the frustum (gsplat's form), ``mean2d = (fx x/z + cx, fy y/z + cy)``;
  pixel ``(u, v)`` samples image coordinate ``(u + 0.5, v + 0.5)``;
- support: a pixel receives a Gaussian when ``o * exp(power) >= 1/255`` and the Mahalanobis
  distance is at most 3 (``power >= -4.5``); the screen extent ``ext * sqrt(cov2d_xx)`` with
  ``ext = min(3, sqrt(2 ln(255 o)))`` bounds exactly that set, so tiling never changes the image;
- colour: SH of degree 0..3 with 3DGS constants, view direction from the camera centre to the mean,
  ``colour = max(SH + 0.5, 0)`` (degree 0: ``colour = 0.2820948 * dc + 0.5``).

The vector-Jacobian products are derived by hand; all maths is built per float dtype by
:func:`make` so gradient tests run in f64 next to f32 production kernels.
"""

import functools
from types import SimpleNamespace

import taichi as ti

Array = ti.template()  # an ndarray argument of a ti.func (passed by reference)

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)
NEAR_PLANE = 0.01
LOW_PASS = 0.3
ALPHA_MIN = 1.0 / 255.0
MAX_SIGMA = 3.0
FRUSTUM_CLAMP = 1.3

# Columns of the per-Gaussian screen-space record written by the projection.
P_MEAN_X, P_MEAN_Y, P_CONIC_A, P_CONIC_B, P_CONIC_C, P_DEPTH, P_OPACITY = range(7)
P_COLOR = 7  # 7, 8, 9
P_CUTOFF = 10  # power below which the pixel gets nothing: -ext^2 / 2
P_WIDTH = 11
# A screen record's gradient holds the differentiable columns: P_MEAN_X .. P_COLOR + 2 (not the cut-off).
N_GRADS = P_CUTOFF


@functools.cache
def make(dt) -> SimpleNamespace:
    """ti.funcs of the projection and its backward for float type ``dt``."""
    vec3 = ti.types.vector(3, dt)
    vec4 = ti.types.vector(4, dt)
    mat3 = ti.types.matrix(3, 3, dt)
    mat23 = ti.types.matrix(2, 3, dt)

    @ti.func
    def quat_to_rotmat(q):
        """Rotation of a unit quaternion [w, x, y, z]."""
        w, x, y, z = q[0], q[1], q[2], q[3]
        return mat3(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )

    @ti.func
    def quat_to_rotmat_vjp(q, G):
        """Gradient w.r.t. the unit quaternion q of <G, R(q)>."""
        w, x, y, z = q[0], q[1], q[2], q[3]
        gw = 2 * (-z * G[0, 1] + y * G[0, 2] + z * G[1, 0] - x * G[1, 2] - y * G[2, 0] + x * G[2, 1])
        gx = 2 * (
            y * G[0, 1] + z * G[0, 2] + y * G[1, 0] - 2 * x * G[1, 1] - w * G[1, 2]
            + z * G[2, 0] + w * G[2, 1] - 2 * x * G[2, 2]
        )
        gy = 2 * (
            -2 * y * G[0, 0] + x * G[0, 1] + w * G[0, 2] + x * G[1, 0] + z * G[1, 2]
            - w * G[2, 0] + z * G[2, 1] - 2 * y * G[2, 2]
        )
        gz = 2 * (
            -2 * z * G[0, 0] - w * G[0, 1] + x * G[0, 2] + w * G[1, 0] - 2 * z * G[1, 1]
            + y * G[1, 2] + x * G[2, 0] + y * G[2, 1]
        )
        return vec4(gw, gx, gy, gz)

    @ti.func
    def sh_basis(d):
        """The 16 real SH basis values of unit direction d (3DGS sign conventions)."""
        x, y, z = d[0], d[1], d[2]
        xx, yy, zz = x * x, y * y, z * z
        return ti.Vector(
            [
                dt(SH_C0),
                -dt(SH_C1) * y,
                dt(SH_C1) * z,
                -dt(SH_C1) * x,
                dt(SH_C2[0]) * x * y,
                dt(SH_C2[1]) * y * z,
                dt(SH_C2[2]) * (2 * zz - xx - yy),
                dt(SH_C2[3]) * x * z,
                dt(SH_C2[4]) * (xx - yy),
                dt(SH_C3[0]) * y * (3 * xx - yy),
                dt(SH_C3[1]) * x * y * z,
                dt(SH_C3[2]) * y * (4 * zz - xx - yy),
                dt(SH_C3[3]) * z * (2 * zz - 3 * xx - 3 * yy),
                dt(SH_C3[4]) * x * (4 * zz - xx - yy),
                dt(SH_C3[5]) * z * (xx - yy),
                dt(SH_C3[6]) * x * (xx - 3 * yy),
            ],
            dt=dt,
        )

    @ti.func
    def sh_basis_jacobian(d):
        """16 x 3 derivatives of :func:`sh_basis` w.r.t. the (unnormalised) components of d."""
        x, y, z = d[0], d[1], d[2]
        xx, yy, zz = x * x, y * y, z * z
        return ti.Matrix(
            [
                [0.0, 0.0, 0.0],
                [0.0, -dt(SH_C1), 0.0],
                [0.0, 0.0, dt(SH_C1)],
                [-dt(SH_C1), 0.0, 0.0],
                [dt(SH_C2[0]) * y, dt(SH_C2[0]) * x, 0.0],
                [0.0, dt(SH_C2[1]) * z, dt(SH_C2[1]) * y],
                [-2 * dt(SH_C2[2]) * x, -2 * dt(SH_C2[2]) * y, 4 * dt(SH_C2[2]) * z],
                [dt(SH_C2[3]) * z, 0.0, dt(SH_C2[3]) * x],
                [2 * dt(SH_C2[4]) * x, -2 * dt(SH_C2[4]) * y, 0.0],
                [6 * dt(SH_C3[0]) * x * y, dt(SH_C3[0]) * (3 * xx - 3 * yy), 0.0],
                [dt(SH_C3[1]) * y * z, dt(SH_C3[1]) * x * z, dt(SH_C3[1]) * x * y],
                [-2 * dt(SH_C3[2]) * x * y, dt(SH_C3[2]) * (4 * zz - xx - 3 * yy), 8 * dt(SH_C3[2]) * y * z],
                [-6 * dt(SH_C3[3]) * x * z, -6 * dt(SH_C3[3]) * y * z, dt(SH_C3[3]) * (6 * zz - 3 * xx - 3 * yy)],
                [dt(SH_C3[4]) * (4 * zz - 3 * xx - yy), -2 * dt(SH_C3[4]) * x * y, 8 * dt(SH_C3[4]) * x * z],
                [2 * dt(SH_C3[5]) * x * z, -2 * dt(SH_C3[5]) * y * z, dt(SH_C3[5]) * (xx - yy)],
                [dt(SH_C3[6]) * (3 * xx - 3 * yy), -6 * dt(SH_C3[6]) * x * y, 0.0],
            ],
            dt=dt,
        )

    @ti.func
    def clamp_to_frustum(p, lim_neg, lim_pos):
        """(tx, ty, clamped_x, clamped_y, bound_x, bound_y): p.xy with x/z, y/z clamped."""
        rx = p[0] / p[2]
        ry = p[1] / p[2]
        bx = ti.min(lim_pos[0], ti.max(-lim_neg[0], rx))
        by = ti.min(lim_pos[1], ti.max(-lim_neg[1], ry))
        return ti.Vector([p[2] * bx, p[2] * by, bx, by, ti.cast(bx != rx, dt), ti.cast(by != ry, dt)], dt=dt)

    @ti.func
    def ewa_jacobian(tx, ty, z, fx, fy):
        return mat23([[fx / z, 0.0, -fx * tx / (z * z)], [0.0, fy / z, -fy * ty / (z * z)]])

    @ti.func
    def support_extent(opacity):
        """Sigma multiple bounding the pixels a Gaussian of this opacity reaches (0 when none)."""
        ext = ti.cast(0.0, dt)
        if opacity >= dt(ALPHA_MIN):
            ext = ti.min(dt(MAX_SIGMA), ti.sqrt(2.0 * ti.log(opacity / dt(ALPHA_MIN))))
        return ext

    @ti.func
    def camera_covariance(g, quats: Array, log_scales: Array, view_rot, isotropic: ti.template()):
        """Covariance of Gaussian g in camera axes (view_rot = R^T of the camera-to-world pose)."""
        cov = mat3(0.0)
        if ti.static(isotropic):
            s = ti.exp(log_scales[g, 0])
            cov = s * s * ti.Matrix.identity(dt, 3)
        else:
            q = vec4(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3])
            rot = quat_to_rotmat(q / q.norm())
            scale = vec3(ti.exp(log_scales[g, 0]), ti.exp(log_scales[g, 1]), ti.exp(log_scales[g, 2]))
            m = rot @ ti.Matrix([[scale[0], 0.0, 0.0], [0.0, scale[1], 0.0], [0.0, 0.0, scale[2]]], dt=dt)
            cov = view_rot @ (m @ m.transpose()) @ view_rot.transpose()
        return cov

    @ti.func
    def frustum_limits(intr, width, height):
        """(neg_x, neg_y, pos_x, pos_y) bounds of x/z, y/z used in the EWA Jacobian."""
        tan_x = 0.5 * width / intr[0]
        tan_y = 0.5 * height / intr[1]
        pad = dt(FRUSTUM_CLAMP - 1.0)
        return ti.Vector(
            [
                intr[2] / intr[0] + pad * tan_x,
                intr[3] / intr[1] + pad * tan_y,
                (width - intr[2]) / intr[0] + pad * tan_x,
                (height - intr[3]) / intr[1] + pad * tan_y,
            ],
            dt=dt,
        )

    @ti.func
    def view_basis(direction, view_dependent: ti.template()):
        """:func:`sh_basis` of unit ``direction`` when ``view_dependent`` (static), else zeros: with one SH
        coefficient per Gaussian (degree 0) only the constant DC term is used, and the higher bands are not
        compiled at all (they are most of the rasterizer's compile time)."""
        basis = ti.Vector.zero(dt, 16)
        if ti.static(view_dependent):
            basis = sh_basis(direction)
        return basis

    @ti.func
    def view_color(g, sh: Array, n_sh, basis, view_dependent: ti.template()):
        """SH colour + 0.5 before the clamp at 0 (3 channels), given :func:`view_basis`; without
        ``view_dependent`` (static) only the DC term is read."""
        col = vec3(0.5) + dt(SH_C0) * vec3(sh[g, 0, 0], sh[g, 0, 1], sh[g, 0, 2])
        if ti.static(view_dependent):
            for k in ti.static(range(1, 16)):
                if k < n_sh:
                    col += basis[k] * vec3(sh[g, k, 0], sh[g, k, 1], sh[g, k, 2])
        return col

    @ti.func
    def project_one(
        g,  # Gaussian index
        means: Array,  # (N, 3) world centres
        quats: Array,  # (N, 4) rotations [w, x, y, z], not necessarily unit (unused when isotropic)
        log_scales: Array,  # (N, 3), or (N, 1) when isotropic
        logits: Array,  # (N,) opacity logits
        sh: Array,  # (N, >= n_sh, 3) SH coefficients
        n_sh,  # SH coefficients used: 1, 4, 9 or 16
        cam,  # 4x4 camera-to-world pose
        intr,  # (fx, fy, cx, cy), pixel centres at +0.5
        width,
        height,
        proj: Array,  # output (N, P_WIDTH): screen record, written for visible Gaussians only
        rect: Array,  # output (N, 4) i32: pixel box u0, v0, u1, v1 (u0 > u1 when culled)
        isotropic: ti.template(),
        view_dependent: ti.template(),  # n_sh > 1 (see view_color)
    ):
        """Project Gaussian g; write its screen record proj[g] and clipped pixel box rect[g]
        (rect[g, 0] > rect[g, 2] marks a culled Gaussian)."""
        rot_c = ti.Matrix([[cam[i, j] for j in ti.static(range(3))] for i in ti.static(range(3))], dt=dt)
        t_c = vec3(cam[0, 3], cam[1, 3], cam[2, 3])
        d = vec3(means[g, 0], means[g, 1], means[g, 2]) - t_c
        view_rot = rot_c.transpose()
        p = view_rot @ d
        rect[g, 0] = 1
        rect[g, 2] = 0
        if p[2] >= dt(NEAR_PLANE):
            cov_c = camera_covariance(g, quats, log_scales, view_rot, isotropic)
            lim = frustum_limits(intr, width, height)
            cl = clamp_to_frustum(p, ti.Vector([lim[0], lim[1]]), ti.Vector([lim[2], lim[3]]))
            jac = ewa_jacobian(cl[0], cl[1], p[2], intr[0], intr[1])
            cov2 = jac @ cov_c @ jac.transpose()
            ca = cov2[0, 0] + dt(LOW_PASS)
            cb = cov2[0, 1]
            cc = cov2[1, 1] + dt(LOW_PASS)
            det = ca * cc - cb * cb
            opacity = 1.0 / (1.0 + ti.exp(-logits[g]))
            ext = support_extent(opacity)
            if det > 0.0 and ext > 0.0:
                mx = intr[0] * p[0] / p[2] + intr[2]
                my = intr[1] * p[1] / p[2] + intr[3]
                rx = ext * ti.sqrt(ca) * (1.0 + 1e-4) + 1e-4
                ry = ext * ti.sqrt(cc) * (1.0 + 1e-4) + 1e-4
                u0 = ti.max(ti.ceil(mx - rx - 0.5), 0.0)
                u1 = ti.min(ti.floor(mx + rx - 0.5), width - 1.0)
                v0 = ti.max(ti.ceil(my - ry - 0.5), 0.0)
                v1 = ti.min(ti.floor(my + ry - 0.5), height - 1.0)
                if u0 <= u1 and v0 <= v1:
                    rect[g, 0] = ti.cast(u0, ti.i32)
                    rect[g, 1] = ti.cast(v0, ti.i32)
                    rect[g, 2] = ti.cast(u1, ti.i32)
                    rect[g, 3] = ti.cast(v1, ti.i32)
                    col = ti.max(view_color(g, sh, n_sh, view_basis(d / d.norm(), view_dependent), view_dependent), 0.0)
                    proj[g, P_MEAN_X] = mx
                    proj[g, P_MEAN_Y] = my
                    proj[g, P_CONIC_A] = cc / det
                    proj[g, P_CONIC_B] = -cb / det
                    proj[g, P_CONIC_C] = ca / det
                    proj[g, P_DEPTH] = p[2]
                    proj[g, P_OPACITY] = opacity
                    for c in ti.static(range(3)):
                        proj[g, P_COLOR + c] = col[c]
                    proj[g, P_CUTOFF] = -0.5 * ext * ext

    @ti.func
    def project_one_vjp(
        g,  # Gaussian index (visible)
        means: Array,  # (N, 3)  -- the inputs as in project_one
        quats: Array,  # (N, 4)
        log_scales: Array,  # (N, 3) or (N, 1)
        logits: Array,  # (N,)
        sh: Array,  # (N, >= n_sh, 3)
        n_sh,
        cam,  # 4x4 camera-to-world
        intr,  # (fx, fy, cx, cy)
        width,
        height,
        gs,  # N_GRADS-vector: dL/d(screen record)
        isotropic: ti.template(),
        view_dependent: ti.template(),
        d_means: Array,  # output (N, 3), added to
        d_quats: Array,  # output (N, 4), added to (untouched when isotropic)
        d_log_scales: Array,  # output (N, 3), added to (untouched when isotropic)
        d_logits: Array,  # output (N,), added to
        d_sh: Array,  # output (N, >= n_sh, 3), added to
    ):
        """Backward of :func:`project_one` for a visible Gaussian g.

        ``gs`` holds dL/d(screen record) in the record's column order (``P_MEAN_X`` .. ``P_COLOR + 2``,
        :data:`N_GRADS` values; the conic's b is the shared off-diagonal entry). Accumulates parameter
        gradients (+=) and returns the 6-vector pose gradient [translation, rotation] of this Gaussian
        (left perturbation).
        """
        rot_c = ti.Matrix([[cam[i, j] for j in ti.static(range(3))] for i in ti.static(range(3))], dt=dt)
        t_c = vec3(cam[0, 3], cam[1, 3], cam[2, 3])
        d = vec3(means[g, 0], means[g, 1], means[g, 2]) - t_c
        view_rot = rot_c.transpose()
        p = view_rot @ d
        fx, fy = intr[0], intr[1]
        z = p[2]

        # colour: clamp mask, SH coefficients and the view direction
        dist = d.norm()
        direction = d / dist
        basis = view_basis(direction, view_dependent)
        raw = view_color(g, sh, n_sh, basis, view_dependent)
        g_col = vec3(0.0)
        for c in ti.static(range(3)):
            if raw[c] > 0.0:
                g_col[c] = gs[P_COLOR + c]
        for c in ti.static(range(3)):
            d_sh[g, 0, c] = d_sh[g, 0, c] + dt(SH_C0) * g_col[c]
        g_d = vec3(0.0)
        if ti.static(view_dependent):  # degree 0 does not depend on the view direction
            for k in ti.static(range(1, 16)):
                if k < n_sh:
                    for c in ti.static(range(3)):
                        d_sh[g, k, c] = d_sh[g, k, c] + basis[k] * g_col[c]
            jac_sh = sh_basis_jacobian(direction)
            g_dir = vec3(0.0)
            for k in ti.static(range(1, 16)):
                if k < n_sh:
                    w = vec3(sh[g, k, 0], sh[g, k, 1], sh[g, k, 2]).dot(g_col)
                    g_dir += w * vec3(jac_sh[k, 0], jac_sh[k, 1], jac_sh[k, 2])
            g_d = (g_dir - direction * direction.dot(g_dir)) / dist

        # opacity through the sigmoid
        opacity = 1.0 / (1.0 + ti.exp(-logits[g]))
        d_logits[g] = d_logits[g] + gs[P_OPACITY] * opacity * (1.0 - opacity)

        # conic -> 2D covariance -> camera covariance and Jacobian
        cov_c = camera_covariance(g, quats, log_scales, view_rot, isotropic)
        lim = frustum_limits(intr, width, height)
        cl = clamp_to_frustum(p, ti.Vector([lim[0], lim[1]]), ti.Vector([lim[2], lim[3]]))
        jac = ewa_jacobian(cl[0], cl[1], z, fx, fy)
        cov2 = jac @ cov_c @ jac.transpose() + dt(LOW_PASS) * ti.Matrix.identity(dt, 2)
        conic = cov2.inverse()
        g_conic = ti.Matrix(
            [[gs[P_CONIC_A], 0.5 * gs[P_CONIC_B]], [0.5 * gs[P_CONIC_B], gs[P_CONIC_C]]], dt=dt
        )
        g_cov2 = -conic @ g_conic @ conic
        g_cov_c = jac.transpose() @ g_cov2 @ jac
        g_jac = 2.0 * g_cov2 @ jac @ cov_c
        z2 = z * z
        g_tx = -g_jac[0, 2] * fx / z2
        g_ty = -g_jac[1, 2] * fy / z2
        g_p = vec3(0.0)
        g_p[2] = (
            -g_jac[0, 0] * fx / z2
            + g_jac[0, 2] * 2.0 * fx * cl[0] / (z2 * z)
            - g_jac[1, 1] * fy / z2
            + g_jac[1, 2] * 2.0 * fy * cl[1] / (z2 * z)
        )
        if cl[4] > 0.0:
            g_p[2] += g_tx * cl[2]
        else:
            g_p[0] += g_tx
        if cl[5] > 0.0:
            g_p[2] += g_ty * cl[3]
        else:
            g_p[1] += g_ty
        # mean2d and depth
        g_p[0] += gs[P_MEAN_X] * fx / z
        g_p[1] += gs[P_MEAN_Y] * fy / z
        g_p[2] += -(gs[P_MEAN_X] * fx * p[0] + gs[P_MEAN_Y] * fy * p[1]) / z2 + gs[P_DEPTH]

        # p = view_rot @ d
        g_d += view_rot.transpose() @ g_p
        g_view = g_p.outer_product(d)
        if ti.static(not isotropic):
            q_raw = vec4(quats[g, 0], quats[g, 1], quats[g, 2], quats[g, 3])
            q_norm = q_raw.norm()
            q = q_raw / q_norm
            rot = quat_to_rotmat(q)
            scale = vec3(ti.exp(log_scales[g, 0]), ti.exp(log_scales[g, 1]), ti.exp(log_scales[g, 2]))
            m = rot @ ti.Matrix([[scale[0], 0.0, 0.0], [0.0, scale[1], 0.0], [0.0, 0.0, scale[2]]], dt=dt)
            cov_w = m @ m.transpose()
            g_view += 2.0 * g_cov_c @ view_rot @ cov_w
            g_cov_w = view_rot.transpose() @ g_cov_c @ view_rot
            g_m = 2.0 * g_cov_w @ m
            g_rot = mat3(0.0)
            for k in ti.static(range(3)):
                g_s = ti.cast(0.0, dt)
                for i in ti.static(range(3)):
                    g_s += rot[i, k] * g_m[i, k]
                    g_rot[i, k] = g_m[i, k] * scale[k]
                d_log_scales[g, k] = d_log_scales[g, k] + g_s * scale[k]
            g_q = quat_to_rotmat_vjp(q, g_rot)
            g_q = (g_q - q * q.dot(g_q)) / q_norm
            for k in ti.static(range(4)):
                d_quats[g, k] = d_quats[g, k] + g_q[k]

        for k in ti.static(range(3)):
            d_means[g, k] = d_means[g, k] + g_d[k]
        # pose: d = mean - t_c, view_rot = R_c^T; left perturbation [rho, phi]
        g_t = -g_d
        b = rot_c @ g_view
        g_phi = vec3(b[1, 2] - b[2, 1], b[2, 0] - b[0, 2], b[0, 1] - b[1, 0]) + t_c.cross(g_t)
        return ti.Vector([g_t[0], g_t[1], g_t[2], g_phi[0], g_phi[1], g_phi[2]], dt=dt)

    @ti.func
    def slots_vjp(
        g,  # the Gaussian
        first,  # its slots are first .. last - 1 of slot_grad
        last,
        slot_grad: Array,  # (S, N_GRADS) dL/d(screen record) per tile slot
        means: Array,
        quats: Array,
        log_scales: Array,
        logits: Array,
        sh: Array,
        n_sh,
        cam,
        intr,
        width,
        height,
        isotropic: ti.template(),
        view_dependent: ti.template(),
        d_means: Array,  # output, added to (as project_one_vjp)
        d_quats: Array,
        d_log_scales: Array,
        d_logits: Array,
        d_sh: Array,
    ):
        """Sum Gaussian g's slot gradients (one slot per tile it touches) and back-propagate them
        through :func:`project_one_vjp`; returns its pose gradient (zero when it touches no tile)."""
        pose = ti.Vector.zero(dt, 6)
        if last > first:
            gs = ti.Vector.zero(dt, N_GRADS)
            for s in range(first, last):
                for c in ti.static(range(N_GRADS)):
                    gs[c] += slot_grad[s, c]
            pose = project_one_vjp(g, means, quats, log_scales, logits, sh, n_sh, cam, intr, width, height, gs,
                                   isotropic, view_dependent, d_means, d_quats, d_log_scales, d_logits, d_sh)
        return pose

    return SimpleNamespace(
        project_one=project_one,
        project_one_vjp=project_one_vjp,
        slots_vjp=slots_vjp,
        vec3=vec3,
        vec4=vec4,
        mat3=mat3,
        mat23=mat23,
        quat_to_rotmat=quat_to_rotmat,
        quat_to_rotmat_vjp=quat_to_rotmat_vjp,
        sh_basis=sh_basis,
        sh_basis_jacobian=sh_basis_jacobian,
        clamp_to_frustum=clamp_to_frustum,
        ewa_jacobian=ewa_jacobian,
        support_extent=support_extent,
    )
