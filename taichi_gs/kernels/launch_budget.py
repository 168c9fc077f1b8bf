"""Counts of kernel launches, host reads of device data and bytes copied while a block of code runs.

:func:`counting` hooks Taichi 1.7's Python entry points while its ``with`` block runs and puts the originals
back on the way out (also after an exception); outside it nothing is hooked and nothing is slowed down.

* launches: ``Kernel.launch_kernel``, which every ``@ti.kernel`` call (its ``.grad`` too, and Taichi's own
  copy and fill kernels) goes through, by kernel name; an ``Ndarray.fill`` that launches no Python kernel
  (CPU and CUDA fill f32 / i32 / u32 ndarrays from C++) counts as one launch, ``ndarray.fill``;
* host reads (the host waits for the device and takes its values): :func:`host_copy.read`, ``to_numpy`` of an
  ndarray or field, an element read (``a[i]``; each entry of a vector or matrix element), a kernel's return
  value, a NumPy array handed to a kernel (GPU backends copy it back after the launch), with the bytes that
  come back;
* host writes: :func:`host_copy.write`, ``from_numpy``, element writes, a NumPy kernel argument, with the
  bytes that go to the device;
* syncs: ``ti.sync()`` outside the copies above (a wait that reads nothing);
* device tasks, when Taichi's kernel profiler is on (``ti.init(kernel_profiler=True)``): what the device
  ran, each top-level loop of a launched kernel one task (one GPU dispatch; on the CPU one parallel loop),
  by kernel and task (the profiler's names); None when it is off.

Reads and writes count once where the project asks for them, alike on every backend: on the CPU backend
``host_copy`` copies through a view of the memory, elsewhere through ``to_numpy`` / ``from_numpy``, whose
own copy kernels still count as launches. Every event keeps its site, the first caller outside Taichi,
this module and ``host_copy`` (``kernels/splat.py:forward``). Field entries of vectors and matrices count
4 bytes each (Taichi's accessor does not say their type).
"""

from __future__ import annotations

import contextlib
import functools
import math
import re
import sys
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from taichi.lang import impl, matrix
from taichi.lang._ndarray import Ndarray, NdarrayHostAccess, ScalarNdarray
from taichi.lang.enums import AutodiffMode
from taichi.lang.field import ScalarField
from taichi.lang.kernel_impl import Kernel
from taichi.lang.matrix import MatrixField, MatrixNdarray, VectorNdarray
from taichi.lang.util import to_numpy_type

from . import host_copy

LAUNCH, READ, WRITE, SYNC, TASK = "launch", "read", "write", "sync", "task"
_PACKAGE = Path(__file__).resolve().parents[1]  # taichi_gs/
# frames that are not a site: Taichi, this module, host_copy, contextlib (the counting context managers)
_NOT_SITES = (str(Path(impl.__file__).resolve().parents[1]), __file__, host_copy.__file__, contextlib.__file__)


@dataclass
class LaunchBudget:
    """What a counted block did: ``events[(kind, name, site)] = [count, bytes]``, kind one of ``launch``,
    ``read``, ``write``, ``sync``, ``task``; name the kernel (launches), the kind of copy (``host_copy.read``,
    ``ndarray element``, ...) or the task (``blend:1 range_for``); bytes copied (reads: to the host, writes: to
    the device). ``tasks_counted``: whether the kernel profiler was on (else no task events)."""

    events: dict[tuple[str, str, str], list[int]] = field(default_factory=dict)
    tasks_counted: bool = False

    def add(self, kind: str, name: str, site: str, nbytes: int = 0) -> None:
        entry = self.events.setdefault((kind, name, site), [0, 0])
        entry[0] += 1
        entry[1] += int(nbytes)

    def count(self, kind: str) -> int:
        """How many events of ``kind``."""
        return sum(c for (k, _, _), (c, _) in self.events.items() if k == kind)

    def nbytes(self, kind: str) -> int:
        """Bytes copied by the events of ``kind``."""
        return sum(b for (k, _, _), (_, b) in self.events.items() if k == kind)

    @property
    def launches(self) -> int:
        return self.count(LAUNCH)

    @property
    def host_reads(self) -> int:
        return self.count(READ)

    @property
    def host_writes(self) -> int:
        return self.count(WRITE)

    @property
    def syncs(self) -> int:
        return self.count(SYNC)

    @property
    def tasks(self) -> int | None:
        return self.count(TASK) if self.tasks_counted else None

    @property
    def bytes_to_host(self) -> int:
        return self.nbytes(READ)

    @property
    def bytes_to_device(self) -> int:
        return self.nbytes(WRITE)

    def by_name(self, kind: str) -> Counter[str]:
        """Events of ``kind`` per name (launches: per kernel)."""
        counts: Counter[str] = Counter()
        for (k, name, _), (c, _) in self.events.items():
            if k == kind:
                counts[name] += c
        return counts

    def by_site(self, kind: str) -> Counter[str]:
        """Events of ``kind`` per "name @ site"."""
        return Counter({f"{name} @ {site}": c for (k, name, site), (c, _) in self.events.items() if k == kind})

    def summary(self) -> dict:
        """Totals, launches per kernel and per site, reads, writes and syncs per site (JSON-ready)."""
        tasks_by_kernel: Counter[str] = Counter()
        for task, c in self.by_name(TASK).items():
            tasks_by_kernel[task.split(":")[0]] += c
        return {
            "launches": self.launches, "tasks": self.tasks, "host_reads": self.host_reads,
            "host_writes": self.host_writes, "syncs": self.syncs, "bytes_to_host": self.bytes_to_host,
            "bytes_to_device": self.bytes_to_device,
            "launches_by_kernel": dict(self.by_name(LAUNCH).most_common()),
            "tasks_by_kernel": dict(tasks_by_kernel.most_common()) if self.tasks_counted else None,
            "tasks_by_name": dict(self.by_name(TASK).most_common()) if self.tasks_counted else None,
            **{f"{kind}_sites": dict(self.by_site(kind).most_common()) for kind in (LAUNCH, READ, WRITE, SYNC)},
        }


