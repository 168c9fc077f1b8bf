"""A hand-made RGB-D scene for the stage-1 tests: three textured walls of a room corner, ray-cast
exactly from any pose, so depth, colour and optical flow are known in closed form."""

from __future__ import annotations

import numpy as np

from taichi_gs.geometry import intrinsics_matrix, invert, project, se3_exp, transform

# Planes n . X = d in world coordinates: back wall, floor (y down), left wall, right wall.
PLANES = [(np.array([0.0, 0.0, 1.0]), 3.0), (np.array([0.0, 1.0, 0.0]), 1.0),
          (np.array([1.0, 0.0, 0.0]), -1.6), (np.array([1.0, 0.0, 0.0]), 1.8)]
WAVES = [(np.array([7.0, 3.0, 5.0]), 0.0, 0.22), (np.array([-4.0, 9.0, 2.0]), 1.0, 0.16),
         (np.array([3.0, -5.0, 11.0]), 2.0, 0.10), (np.array([15.0, 13.0, -9.0]), 0.5, 0.07)]


def small_K(width: int = 160, height: int = 120) -> np.ndarray:
    return intrinsics_matrix(0.9 * width, 0.9 * width, (width - 1) / 2, (height - 1) / 2)


def texture(points: np.ndarray) -> np.ndarray:
    """Smooth multi-frequency RGB texture of world points, in [0, 1]."""
    base = sum(a * np.sin(points @ k + phase) for k, phase, a in WAVES)
    rgb = np.stack([0.5 + base, 0.5 + 0.8 * base + 0.05 * np.sin(points @ WAVES[1][0]), 0.5 + 0.6 * base], axis=-1)
    return np.clip(rgb, 0.0, 1.0).astype(np.float32)


def render(pose: np.ndarray, K: np.ndarray, width: int = 160, height: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """Exact colour (H x W x 3) and depth (H x W, metres) seen by a camera-to-world pose."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    rays_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
    R, origin = pose[:3, :3], pose[:3, 3]
    rays = rays_cam @ R.T
    best = np.full(u.shape, np.inf)
    for normal, d in PLANES:
        denom = rays @ normal
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (d - origin @ normal) / denom
        best = np.where((s > 0) & (s < best), s, best)
    depth = np.where(np.isfinite(best), best, 0.0)  # s is the camera z because rays_cam has z = 1
    color = texture(origin + rays * depth[..., None])
    return color, depth.astype(np.float32)


def exact_flow(depth: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Flow of each pixel under the motion T (camera t -> t+1) of a static scene."""
    from taichi_gs.geometry import backproject

    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    moved = project(transform(T, backproject(depth, K)), K)
    return np.stack([moved[..., 0] - u, moved[..., 1] - v], axis=-1).astype(np.float32)


def pair(T: np.ndarray, width: int = 160, height: int = 120, start: np.ndarray | None = None):
    """Colour, depth of frames t and t+1 (relative motion T) and K."""
    K = small_K(width, height)
    pose_t = np.eye(4) if start is None else start
    color_t, depth_t = render(pose_t, K, width, height)
    color_t1, depth_t1 = render(pose_t @ invert(T), K, width, height)
    return color_t, depth_t, color_t1, depth_t1, K


MOTION = se3_exp(np.array([0.04, -0.015, 0.03, 0.012, -0.02, 0.008]))


def test_scene_is_consistent_with_its_flow():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    assert np.all(depth_t > 0) and np.all(depth_t1 > 0)
    flow = exact_flow(depth_t, K, MOTION)
    from taichi_gs.sampling import bilinear

    h, w = depth_t.shape
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    target = np.stack([u + flow[..., 0], v + flow[..., 1]], -1).reshape(-1, 2).astype(np.float64)
    sampled, inside = bilinear(color_t1.astype(np.float64), target)
    error = np.abs(sampled - color_t.reshape(-1, 3))[inside]
    assert inside.mean() > 0.8 and np.median(error) < 0.01
