"""Errors a user can act on: the CLI prints them on one line and exits with code 2 (bad input) or 4
(an optimiser diverged)."""

from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """Bad input: names the offending file and how to fix it."""

    def __init__(self, path: str | Path | None, problem: str, fix: str):
        self.path = None if path is None else Path(path)
        self.problem = problem
        self.fix = fix
        where = f"{self.path}: " if self.path is not None else ""
        super().__init__(f"{where}{problem}; {fix}")


class BackendError(RuntimeError):
    """The requested Taichi backend is not available on this machine."""


class DivergenceError(RuntimeError):
    """An optimiser diverged: non-finite values or a runaway loss. Names the stage and iteration."""

    def __init__(self, stage: str, iteration: int, problem: str):
        self.stage = stage
        self.iteration = iteration
        super().__init__(f"{stage} diverged at iteration {iteration}: {problem}")
