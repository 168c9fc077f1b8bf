"""What a training step's kernels hand back to the host, left on the device in one flat buffer and read in
one go: the loss values, the rasterizer's pose rows, the warp's per-row pose gradients, the colour
transform's per-row gradient. A kernel writes its values at a :class:`Slot` (the buffer and an offset);
:meth:`StepValues.read` then copies every value of the step in one host read (one synchronisation),
by name.

Slots name their :class:`StepValues`, not its buffer: when a slot does not fit, the buffer is replaced by a
larger copy (a read and a write, once, on the first steps), and slots taken before write into the new one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import taichi as ti

from . import host_copy


@dataclass(frozen=True)
class Slot:
    """Where a kernel leaves ``size`` values: ``values[at]`` to ``values[at + size - 1]``, rows of ``width``
    values row-major."""

    owner: StepValues
    at: int
    size: int
    width: int = 1

    @property
    def values(self) -> ti.Ndarray:
        """The flat device buffer the values go to (pass it to the kernel with :attr:`at`)."""
        return self.owner.buffer

    def row(self, j: int) -> Slot:
        """Row ``j`` of this slot's rows."""
        if not 0 <= j < self.size // self.width:
            raise ValueError(f"row {j} of a slot of {self.size // self.width} rows")
        return Slot(self.owner, self.at + j * self.width, self.width, self.width)


class StepValues:
    """A training step's values on the device in named slots (:meth:`at`: one value per name; :meth:`rows`: a
    block of rows), read together (:meth:`read`): one host read per step."""

    def __init__(self, dtype, size: int = 256) -> None:
        self.buffer = ti.ndarray(dtype, (size,))
        self.shapes: dict[str, tuple[int, int, int]] = {}  # name -> (at, rows, width); width 0: one value
        self.used = 0

    def at(self, *names: str) -> Slot:
        """The next ``len(names)`` values, one per name (e.g. a loss kernel's values, in its order)."""
        at = self._take(len(names))
        for i, name in enumerate(names):
            self._name(name, (at + i, 1, 0))
        return Slot(self, at, len(names))

    def rows(self, name: str, count: int, width: int) -> Slot:
        """The next ``count`` rows of ``width`` values, read as one (count, width) array."""
        at = self._take(count * width)
        self._name(name, (at, count, width))
        return Slot(self, at, count * width, width)

    def clear(self) -> None:
        """Forget the slots (the next step, or a step that runs again)."""
        self.shapes, self.used = {}, 0

    def read(self) -> dict[str, float | np.ndarray]:
        """Every named value in one read, as float (:meth:`at`) or float64 (rows, width) arrays (:meth:`rows`);
        the slots are then free for the next step."""
        flat = host_copy.read(self.buffer, self.used).astype(np.float64) if self.used else np.zeros(0)
        named = {name: float(flat[at]) if width == 0 else flat[at:at + rows * width].reshape(rows, width)
                 for name, (at, rows, width) in self.shapes.items()}
        self.clear()
        return named

    def _name(self, name: str, shape: tuple[int, int, int]) -> None:
        if name in self.shapes:
            raise ValueError(f"step value {name!r} taken twice in one step")
        self.shapes[name] = shape

    def _take(self, size: int) -> int:
        """Offset of ``size`` more values, the buffer grown (its values kept) when they do not fit."""
        at, self.used = self.used, self.used + size
        if self.used > self.buffer.shape[0]:
            grown = ti.ndarray(self.buffer.dtype, (max(2 * self.buffer.shape[0], int(self.used * 1.25)),))
            if at:
                kept = np.zeros(grown.shape[0])
                kept[:at] = host_copy.read(self.buffer, at)
                host_copy.write(grown, kept)
            self.buffer = grown
        return at
