"""Where the time goes: wall and CPU seconds per stage and per kind of work inside it.

The functions that do the work (stage 1's optical flow, flow solve, ICP, RGB-D odometry, verification and pose
graph; the rasterizer forward and backward, losses, the k-view average or the warped views, Adam,
densification, exposure gradients, divergence checks, checkpoints and output writing) are marked where they
are defined with :func:`timed`, and ``pipeline.run_stage`` with :func:`stage_scope`. While a :class:`Profiler`
is installed (:func:`install`; ``taichi-gs reconstruct --profile``) each marked call is timed, and
:func:`write` writes ``OUT/profile.json`` and ``OUT/profile.md``. Each timed section synchronises
the device at its ends, and time is counted exclusively: a section nested in another (a render
inside a test-view exposure fit) is taken out of its parent. Each section also carries its inclusive
seconds (the parent with what is nested in it: how long the test-view exposure fits took, renders
included). "other host work" is a stage's wall time that no section covers (the Python training
loop, host-side pose updates, progress). CPU seconds are the process's user + sys time (every
thread), so CPU seconds / wall seconds is how many cores a section kept busy. Without a profiler
installed a marked function costs one global read per call, and nothing is synchronised.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Concatenate, ParamSpec, TypeVar

from .io import jsonout
from .io.atomic import write_text

P = ParamSpec("P")
R = TypeVar("R")


def _cpu_seconds() -> float:
    t = os.times()
    return t.user + t.system


def _entry(wall: float = 0.0, cpu: float = 0.0, calls: int = 0) -> dict[str, float]:
    """A section's record: exclusive and inclusive seconds (equal for a section with nothing nested)."""
    return {"wall_s": wall, "cpu_s": cpu, "calls": calls, "inclusive_wall_s": wall, "inclusive_cpu_s": cpu}


class Profiler:
    """Exclusive wall / CPU seconds and call counts per (stage, section)."""

    def __init__(self, sync: Callable[[], None] | None = None) -> None:
        self.sync = sync or (lambda: None)
        self.stages: dict[str, dict[str, Any]] = {}
        self.stage = "outside stages"
        self._stack: list[list[float]] = []  # per open section: [child wall, child cpu]
        self.last = ("", 0.0, 0.0)  # (name, exclusive wall, exclusive cpu) of the section closed last

    @contextmanager
    def section(self, name: str):
        """Time the enclosed work under ``name`` in the current stage (exclusive of nested sections)."""
        self.sync()
        wall0, cpu0 = time.perf_counter(), _cpu_seconds()
        self._stack.append([0.0, 0.0])
        try:
            yield
        finally:
            self.sync()
            wall, cpu = time.perf_counter() - wall0, _cpu_seconds() - cpu0
            child_wall, child_cpu = self._stack.pop()
            if self._stack:
                self._stack[-1][0] += wall
                self._stack[-1][1] += cpu
            record = self.stages.setdefault(self.stage, {"wall_s": 0.0, "cpu_s": 0.0, "sections": {}})
            entry = record["sections"].setdefault(name, _entry())
            entry["wall_s"] += wall - child_wall
            entry["cpu_s"] += cpu - child_cpu
            entry["inclusive_wall_s"] += wall
            entry["inclusive_cpu_s"] += cpu
            entry["calls"] += 1
            self.last = (name, wall - child_wall, cpu - child_cpu)

    def split_last(self, parts: dict[str, float]) -> None:
        """Move the named wall seconds of the section that just closed into sections of their own
        ("<section>: <part>"), with its CPU seconds shared in proportion."""
        name, wall, cpu = self.last
        sections = self.stages[self.stage]["sections"]
        for part, seconds in parts.items():
            seconds = min(seconds, sections[name]["wall_s"])
            share = cpu * seconds / max(wall, 1e-12)
            entry = sections.setdefault(f"{name}: {part}", _entry())
            entry["wall_s"] += seconds
            entry["cpu_s"] += share
            entry["inclusive_wall_s"] += seconds
            entry["inclusive_cpu_s"] += share
            entry["calls"] += 1
            sections[name]["wall_s"] -= seconds
            sections[name]["cpu_s"] -= share

    @contextmanager
    def stage_scope(self, stage: str):
        """Time a whole stage; sections inside are booked to it."""
        previous, self.stage = self.stage, stage
        self.sync()
        wall0, cpu0 = time.perf_counter(), _cpu_seconds()
        saved, self._stack = self._stack, []
        try:
            yield
        finally:
            self.sync()
            record = self.stages.setdefault(stage, {"wall_s": 0.0, "cpu_s": 0.0, "sections": {}})
            record["wall_s"] += time.perf_counter() - wall0
            record["cpu_s"] += _cpu_seconds() - cpu0
            self._stack, self.stage = saved, previous

    def report(self) -> dict[str, Any]:
        """Per stage: wall, CPU, cores, and sections sorted by wall time, with "other host work"."""
        out: dict[str, Any] = {}
        for stage, record in self.stages.items():
            sections = dict(record["sections"])
            covered_wall = sum(s["wall_s"] for s in sections.values())
            covered_cpu = sum(s["cpu_s"] for s in sections.values())
            if record["wall_s"] > 0:
                sections["other host work"] = _entry(max(record["wall_s"] - covered_wall, 0.0),
                                                     max(record["cpu_s"] - covered_cpu, 0.0), calls=1)
            total = max(record["wall_s"], covered_wall, 1e-12)
            rows = {name: {**s, "share": s["wall_s"] / total, "cores": s["cpu_s"] / max(s["wall_s"], 1e-12)}
                    for name, s in sorted(sections.items(), key=lambda kv: -kv[1]["wall_s"])}
            out[stage] = {"wall_s": record["wall_s"], "cpu_s": record["cpu_s"],
                          "cores": record["cpu_s"] / max(record["wall_s"], 1e-12), "sections": rows}
        return out

    def markdown(self) -> str:
        """The report as Markdown tables, one per stage."""
        lines = ["# taichi-gs profile", "",
                 "Exclusive wall and CPU (user + sys) seconds per section; cores = CPU / wall; "
                 "incl.: with the sections nested in it (the renders of a test-view exposure fit). "
                 "Stage 1 (pose) runs on one thread while profiled, so that its sections do not overlap: "
                 "without --profile it overlaps pairs and graph edges on one thread per core and takes less "
                 "wall time.", ""]
        for stage, record in self.report().items():
            lines += [f"## {stage}: {record['wall_s']:.1f} s wall, {record['cpu_s']:.1f} CPU-s, "
                      f"{record['cores']:.2f} cores", "",
                      "| section | calls | wall s | share | CPU s | cores | ms/call | incl. wall s | incl. CPU s |",
                      "|---|---|---|---|---|---|---|---|---|"]
            for name, s in record["sections"].items():
                lines.append(f"| {name} | {s['calls']} | {s['wall_s']:.2f} | {100 * s['share']:.1f}% | "
                             f"{s['cpu_s']:.2f} | {s['cores']:.2f} | {1000 * s['wall_s'] / max(s['calls'], 1):.2f} | "
                             f"{s['inclusive_wall_s']:.2f} | {s['inclusive_cpu_s']:.2f} |")
            lines.append("")
        return "\n".join(lines)


