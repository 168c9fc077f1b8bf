"""A deliberately simple NumPy Gaussian-splat renderer: no tiles, every pixel blends every Gaussian
in global depth order, with the same image-formation rules as the Taichi rasterizer."""

from __future__ import annotations

import numpy as np

from taichi_gs.geometry import quat_to_rotmat

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
C3 = [-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
      -0.4570457994644658, 1.445305721320277, -0.5900435899266435]


def sh_basis(d: np.ndarray) -> np.ndarray:
    """(N, 16) real SH basis at unit directions d (N, 3), 3DGS signs."""
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    xx, yy, zz = x * x, y * y, z * z
    return np.stack([
        np.full_like(x, C0), -C1 * y, C1 * z, -C1 * x,
        C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy),
        C3[0] * y * (3 * xx - yy), C3[1] * x * y * z, C3[2] * y * (4 * zz - xx - yy),
        C3[3] * z * (2 * zz - 3 * xx - 3 * yy), C3[4] * x * (4 * zz - xx - yy), C3[5] * z * (xx - yy),
        C3[6] * x * (xx - 3 * yy),
    ], axis=1)


def render(means, quats, log_scales, opacity_logits, colors, K, cam_to_world, width, height, background=(0, 0, 0)):
    """(rgb, depth, alpha) in float64."""
    means = np.asarray(means, np.float64)
    colors = np.asarray(colors, np.float64)
    if colors.ndim == 2:
        colors = colors[:, None, :]
    R, t = cam_to_world[:3, :3], cam_to_world[:3, 3]
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    d = means - t
    p = d @ R  # R^T d per row
    opacity = 1 / (1 + np.exp(-np.asarray(opacity_logits, np.float64)))
    dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
    basis = sh_basis(dirs)[:, : colors.shape[1]]
    col = np.maximum(np.einsum("nk,nkc->nc", basis, colors) + 0.5, 0.0)

    tan_x, tan_y = 0.5 * width / fx, 0.5 * height / fy
    lim = [(cx / fx + 0.3 * tan_x, (width - cx) / fx + 0.3 * tan_x),
           (cy / fy + 0.3 * tan_y, (height - cy) / fy + 0.3 * tan_y)]
    splats = []
    for i in range(len(means)):
        z = p[i, 2]
        if z < 0.01 or opacity[i] < 1 / 255:
            continue
        rot = quat_to_rotmat(quats[i])
        m = rot * np.exp(log_scales[i])
        cov_c = R.T @ (m @ m.T) @ R
        tx = z * np.clip(p[i, 0] / z, -lim[0][0], lim[0][1])
        ty = z * np.clip(p[i, 1] / z, -lim[1][0], lim[1][1])
        J = np.array([[fx / z, 0, -fx * tx / z**2], [0, fy / z, -fy * ty / z**2]])
        cov2 = J @ cov_c @ J.T + 0.3 * np.eye(2)
        if np.linalg.det(cov2) <= 0:
            continue
        ext = min(3.0, np.sqrt(2 * np.log(255 * opacity[i])))
        mean2d = np.array([fx * p[i, 0] / z + cx, fy * p[i, 1] / z + cy])
        splats.append((z, i, mean2d, np.linalg.inv(cov2), -0.5 * ext * ext))
    splats.sort(key=lambda s: (s[0], s[1]))

    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    px, py = u + 0.5, v + 0.5
    T = np.ones((height, width))
    rgb = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    done = np.zeros((height, width), bool)
    for z, i, mean2d, conic, cutoff in splats:
        dx, dy = mean2d[0] - px, mean2d[1] - py
        power = -0.5 * (conic[0, 0] * dx * dx + conic[1, 1] * dy * dy) - conic[0, 1] * dx * dy
        alpha = np.minimum(0.99, opacity[i] * np.exp(power))
        hit = ~done & (power >= cutoff) & (alpha >= 1 / 255)
        next_T = T * (1 - alpha)
        stop = hit & (next_T < 1e-4)
        done |= stop
        use = hit & ~stop
        w = np.where(use, alpha * T, 0.0)
        rgb += w[..., None] * col[i]
        depth += w * z
        T = np.where(use, next_T, T)
    rgb += T[..., None] * np.asarray(background, np.float64)
    return rgb, depth, 1 - T
