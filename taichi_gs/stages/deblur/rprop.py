"""Rprop for the small deterministic fits of stage 3 (a held-out frame's exposure offsets and colour
transform with the scene frozen): each coordinate keeps its own step size, which grows while its
gradient keeps its sign and halves when the sign flips (iRprop-, Igel and Huesken 2000). The same
frame is fitted at every step, so the gradient is not noisy and its sign history is informative:
the steps grow across the distance to the optimum and shrink once they straddle it, where Adam at a
fixed rate keeps stepping about the rate's size."""

from __future__ import annotations

import numpy as np

GROW, SHRINK = 1.2, 0.5


class Rprop:
    """Per-coordinate step sizes for one parameter array of ``shape``, starting at ``step`` and kept
    within [``step`` * ``min_ratio``, ``step`` * ``max_ratio``]."""

    def __init__(self, shape: tuple[int, ...], step: float, min_ratio: float = 0.01, max_ratio: float = 10.0):
        if step <= 0:
            raise ValueError(f"the initial Rprop step must be positive, got {step}")
        self.steps = np.full(shape, float(step))
        self.previous = np.zeros(shape)
        self.lo, self.hi = step * min_ratio, step * max_ratio

    def step(self, value: np.ndarray, grad: np.ndarray) -> np.ndarray:
        """The updated ``value`` after one step against ``grad`` (a coordinate whose gradient just
        changed sign shrinks its step and waits one step)."""
        agree = grad * self.previous
        self.steps = np.where(agree > 0, np.minimum(self.steps * GROW, self.hi),
                              np.where(agree < 0, np.maximum(self.steps * SHRINK, self.lo), self.steps))
        grad = np.where(agree < 0, 0.0, grad)
        self.previous = grad
        return value - np.sign(grad) * self.steps