_ACTIVE: Profiler | None = None  # the installed profiler; None: every timed function runs as it is


def timed(name: str, phases: str | None = None) -> Callable[[Callable[P, R]], Callable[P, R]]:
    """Time each call of the decorated function as section ``name`` while a profiler is installed; without one
    the call passes straight through (one global read, no device sync). ``phases``: the keyword argument
    through which the function adds its own phases' wall seconds to a dict (the rasterizer's forward:
    project, sort, blend); they become sections "<name>: <phase>". A call that passes that dict itself is not
    timed (its caller is keeping the clock)."""

    def decorate(function: Callable[P, R]) -> Callable[P, R]:
        @functools.wraps(function)
        def timed_call(*args: P.args, **kwargs: P.kwargs) -> R:
            profiler = _ACTIVE
            if profiler is None or (phases is not None and kwargs.get(phases) is not None):
                return function(*args, **kwargs)
            if phases is None:
                with profiler.section(name):
                    return function(*args, **kwargs)
            parts: dict[str, float] = {}
            with profiler.section(name):
                result = function(*args, **{**kwargs, phases: parts})
            profiler.split_last(parts)
            return result

        return timed_call

    return decorate


def stage_scope(function: Callable[Concatenate[str, P], R]) -> Callable[Concatenate[str, P], R]:
    """Time each call of ``function(stage, ...)`` as the whole of stage ``stage`` while a profiler is
    installed: the sections inside are booked to it."""

    @functools.wraps(function)
    def scoped(stage: str, *args: P.args, **kwargs: P.kwargs) -> R:
        profiler = _ACTIVE
        if profiler is None:
            return function(stage, *args, **kwargs)
        with profiler.stage_scope(stage):
            return function(stage, *args, **kwargs)

    return scoped


def install(profiler: Profiler) -> None:
    """Time every :func:`timed` function and :func:`stage_scope` with ``profiler`` until :func:`uninstall`."""
    global _ACTIVE
    _ACTIVE = profiler


def uninstall() -> None:
    """Stop timing: the timed functions pass straight through again."""
    global _ACTIVE
    _ACTIVE = None


def write(profiler: Profiler, folder: Path) -> tuple[Path, Path]:
    """Write ``folder/profile.json`` and ``folder/profile.md``; returns both paths."""
    folder = Path(folder)
    json_path, md_path = folder / "profile.json", folder / "profile.md"
    write_text(json_path, jsonout.dumps(profiler.report(), indent=2) + "\n")
    write_text(md_path, profiler.markdown())
    return json_path, md_path
