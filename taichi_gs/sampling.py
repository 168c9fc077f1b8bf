"""NumPy images sampled at N sub-pixel coordinates (OpenCV's convention: pixel centres at integers), (N, 2)
arrays of (u, v): bilinear colour or grey, bilinear depth with its image gradient, the nearest pixel."""

from __future__ import annotations

import numpy as np


def bilinear(image: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear samples of an H x W (x C) image at N pixels, and the mask of pixels inside it."""
    u0, v0, a, b, inside = _cells(pixels, image.shape[:2])
    if image.ndim == 3:
        a, b = a[:, None], b[:, None]
    top = (1 - a) * image[v0, u0] + a * image[v0, u0 + 1]
    bottom = (1 - a) * image[v0 + 1, u0] + a * image[v0 + 1, u0 + 1]
    return (1 - b) * top + b * bottom, inside


def bilinear_depth(depth: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear depth, its exact image gradient (N x 2), and validity (inside, four valid neighbours)."""
    u0, v0, a, b, inside = _cells(pixels, depth.shape)
    d00, d01 = depth[v0, u0], depth[v0, u0 + 1]
    d10, d11 = depth[v0 + 1, u0], depth[v0 + 1, u0 + 1]
    valid = inside & (d00 > 0) & (d01 > 0) & (d10 > 0) & (d11 > 0)
    value = (1 - b) * ((1 - a) * d00 + a * d01) + b * ((1 - a) * d10 + a * d11)
    du = (1 - b) * (d01 - d00) + b * (d11 - d10)
    dv = (1 - a) * (d10 - d00) + a * (d11 - d01)
    return value, np.stack([du, dv], axis=1), valid


def nearest_pixel(pixels: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Column and row (each N) of the image pixel nearest each of N pixel coordinates, clipped into an
    H x W ``shape`` (non-finite coordinates go to 0)."""
    u = np.clip(np.round(np.nan_to_num(pixels[:, 0])).astype(np.int64), 0, shape[1] - 1)
    v = np.clip(np.round(np.nan_to_num(pixels[:, 1])).astype(np.int64), 0, shape[0] - 1)
    return u, v


def _cells(pixels: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                                                np.ndarray]:
    """Each pixel's 2 x 2 cell of an H x W ``shape``: its top-left corner (u0, v0), the offsets (a, b) into it,
    and the mask of pixels inside the image (outside ones get the cell at the origin)."""
    h, w = shape
    u, v = pixels[:, 0], pixels[:, 1]
    inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    u = np.where(inside, u, 0.0)
    v = np.where(inside, v, 0.0)
    u0 = np.minimum(np.floor(u).astype(np.int64), w - 2)
    v0 = np.minimum(np.floor(v).astype(np.int64), h - 2)
    return u0, v0, u - u0, v - v0, inside
