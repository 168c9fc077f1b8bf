"""[ours] A frame's depth moved to its colour's instant. Where the depth stream runs free of the colour stream (TUM
fr1's Kinect: a depth frame up to half a frame from its colour frame), the depth shows the scene from where the camera
was when the depth was taken (``exposures.DepthMoments``), not from the mid-exposure pose whose render the training's
depth loss compares it with. Moving each training frame's depth by that motion once, before training, lets the loss
meet depth as the mid-exposure camera would see it."""

from __future__ import annotations

import numpy as np

from ...geometry import se3_exp
from .exposures import DepthMoments


def moved_depth(depth: np.ndarray, K: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """``depth`` (H, W; 0 or non-finite: none) as a camera moved by ``motion`` sees it (4x4: a point x in the depth's
    camera is ``motion @ x`` in the moved one). Each valid pixel's point lands on the four pixels around where it
    projects (so a surface the move stretches keeps no gaps), the nearest surface kept where several land: edges in
    front may grow by up to a pixel. 0 where none lands (what the depth camera did not see)."""
    height, width = depth.shape
    v, u = np.nonzero(np.isfinite(depth) & (depth > 0))
    z = depth[v, u].astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    moved = points @ motion[:3, :3].T + motion[:3, 3]
    moved = moved[moved[:, 2] > 0]
    x = K[0, 0] * moved[:, 0] / moved[:, 2] + K[0, 2]
    y = K[1, 1] * moved[:, 1] / moved[:, 2] + K[1, 2]
    nearest = np.full(height * width, np.inf)
    for cols in (np.floor(x), np.ceil(x)):
        for rows in (np.floor(y), np.ceil(y)):
            inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
            at = (rows[inside] * width + cols[inside]).astype(np.int64)
            np.minimum.at(nearest, at, moved[inside, 2])
    return np.where(np.isfinite(nearest), nearest, 0.0).reshape(height, width).astype(np.float32)


def colour_instant_motions(moments: DepthMoments, frames: list[int], count: int) -> np.ndarray | None:
    """(count, 4, 4) the motion from each of ``frames``' depth poses to its mid-exposure pose (identity for every other
    frame and for depth taken with its colour), or None when no frame's depth needs moving."""
    motions = np.tile(np.eye(4), (count, 1, 1))
    for i in frames:
        shift = moments.shift(i)
        if shift.any():
            motions[i] = se3_exp(shift)  # mid^-1 @ depth pose = exp(shift): the depth's points into the mid camera
    return None if np.array_equal(motions, np.tile(np.eye(4), (count, 1, 1))) else motions
