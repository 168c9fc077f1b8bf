"""Image outputs: 8-bit colour and 16-bit depth PNGs, written atomically."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .atomic import atomic_path


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] as 8-bit."""
    return np.round(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)


def encode_depth(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """16-bit depth image: round(metres x scale), 0 where invalid or beyond what 16 bits hold."""
    raw = np.round(np.clip(np.nan_to_num(depth_m, nan=0.0), 0.0, None) * depth_scale)
    raw[raw > np.iinfo(np.uint16).max] = 0
    return raw.astype(np.uint16)


def write_png(path: str | Path, image: np.ndarray) -> None:
    """Write an RGB (H x W x 3) or single-channel (8- or 16-bit) image as PNG, atomically."""
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), image):
            raise OSError(f"could not write {path}")
