"""[ours] One verification score for any candidate relative pose of two RGB-D frames.

Every candidate (flow solve, ICP, RGB-D odometry, constant velocity) is scored the same way, so the
stage can pick the best one and call a pair weak from the score rather than from ICP's own fitness,
which stays high when ICP slides along a plane. For a transform T (camera a -> camera b):

- a fixed grid of pixels of frame a with reliable depth is moved by T and projected into frame b;
- geometric residual: point-to-plane distance to frame b's surface at that pixel,
  ``r_g = n_b . (T P_a - P_b)``, scaled by the depth sensor's noise ``sigma(z) = s0 + s2 z^2`` and by
  how much of it bilinear interpolation leaves where the point lands (:func:`interpolation_noise`);
- photometric residual: grey value of a minus grey value of b at the warped pixel (both lightly
  smoothed, each minus its mean over the overlap so a global brightness change does not count),
  scaled by ``sigma_photo``; colour constrains motion along planes, where depth alone cannot;
- each residual goes through the bounded Geman-McClure loss ``r^2 / (r^2 + sigma^2)`` (0 = perfect,
  1 = outlier), so occlusions and moving objects cost at most one unit per pixel;
- the same is done backwards (frame b's pixels moved by T^-1 into frame a), and the two directions are
  averaged: a candidate must explain both frames (forward-backward consistency).

The score is the mean robust cost over the overlap, in [0, 1]; lower is better. ``overlap`` is the
smaller of the two directions' fractions of grid pixels that land on valid depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from . import profiling
from .geometry import backproject, project, transform
from .icp import reliable_depth_mask
from .sampling import bilinear, bilinear_depth, nearest_pixel


MEAN_BILINEAR_SQUARES = 4.0 / 9.0  # the mean of sum w^2 over uniform sub-pixel positions: (2/3)^2


@dataclass(frozen=True)
class VerifySettings:
    """Noise scales of the score and the grid it is computed on."""

    grid_points: int = 3000  # grid pixels per direction (fewer where depth is missing)
    depth_sigma_m: float = 0.003  # s0: depth noise at zero range
    depth_sigma_quadratic: float = 0.0025  # s2: depth noise growth, metres per metre^2 (Kinect-like)
    photo_sigma: float = 0.04  # grey levels in [0, 1]
    photo_weight: float = 1.0  # weight of the photometric cost against the geometric one
    smooth_px: float = 1.0  # Gaussian sigma (pixels at 320 px width; scaled with the width)
    min_depth_m: float = 0.1
    max_depth_m: float = 10.0
    depth_edge_ratio: float = 0.05


@dataclass(frozen=True)
class FrameView:
    """What scoring needs of one frame: smoothed grey image, depth, normals and the grid samples."""

    gray: np.ndarray  # H x W float64
    depth: np.ndarray  # H x W float64, 0 = invalid
    normals: np.ndarray  # H x W x 3 camera-frame unit normals (NaN where undefined)
    grid_points: np.ndarray  # N x 3 camera-frame points of the grid pixels
    grid_gray: np.ndarray  # N grey values there


@dataclass(frozen=True)
class Verification:
    """Score of one candidate (lower is better), its two components and the overlap fraction."""

    score: float
    geometric: float
    photometric: float
    overlap: float
    flow: float = float("nan")  # disagreement with the measured optical flow (flow_disagreement), when used

    def to_dict(self) -> dict:
        return {k: round(float(v), 5) if np.isfinite(v) else None for k, v in self.__dict__.items()}


@dataclass(frozen=True)
class FlowCheck:
    """[ours] The pair's measured optical flow (camera a -> b, H x W x 2 pixels) and where it is trusted
    (forward-backward consistent): what a candidate's rigid flow is compared with."""

    flow: np.ndarray
    trusted: np.ndarray


