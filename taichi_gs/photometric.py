"""Per-frame photometric compensation: an affine colour transform ``M`` (3 x 4) of a frame's render,
``out = image @ M[:, :3].T + M[:, 3]``, so that exposure and white-balance changes of a real camera
are explained per frame instead of being baked into the scene's colours or mistaken for blur.
The transform is linear, so applying it to the k-view average equals averaging transformed views.
Host-side NumPy (a few operations per image, no per-pixel Python loops)."""

from __future__ import annotations

import numpy as np

IDENTITY = np.hstack([np.eye(3), np.zeros((3, 1))])


def apply_affine(image: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``image`` (H, W, 3) transformed by the 3 x 4 affine ``M``."""
    return image @ M[:, :3].T + M[:, 3]


def affine_backward(image: np.ndarray, M: np.ndarray, grad_out: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients (dL/d image, dL/d M) of a loss L given dL/d out for ``out = apply_affine(image, M)``."""
    flat_g = grad_out.reshape(-1, 3).astype(np.float64)
    flat_x = image.reshape(-1, 3).astype(np.float64)
    grad_M = np.hstack([flat_g.T @ flat_x, flat_g.sum(axis=0)[:, None]])
    return grad_out @ M[:, :3], grad_M


def identity_penalty(M: np.ndarray, weight: float) -> tuple[float, np.ndarray]:
    """``weight * |M - I|^2`` (squared Frobenius norm) and its gradient: keeps the scene's colours the
    reference (the transforms' gauge)."""
    delta = M - IDENTITY
    return float(weight * np.sum(delta**2)), 2.0 * weight * delta
