"""Divergence checks for the training loops of stages 2 and 3.

Training stops with a :class:`~taichi_gs.errors.DivergenceError` (the CLI exits 4) when a loss or a
gradient is not finite, when the loss runs away (above ``runaway_factor`` times the lowest loss seen
so far, for ``patience`` checks in a row), or when parameters leave the scene: non-finite values, or
Gaussian centres farther than ``max_distance_extents`` scene extents from the scene's centre. The
caller checks before it saves a checkpoint, so the last checkpoint on disk is always a good one.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np

from .. import profiling
from ..errors import DivergenceError


class DivergenceGuard:
    """Watches one training run; see the module doc."""

    def __init__(self, stage: str, centre: np.ndarray, extent: float, runaway_factor: float = 100.0,
                 patience: int = 20, max_distance_extents: float = 100.0):
        self.stage = stage
        self.centre = np.asarray(centre, dtype=np.float64)
        self.extent = float(extent)
        self.runaway_factor = runaway_factor
        self.patience = patience
        self.max_distance_extents = max_distance_extents
        self.best = np.inf
        self.strikes = 0

    def check_step(self, iteration: int, loss: float, gradients: Iterable[np.ndarray] = ()) -> None:
        """Finite loss and gradients; no runaway loss."""
        if not np.isfinite(loss):
            raise DivergenceError(self.stage, iteration, f"loss is {loss}")
        for gradient in gradients:
            if not np.all(np.isfinite(gradient)):
                raise DivergenceError(self.stage, iteration, "non-finite gradient")
        self.best = min(self.best, loss)
        if self.best > 0 and loss > self.runaway_factor * self.best:
            self.strikes += 1
            if self.strikes >= self.patience:
                raise DivergenceError(self.stage, iteration, f"loss {loss:.4g} ran away from its best {self.best:.4g}")
        else:
            self.strikes = 0

    @profiling.timed("divergence checks (parameter download)")
    def check_parameters(self, iteration: int, means: np.ndarray, *others: np.ndarray) -> None:
        """Finite parameters, and Gaussian centres within reach of the scene."""
        for values in (means, *others):
            if not np.all(np.isfinite(values)):
                raise DivergenceError(self.stage, iteration, "non-finite parameters")
        if len(means):
            distance = float(np.max(np.linalg.norm(np.asarray(means, dtype=np.float64) - self.centre, axis=1)))
            if distance > self.max_distance_extents * self.extent:
                raise DivergenceError(self.stage, iteration, f"Gaussians flew {distance:.3g} m from the scene "
                                      f"(extent {self.extent:.3g} m)")
