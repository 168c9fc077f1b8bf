"""Stage 3's density control beyond 3DGS's: the schedule in the policy's units, and [ours] Gaussians
added where a view's render leaves pixels uncovered."""

from __future__ import annotations

import cv2
import numpy as np

from ... import profiling
from .config import DeblurConfig
from .density_control import DensitySchedule
from .model import BlurScene


def density_schedule(config: DeblurConfig, extent: float, width: int, centres: np.ndarray,
                     focal: float) -> DensitySchedule:
    """The config's density control in the policy's units (pixels, metres); ``centres`` and ``focal``
    (training cameras, this resolution) for ``split_px``."""
    # mean pixel gradient -> NDC gradient as 3DGS measures it (d ndc = 2 / W d pixel)
    threshold = np.inf if config.densify_by == "error" else config.densify_grad * 2.0 / width
    return DensitySchedule(config.densify_from, config.densify_until, config.densify_every, threshold,
                           config.split_scale * extent, config.prune_opacity, config.prune_scale * extent,
                           config.max_gaussians, config.reset_opacity_every, config.split_px, centres, focal)


def nearest_filled(depth: np.ndarray) -> np.ndarray:
    """``depth`` with every 0 replaced by the nearest (L2) positive value; all zeros stay zeros."""
    valid = depth > 0
    if valid.all() or not valid.any():
        return depth
    _, labels = cv2.distanceTransformWithLabels((~valid).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    lookup = np.zeros(labels.max() + 1, depth.dtype)
    lookup[labels[valid]] = depth[valid]
    return lookup[labels]


@profiling.timed("densify / prune / fill")
def fill_uncovered(model: BlurScene, color: np.ndarray, depth: np.ndarray, cam_to_world: np.ndarray, K: np.ndarray,
                   stride: int, max_gaussians: int, rng: np.random.Generator, radius_px: float | None = None) -> int:
    """Add Gaussians where the render of a view has alpha < 0.5 (among the pixels the camera saw, if the
    model has a sourced mask): one per ``stride`` pixels (a random phase), coloured by the input, at
    the sensor depth, else the scene's rendered depth (alpha >= 0.5), else the nearest pixel's such
    depth; radius (sigma) ``radius_px`` pixels' footprint (default: the stride). Returns how many."""
    rendered, alpha = model.coverage(cam_to_world)
    known = np.where(depth > 0, depth, np.where(alpha >= 0.5, rendered, 0.0))
    grid = np.zeros(alpha.shape, bool)
    oy, ox = rng.integers(stride, size=2)
    grid[oy::stride, ox::stride] = True
    if model.sourced is not None:
        grid &= model.sourced
    v, u = np.nonzero((alpha < 0.5) & grid)
    room = max(max_gaussians - model.count, 0)
    if len(v) == 0 or room == 0 or not (known > 0).any():
        return 0
    if len(v) > room:
        keep = rng.choice(len(v), size=room, replace=False)
        v, u = v[keep], u[keep]
    z = nearest_filled(known)[v, u].astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    model.add_gaussians(points @ cam_to_world[:3, :3].T + cam_to_world[:3, 3], color[v, u],
                        (radius_px or stride) * z / K[0, 0], opacity=0.5)
    return len(v)
