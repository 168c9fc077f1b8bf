"""Camera paths for novel-view renders: along the estimated trajectory, or an orbit around what
the cameras looked at. Poses are camera-to-world 4x4 with OpenCV axes."""

from __future__ import annotations

import numpy as np

from .geometry import interpolate, pose_from_rt


def trajectory_path(poses: np.ndarray, count: int) -> np.ndarray:
    """``count`` poses spread evenly along the trajectory (SE(3) interpolation between frames)."""
    positions = np.linspace(0.0, len(poses) - 1, count)
    out = []
    for x in positions:
        i = min(int(np.floor(x)), len(poses) - 2) if len(poses) > 1 else 0
        out.append(poses[i] if len(poses) == 1 else interpolate(poses[i], poses[i + 1], float(x - i)))
    return np.stack(out)


def look_at(position: np.ndarray, target: np.ndarray, down: np.ndarray) -> np.ndarray:
    """Camera-to-world pose at ``position`` looking at ``target``, image y along ``down``."""
    z = target - position
    z = z / np.linalg.norm(z)
    x = np.cross(down, z)
    x = x / np.linalg.norm(x)
    return pose_from_rt(np.stack([x, np.cross(z, x), z], axis=1), position)


def orbit_path(poses: np.ndarray, points: np.ndarray, count: int, radius_fraction: float = 0.15) -> np.ndarray:
    """``count`` poses on a circle around the mean camera, all looking at the scene point straight
    ahead of it (at the median depth of ``points``); radius = ``radius_fraction`` x that depth."""
    centre = poses[:, :3, 3].mean(axis=0)
    forward = poses[:, :3, 2].mean(axis=0)
    forward /= np.linalg.norm(forward)
    down = poses[:, :3, 1].mean(axis=0)
    down -= forward * (down @ forward)
    down /= np.linalg.norm(down)
    right = np.cross(down, forward)
    depths = (points - centre) @ forward
    ahead = depths[depths > 0]
    focus = float(np.median(ahead)) if len(ahead) else 1.0
    target = centre + focus * forward
    radius = radius_fraction * focus
    angles = np.linspace(0.0, 2.0 * np.pi, count, endpoint=False)
    return np.stack([look_at(centre + radius * (np.cos(a) * right + np.sin(a) * down), target, down) for a in angles])