class _Count:
    """The active count: its budget, and how deep the caller is inside a counted copy or launch (whose own
    reads, writes and syncs are part of it, not counted again)."""

    def __init__(self) -> None:
        self.budget = LaunchBudget()
        self.depth = 0

    @contextmanager
    def copy(self, kind: str, name: str, nbytes: Callable[[], int]) -> Iterator[None]:
        """Count one read or write of ``nbytes()`` bytes (asked after the copy) unless inside another."""
        outer = self.depth == 0
        site = _site() if outer else ""
        self.depth += 1
        try:
            yield
        finally:
            self.depth -= 1
        if outer:
            self.budget.add(kind, name, site, nbytes())


_active: _Count | None = None


@contextmanager
def counting() -> Iterator[LaunchBudget]:
    """Count launches, host reads and writes, syncs and bytes copied inside the block (see the module)."""
    global _active
    if _active is not None:
        raise RuntimeError("launch_budget.counting() is already active; counts do not nest")
    count = _Count()
    hooks = _hooks(count)
    originals = [(owner, name, owner.__dict__[name]) for owner, name, _ in hooks]
    count.budget.tasks_counted = bool(impl.current_cfg().kernel_profiler)
    first_task = len(_profiler_records()) if count.budget.tasks_counted else 0
    _active = count
    try:
        for owner, name, hook in hooks:
            setattr(owner, name, hook)
        yield count.budget
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)
        _active = None
    for record in _profiler_records()[first_task:] if count.budget.tasks_counted else ():
        count.budget.add(TASK, task_name(record.name), "")


def task_name(profiler_name: str) -> str:
    """The profiler's name of a task as "kernel:task": "backward_c86_0_kernel_1_range_for" -> "backward:1 range_for"."""
    match = re.fullmatch(r"(\w+?)_c\d+_\d+_kernel_(\d+)_(\w+)", profiler_name)
    return f"{match[1]}:{match[2]} {match[3]}" if match else profiler_name


def _profiler_records() -> list:
    """Taichi's kernel profiler records so far (each task the device ran), after the device finished."""
    prog = impl.get_runtime().prog
    prog.sync_kernel_profiler()
    prog.update_kernel_profiler()
    return prog.get_kernel_profiler_records()


def _site() -> str:
    """The first caller outside Taichi, this module, host_copy and contextlib: "kernels/splat.py:forward"."""
    frame = sys._getframe(1)
    while frame is not None and frame.f_code.co_filename.startswith(_NOT_SITES):
        frame = frame.f_back
    if frame is None:
        return "?"
    path = Path(frame.f_code.co_filename)
    try:
        where = path.resolve().relative_to(_PACKAGE).as_posix()
    except ValueError:
        where = path.name
    return f"{where}:{frame.f_code.co_name}"


def _itemsize(dtype) -> int:
    return np.dtype(to_numpy_type(dtype)).itemsize


def _array_bytes(array) -> int:
    """Bytes of a whole ndarray or field (element dimensions included)."""
    total = getattr(array, "arr", None)
    shape = tuple(total.total_shape()) if hasattr(total, "total_shape") else \
        tuple(array.shape) + tuple(getattr(array, "element_shape", None) or ())  # fields
    return math.prod(int(d) for d in shape) * _itemsize(array.dtype)


def _return_bytes(kernel: Kernel) -> int:
    """Bytes of a kernel's return values (scalars, vectors, matrices)."""
    total = 0
    for ret in kernel.return_type:
        if hasattr(ret, "n") and hasattr(ret, "dtype"):  # vector / matrix type
            total += ret.n * getattr(ret, "m", 1) * _itemsize(ret.dtype)
        else:
            total += _itemsize(ret)
    return total


