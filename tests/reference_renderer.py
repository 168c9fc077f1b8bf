"""A deliberately simple NumPy Gaussian-splat renderer: no tiles, every pixel blends every Gaussian
in global depth order, with the same image-formation rules as the Taichi rasterizer.

Split into the rasterizer's parts so each can be tested alone: :func:`project` (screen records and
pixel boxes), :func:`bin_tiles` (per-tile depth-sorted lists) and :func:`blend_tiles` (per-tile
front-to-back blending); :func:`render` is projection + one global blend."""

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


def project(means, quats, log_scales, opacity_logits, colors, K, cam_to_world, width, height) -> dict:
    """The per-Gaussian part: screen-space records, as the rasterizer's projection writes them.

    Returns arrays over all N Gaussians: ``visible`` (culled: behind the near plane, opacity under
    1/255, degenerate, or a pixel box outside the image), ``mean2d`` (N, 2), ``conic`` (N, 3) =
    (a, b, c) of the inverse 2D covariance, ``depth``, ``opacity``, ``color`` (N, 3), ``cutoff``
    (the power below which a pixel gets nothing: -ext^2 / 2) and ``rect`` (N, 4) int pixel box
    (u0, v0, u1, v1) of the support. Invisible rows hold zeros."""
    means = np.asarray(means, np.float64)
    colors = np.asarray(colors, np.float64)
    if colors.ndim == 2:
        colors = colors[:, None, :]
    n = len(means)
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
    out = {"visible": np.zeros(n, bool), "mean2d": np.zeros((n, 2)), "conic": np.zeros((n, 3)),
           "depth": np.zeros(n), "opacity": np.zeros(n), "color": np.zeros((n, 3)), "cutoff": np.zeros(n),
           "rect": np.zeros((n, 4), np.int64)}
    for i in range(n):
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
        ext = min(3.0, np.sqrt(2 * np.log(255 * opacity[i])))
        if np.linalg.det(cov2) <= 0 or ext <= 0:
            continue
        mean2d = np.array([fx * p[i, 0] / z + cx, fy * p[i, 1] / z + cy])
        # the support's pixel box: pixel u samples u + 0.5; widened by 1e-4 so no pixel is lost to rounding
        rx = ext * np.sqrt(cov2[0, 0]) * (1 + 1e-4) + 1e-4
        ry = ext * np.sqrt(cov2[1, 1]) * (1 + 1e-4) + 1e-4
        u0, u1 = max(np.ceil(mean2d[0] - rx - 0.5), 0), min(np.floor(mean2d[0] + rx - 0.5), width - 1)
        v0, v1 = max(np.ceil(mean2d[1] - ry - 0.5), 0), min(np.floor(mean2d[1] + ry - 0.5), height - 1)
        if u0 > u1 or v0 > v1:
            continue
        conic = np.linalg.inv(cov2)
        out["visible"][i] = True
        out["mean2d"][i] = mean2d
        out["conic"][i] = conic[0, 0], conic[0, 1], conic[1, 1]
        out["depth"][i], out["opacity"][i], out["color"][i] = z, opacity[i], col[i]
        out["cutoff"][i] = -0.5 * ext * ext
        out["rect"][i] = u0, v0, u1, v1
    return out


def bin_tiles(records: dict, width: int, height: int, tile: int = 16) -> list[np.ndarray]:
    """The binning part: per tile (row-major), the visible Gaussians whose pixel box touches it,
    front to back, equal depths by index."""
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    lists: list[list[int]] = [[] for _ in range(tiles_x * tiles_y)]
    for i in np.flatnonzero(records["visible"]):
        u0, v0, u1, v1 = records["rect"][i] // tile
        for ty in range(v0, v1 + 1):
            for tx in range(u0, u1 + 1):
                lists[ty * tiles_x + tx].append(int(i))
    depth = records["depth"]
    return [np.array(sorted(ids, key=lambda i: (depth[i], i)), np.int64) for ids in lists]


def _blend(records: dict, ids, px, py, background, support_cutoff: bool = True):
    """Front-to-back blending of Gaussians ``ids`` (in order) at pixel centres (px, py):
    (rgb, depth, alpha, index in ``ids`` of the last contributor or -1)."""
    T = np.ones(px.shape)
    rgb = np.zeros(px.shape + (3,))
    depth = np.zeros(px.shape)
    last = np.full(px.shape, -1)
    done = np.zeros(px.shape, bool)
    for k, i in enumerate(ids):
        (a, b, c), (mx, my) = records["conic"][i], records["mean2d"][i]
        dx, dy = mx - px, my - py
        power = -0.5 * (a * dx * dx + c * dy * dy) - b * dx * dy
        alpha = np.minimum(0.99, records["opacity"][i] * np.exp(power))
        hit = ~done & (alpha >= 1 / 255)
        if support_cutoff:
            hit &= power >= records["cutoff"][i]
        next_T = T * (1 - alpha)
        stop = hit & (next_T < 1e-4)
        done |= stop
        use = hit & ~stop
        w = np.where(use, alpha * T, 0.0)
        rgb += w[..., None] * records["color"][i]
        depth += w * records["depth"][i]
        T = np.where(use, next_T, T)
        last = np.where(use, k, last)
    rgb += T[..., None] * np.asarray(background, np.float64)
    return rgb, depth, 1 - T, last


def blend_tiles(records: dict, tile_lists: list[np.ndarray], width: int, height: int, background=(0, 0, 0),
                tile: int = 16):
    """The blending part, tile by tile from :func:`bin_tiles`' lists: (rgb, depth, alpha, last) with
    ``last`` the tile-local index of each pixel's last contributor (-1 for none)."""
    tiles_x = -(-width // tile)
    rgb, depth, alpha = np.zeros((height, width, 3)), np.zeros((height, width)), np.zeros((height, width))
    last = np.full((height, width), -1)
    for t, ids in enumerate(tile_lists):
        u0, v0 = (t % tiles_x) * tile, (t // tiles_x) * tile
        v, u = np.mgrid[v0:min(v0 + tile, height), u0:min(u0 + tile, width)]
        part = _blend(records, ids, u + 0.5, v + 0.5, background)
        for full, got in zip((rgb, depth, alpha, last), part):
            full[v, u] = got
    return rgb, depth, alpha, last


def render(means, quats, log_scales, opacity_logits, colors, K, cam_to_world, width, height, background=(0, 0, 0),
           support_cutoff: bool = True):
    """(rgb, depth, alpha) in float64: every pixel blends every Gaussian in global depth order.

    ``support_cutoff=False`` is the published 3DGS image formation: no per-pixel cut at 3 sigma (a
    Gaussian reaches every pixel where its alpha is at least 1/255; 3DGS's tile rectangles of
    3 sqrt(largest eigenvalue) approximate that set), everything else the same."""
    records = project(means, quats, log_scales, opacity_logits, colors, K, cam_to_world, width, height)
    ids = sorted(np.flatnonzero(records["visible"]), key=lambda i: (records["depth"][i], i))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rgb, depth, alpha, _ = _blend(records, ids, u + 0.5, v + 0.5, background, support_cutoff)
    return rgb, depth, alpha