@profiling.timed("verification")
def flow_disagreement(T: np.ndarray, depth: np.ndarray, K: np.ndarray, check: FlowCheck, scale_px: float,
                      stride: int = 1) -> float:
    """[ours] Mean of min(r / scale_px, 1)^2 over trusted pixels with depth (every ``stride``-th row and
    column), r the distance (pixels) between where T (camera a -> b) moves the pixel's point and where the
    measured flow moves it; 1 when nothing compares. Candidates within a pixel of the flow score alike;
    one that slid along a plain wall, which depth and colour residuals cannot see, disagrees by many pixels."""
    if not np.all(np.isfinite(T)):
        return 1.0
    depth_s, trusted_s = depth[::stride, ::stride], check.trusted[::stride, ::stride]
    valid = trusted_s & (depth_s > 0)
    if not valid.any():
        return 1.0
    # pixel (u', v') of the strided grid is pixel (stride u', stride v') of the image: K scaled by 1/stride
    K_s = K.copy()
    K_s[:2] /= stride
    v, u = np.nonzero(valid)
    with np.errstate(invalid="ignore", divide="ignore"):
        moved = project(transform(T, backproject(depth_s, K_s)[valid]), K)
    measured = stride * np.stack([u, v], axis=1) + check.flow[::stride, ::stride][valid]
    r = np.linalg.norm(moved - measured, axis=1)
    r = np.where(np.isfinite(r), r, scale_px)
    return float(np.mean(np.minimum(r / scale_px, 1.0) ** 2))