def _entry_bytes(access) -> int:
    """Bytes of one entry of a vector / matrix element read or written from Python."""
    return _itemsize(access.ndarr.dtype) if isinstance(access, NdarrayHostAccess) else 4


def _hooks(count: _Count) -> list[tuple[object, str, Callable]]:
    """(owner, attribute, hook) for every entry point counted; each hook calls the owner's original."""
    budget = count.budget

    def launch_kernel(original):
        @functools.wraps(original)
        def hook(self, t_kernel, *args):
            outer = count.depth == 0
            site = _site()
            count.depth += 1
            try:
                result = original(self, t_kernel, *args)
            finally:
                count.depth -= 1
            budget.add(LAUNCH, self.func.__name__ + (".grad" if self.autodiff_mode == AutodiffMode.REVERSE else ""),
                       site)
            if outer:
                for arg in args:
                    if isinstance(arg, np.ndarray):  # GPU backends copy it to the device and back, waiting for it
                        budget.add(WRITE, "numpy argument", site, arg.nbytes)
                        budget.add(READ, "numpy argument", site, arg.nbytes)
                if self.return_type is not None:
                    budget.add(READ, "kernel return", site, _return_bytes(self))
            return result
        return hook

    def fill(original):
        @functools.wraps(original)
        def hook(self, val):
            before, site = budget.launches, _site()
            count.depth += 1
            try:
                original(self, val)
            finally:
                count.depth -= 1
            if budget.launches == before:  # filled from C++ (CPU, CUDA): a launch all the same
                budget.add(LAUNCH, "ndarray.fill", site)
        return hook

    def sync(original):
        @functools.wraps(original)
        def hook(self):
            if count.depth == 0:
                budget.add(SYNC, "ti.sync", _site())
            return original(self)
        return hook

    def reader(name: str, nbytes: Callable):
        def wrap(original):
            @functools.wraps(original)
            def hook(self, *args, **kwargs):
                result = None
                with count.copy(READ, name, lambda: nbytes(self, result)):
                    result = original(self, *args, **kwargs)
                return result
            return hook
        return wrap

    def writer(name: str, nbytes: Callable):
        def wrap(original):
            @functools.wraps(original)
            def hook(self, *args, **kwargs):
                with count.copy(WRITE, name, lambda: nbytes(self, *args)):
                    return original(self, *args, **kwargs)
            return hook
        return wrap

    def read_bytes(_array, result) -> int:
        return int(result.nbytes)

    def element_bytes(array, _result) -> int:
        return _itemsize(array.dtype)

    def written_bytes(array, *_args) -> int:
        return _array_bytes(array)

    def element_written(array, *_args) -> int:
        return _itemsize(array.dtype)

    hooks: list[tuple[object, str, Callable]] = []
    for cls in (ScalarNdarray, VectorNdarray, MatrixNdarray, ScalarField, MatrixField):
        kind = "field" if issubclass(cls, (ScalarField, MatrixField)) else "ndarray"
        own = cls.__dict__
        hooks.append((cls, "to_numpy", reader(f"{kind}.to_numpy", read_bytes)(own["to_numpy"])))
        hooks.append((cls, "from_numpy", writer(f"{kind}.from_numpy", written_bytes)(own["from_numpy"])))
    for cls in (ScalarNdarray, ScalarField):  # vector / matrix elements: per entry, below
        kind = "field" if cls is ScalarField else "ndarray"
        hooks.append((cls, "__getitem__", reader(f"{kind} element", element_bytes)(cls.__dict__["__getitem__"])))
        hooks.append((cls, "__setitem__", writer(f"{kind} element", element_written)(cls.__dict__["__setitem__"])))
    hooks.append((matrix, "_read_host_access",
                  reader("vector / matrix entry", lambda access, _: _entry_bytes(access))(matrix._read_host_access)))
    hooks.append((matrix, "_write_host_access",
                  writer("vector / matrix entry", lambda access, _: _entry_bytes(access))(matrix._write_host_access)))
    hooks.append((Kernel, "launch_kernel", launch_kernel(Kernel.__dict__["launch_kernel"])))
    hooks.append((Ndarray, "fill", fill(Ndarray.__dict__["fill"])))
    hooks.append((impl.PyTaichi, "sync", sync(impl.PyTaichi.__dict__["sync"])))

    def host_read(original):
        @functools.wraps(original)
        def hook(array, rows=None):
            result = None
            with count.copy(READ, "host_copy.read", lambda: result.nbytes):
                result = original(array, rows)
            return result
        return hook

    def host_write(original):
        @functools.wraps(original)
        def hook(array, values):
            with count.copy(WRITE, "host_copy.write", lambda: _array_bytes(array)):
                return original(array, values)
        return hook

    hooks.append((host_copy, "read", host_read(host_copy.__dict__["read"])))
    hooks.append((host_copy, "write", host_write(host_copy.__dict__["write"])))
    return hooks
