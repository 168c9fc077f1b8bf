"""What stages 2 and 3 share: learning-rate decay and the reduced training resolution."""

from __future__ import annotations

import numpy as np


def exp_decay(start: float, end: float, fraction: float) -> float:
    """Log-linear interpolation from ``start`` (fraction 0) to ``end`` (fraction 1), as 3DGS decays rates."""
    return float(np.exp(np.log(start) * (1.0 - fraction) + np.log(end) * fraction))


def downsample_depth(depth: np.ndarray, scale: int) -> np.ndarray:
    """Nearest-neighbour subsampling at pixel centres (keeps depth sharp, no mixing at edges)."""
    if scale == 1:
        return depth
    return np.ascontiguousarray(depth[scale // 2::scale, scale // 2::scale])


def scaled_intrinsics(K: np.ndarray, scale: int) -> np.ndarray:
    """Intrinsics of the image subsampled at pixels scale*i + scale//2 (OpenCV convention)."""
    K = K.copy()
    K[0, 0] /= scale
    K[1, 1] /= scale
    K[0, 2] = (K[0, 2] - scale // 2) / scale
    K[1, 2] = (K[1, 2] - scale // 2) / scale
    return K
