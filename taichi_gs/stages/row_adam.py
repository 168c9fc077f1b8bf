"""Adam on host-side parameters kept one row per frame (camera poses, exposure offsets, colour
transforms), stepped one row at a time: the stages' per-frame optimiser next to the kernels' one."""

from __future__ import annotations

import numpy as np


class RowAdam:
    """Per-row Adam moments and step counts for ``rows`` parameters of ``shape`` each."""

    def __init__(self, rows: int, shape: tuple[int, ...], beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8):
        self.moments = np.zeros((rows, 2, *shape))
        self.steps = np.zeros(rows, dtype=np.int64)
        self.beta1, self.beta2, self.eps = beta1, beta2, eps

    def direction(self, row: int, grad: np.ndarray) -> np.ndarray:
        """Record one step of ``row`` with gradient ``grad``; the bias-corrected m / (sqrt(v) + eps)
        to subtract (times the learning rate) in the parameter's own update."""
        self.steps[row] += 1
        t = self.steps[row]
        m, v = self.moments[row]
        m[:] = self.beta1 * m + (1 - self.beta1) * grad
        v[:] = self.beta2 * v + (1 - self.beta2) * grad**2
        return (m / (1 - self.beta1**t)) / (np.sqrt(v / (1 - self.beta2**t)) + self.eps)

    def step(self, row: int, value: np.ndarray, grad: np.ndarray, lr: float | np.ndarray) -> np.ndarray:
        """The updated ``value`` of ``row`` for parameters in a vector space."""
        return value - lr * self.direction(row, grad)

    def state(self, name: str) -> dict[str, np.ndarray]:
        """Arrays to checkpoint, keyed ``<name>_moments`` and ``<name>_steps``."""
        return {f"{name}_moments": self.moments.copy(), f"{name}_steps": self.steps.copy()}

    def load_state(self, arrays: dict[str, np.ndarray], name: str) -> None:
        """Restore what ``state(name)`` saved."""
        moments, steps = arrays[f"{name}_moments"], arrays[f"{name}_steps"]
        if moments.shape != self.moments.shape or steps.shape != self.steps.shape:
            raise ValueError(f"checkpointed {name} Adam state has shape {moments.shape}, expected {self.moments.shape}")
        self.moments, self.steps = moments.copy(), steps.copy()