@profiling.timed("verification")
def frame_view(color: np.ndarray, depth: np.ndarray, K: np.ndarray, settings: VerifySettings = VerifySettings()) -> FrameView:
    """Precompute one frame's grey image, normals and grid samples (reused for every candidate)."""
    h, w = depth.shape
    gray = cv2.cvtColor(np.ascontiguousarray(color, dtype=np.float32), cv2.COLOR_RGB2GRAY).astype(np.float64)
    sigma = settings.smooth_px * w / 320.0
    if sigma > 0:
        gray = cv2.GaussianBlur(gray, (0, 0), sigma)
    depth = np.asarray(depth, dtype=np.float64)
    mask = reliable_depth_mask(depth, settings.min_depth_m, settings.max_depth_m, settings.depth_edge_ratio)
    depth = np.where(mask, depth, 0.0)
    points = backproject(depth, K)
    normals = depth_normals(points, mask)
    stride = max(1, int(np.sqrt(mask.sum() / max(settings.grid_points, 1))))
    grid = np.zeros_like(mask)
    grid[stride // 2::stride, stride // 2::stride] = True
    grid &= mask
    return FrameView(gray, depth, normals, points[grid], gray[grid])


def depth_normals(points: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Unit normals (facing the camera) from central differences of a point map; NaN where undefined."""
    x, y, z = (np.ascontiguousarray(points[..., k]) for k in range(3))

    def differences(plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        du, dv = np.zeros_like(plane), np.zeros_like(plane)
        du[:, 1:-1] = plane[:, 2:] - plane[:, :-2]
        dv[1:-1] = plane[2:] - plane[:-2]
        return du, dv

    (ax, bx), (ay, by), (az, bz) = differences(x), differences(y), differences(z)
    nx, ny, nz = ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx  # du x dv
    ok = np.zeros_like(mask)
    ok[1:-1, 1:-1] = mask[1:-1, 2:] & mask[1:-1, :-2] & mask[2:, 1:-1] & mask[:-2, 1:-1] & mask[1:-1, 1:-1]
    length = np.sqrt(nx * nx + ny * ny + nz * nz)
    ok &= length > 0
    length = np.where(ok, length, 1.0)
    nx, ny, nz = nx / length, ny / length, nz / length
    scale = np.where(ok, np.where(nx * x + ny * y + nz * z > 0, -1.0, 1.0), np.nan)  # face the camera
    return np.stack([nx * scale, ny * scale, nz * scale], axis=-1)


def _direction(T: np.ndarray, source: FrameView, target: FrameView, K: np.ndarray,
               settings: VerifySettings) -> tuple[float, float, int, int]:
    """Sums of the geometric and photometric robust costs of source's grid moved by T into target,
    the number of grid points that land on valid target depth, and the grid size."""
    n = len(source.grid_points)
    if n == 0:
        return 0.0, 0.0, 0, 0
    Q = source.grid_points @ T[:3, :3].T + T[:3, 3]
    front = Q[:, 2] > 1e-3
    z = np.where(front, Q[:, 2], 1.0)
    pixels = np.stack([K[0, 0] * Q[:, 0] / z + K[0, 2], K[1, 1] * Q[:, 1] / z + K[1, 2]], axis=-1)
    pixels[~front] = np.nan
    depth, _, valid = bilinear_depth(target.depth, pixels)
    u, v = nearest_pixel(pixels, target.depth.shape)
    normal = target.normals[v, u]
    valid &= front & np.all(np.isfinite(normal), axis=1)
    m = int(valid.sum())
    if m == 0:
        return 0.0, 0.0, 0, n
    Q, pixels, depth, normal = Q[valid], pixels[valid], depth[valid], normal[valid]
    rays = np.stack([(pixels[:, 0] - K[0, 2]) / K[0, 0], (pixels[:, 1] - K[1, 2]) / K[1, 1], np.ones(m)], axis=-1)
    r_geo = np.sum(normal * (Q - depth[:, None] * rays), axis=1)
    sigma_geo = (settings.depth_sigma_m + settings.depth_sigma_quadratic * depth**2) * interpolation_noise(pixels)
    geometric = _geman_mcclure(r_geo, sigma_geo)
    target_gray, _ = bilinear(target.gray, pixels)
    source_gray = source.grid_gray[valid]
    r_photo = (source_gray - source_gray.mean()) - (target_gray - target_gray.mean())
    photometric = _geman_mcclure(r_photo, settings.photo_sigma)
    return float(geometric.sum()), float(photometric.sum()), m, n


def interpolation_noise(pixels: np.ndarray) -> np.ndarray:
    """How the geometric residual's noise depends on where each point lands in the target frame, with
    mean 1 over positions. The residual is one source depth sample minus a bilinear mix of four target
    samples with weights w, so its variance is sigma^2 (1 + sum w^2): sum w^2 is 1 on a pixel, 1/4
    between four and 4/9 on average. Scaling sigma by sqrt((1 + sum w^2) / (1 + 4/9)) keeps each point's
    expected cost the same wherever it lands; with one scale for all, a candidate that lands between
    pixels looked better than one that lands on them, and a still camera (every point on a pixel) worse
    than a slightly wrong motion."""
    a = pixels[:, 0] - np.floor(pixels[:, 0])
    b = pixels[:, 1] - np.floor(pixels[:, 1])
    squares = ((1.0 - a) ** 2 + a**2) * ((1.0 - b) ** 2 + b**2)
    return np.sqrt((1.0 + squares) / (1.0 + MEAN_BILINEAR_SQUARES))


def _geman_mcclure(r: np.ndarray, sigma) -> np.ndarray:
    r2 = r * r
    return r2 / (r2 + np.square(sigma))


@profiling.timed("verification")
def verify(T: np.ndarray, a: FrameView, b: FrameView, K: np.ndarray, settings: VerifySettings = VerifySettings()) -> Verification:
    """Score of the transform T (camera a -> camera b); infinite when it leaves no overlap."""
    if not np.all(np.isfinite(T)):
        return Verification(float("inf"), float("nan"), float("nan"), 0.0)
    T_inv = np.linalg.inv(T)
    g1, p1, m1, n1 = _direction(T, a, b, K, settings)
    g2, p2, m2, n2 = _direction(T_inv, b, a, K, settings)
    m = m1 + m2
    overlap = min(m1 / max(n1, 1), m2 / max(n2, 1))
    if m == 0:
        return Verification(float("inf"), float("nan"), float("nan"), overlap)
    geometric, photometric = (g1 + g2) / m, (p1 + p2) / m
    score = (geometric + settings.photo_weight * photometric) / (1.0 + settings.photo_weight)
    return Verification(score, geometric, photometric, overlap)
