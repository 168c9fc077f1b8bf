"""Where the time goes: wall and CPU seconds per stage and per kind of work inside it.

:func:`install` wraps the functions that do the work (stage 1's optical flow, flow solve, ICP, RGB-D
odometry, verification and pose graph; the rasterizer forward and backward, losses, the k-view average
or the warped views, Adam, densification, exposure gradients, divergence checks, checkpoints and output
writing) with timers, so a run with ``taichi-gs reconstruct --profile``
writes ``OUT/profile.json`` and ``OUT/profile.md`` (:func:`write`). Each timed section synchronises
the device at its ends, and time is counted exclusively: a section nested in another (a render
inside a test-view exposure fit) is taken out of its parent. Each section also carries its inclusive
seconds (the parent with what is nested in it: how long the test-view exposure fits took, renders
included). "other host work" is a stage's wall time that no section covers (the Python training
loop, host-side pose updates, progress). CPU seconds are the process's user + sys time (every
thread), so CPU seconds / wall seconds is how many cores a section kept busy. Without
:func:`install` nothing is wrapped and nothing is slowed down.
"""

from __future__ import annotations

import functools
import os
import time
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from .io import jsonout
from .io.atomic import write_text


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


_INSTALLED: list[tuple[Any, str, Any]] = []  # (owner, attribute, original) of every wrapped function


def _replace(owner: Any, attribute: str, wrapper: Any) -> None:
    _INSTALLED.append((owner, attribute, getattr(owner, attribute)))
    wrapper._profiled = True
    setattr(owner, attribute, wrapper)


def _wrap(owner: Any, attribute: str, profiler: Profiler, name: str) -> None:
    original = getattr(owner, attribute)
    if getattr(original, "_profiled", False):
        return

    @functools.wraps(original)
    def timed(*args, **kwargs):
        with profiler.section(name):
            return original(*args, **kwargs)

    _replace(owner, attribute, timed)


def _wrap_forward(rasterizer_class: Any, profiler: Profiler) -> None:
    """Time the rasterizer's forward with its own phase clock (project, sort, blend) split out."""
    original = rasterizer_class.forward
    if getattr(original, "_profiled", False):
        return

    @functools.wraps(original)
    def forward(self, *args, **kwargs):
        if kwargs.get("timings") is not None:
            return original(self, *args, **kwargs)
        parts: dict[str, float] = {}
        with profiler.section("render forward"):
            view = original(self, *args, timings=parts, **kwargs)
        profiler.split_last(parts)
        return view

    _replace(rasterizer_class, "forward", forward)


# Stage 1's timed functions (attribute, section), wherever a stage-1 module binds them
STAGE1_SECTIONS = (
    ("dis_flow", "optical flow (DIS)"), ("_flow_solve", "flow solve (se(3))"), ("add_joint", "joint solve (se(3))"),
    ("sample_pair", "flow samples"), ("joint_normals", "depth normals"),
    ("depth_cloud", "point clouds (Open3D; import on first use)"), ("prepare_icp", "ICP"), ("align", "ICP"),
    ("rgbd_odometry", "RGB-D odometry (Open3D)"), ("frame_view", "verification"), ("verify", "verification"),
    ("flow_disagreement", "verification"), ("_information", "pose graph: information matrices"),
    ("optimise", "pose graph: optimisation"), ("fuse_points", "fused point cloud"),
)


def install(profiler: Profiler) -> None:
    """Wrap the stages' work functions with ``profiler``'s timers (for the rest of the process)."""
    from . import deblur_model, density, flow, pipeline, refine_model
    from .io import sequence
    from .kernels import affine, blur, losses, optim, splat, warp
    from .stages import checkpoint, deblur, divergence, pose, pose_edges, pose_frames, pose_pair, refine

    profiler.sync = splat.sync
    _wrap_forward(splat.Rasterizer, profiler)
    for owner, attribute, name in [
        (splat.Rasterizer, "backward", "render backward"),
        (losses, "l1_and_clipped_mse", "losses (device)"), (losses, "dssim", "losses (device)"),
        (losses, "masked_depth_l1", "losses (device)"), (losses, "opacity_binarization", "losses (device)"),
        (losses, "normalised_depth_l1_and_coverage", "losses (device)"),
        (affine, "forward", "colour transform (device)"), (affine, "backward", "colour transform (device)"),
        (blur, "average", "k-view average / spread"), (blur, "spread", "k-view average / spread"),
        (warp, "accumulate", "warped views (device)"), (warp, "backward", "warped views (device)"),
        (optim.Adam, "step", "Adam (Gaussians)"),
        (deblur_model, "exposure_pose_gradients", "exposure gradients (host)"),
        (density.DensityControl, "observe", "densification statistics"),
        (density.DensityControl, "densify_and_prune", "densify / prune / fill"),
        (deblur, "fill_uncovered", "densify / prune / fill"),
        (refine_model.DepthRefiner, "prune", "densify / prune / fill"),
        (refine_model.DepthRefiner, "reset_opacity", "densify / prune / fill"),
        (deblur_model.BlurScene, "step", "step host work (uploads, fills)"),
        (refine_model.DepthRefiner, "step", "step host work (uploads, fills)"),
        (deblur, "_refine_test_exposure", "test-view exposure fits"),
        (divergence.DivergenceGuard, "check_parameters", "divergence checks (parameter download)"),
        (checkpoint, "save", "checkpoints (I/O)"),
        (deblur, "_write_outputs", "outputs (renders, PLY, plots: I/O)"),
        (refine, "_write_outputs", "outputs (renders, PLY, plots: I/O)"),
        (flow, "dis_flow", "optical flow (DIS)"),
        # stage 1's modules import some of these from each other: each module's own binding is timed
        *[(module, attribute, name) for module in (pose, pose_pair, pose_frames, pose_edges)
          for attribute, name in STAGE1_SECTIONS if hasattr(module, attribute)],
        # frame reads in every stage, counted once each (not their callers, such as stage 3's _load_frames)
        (sequence.Sequence, "color", "input frames (I/O)"), (sequence.Sequence, "depth", "input frames (I/O)"),
    ]:
        _wrap(owner, attribute, profiler, name)
    original_run_stage = pipeline.run_stage
    if not getattr(original_run_stage, "_profiled", False):
        @functools.wraps(original_run_stage)
        def run_stage(stage: str, *args, **kwargs):
            with profiler.stage_scope(stage):
                return original_run_stage(stage, *args, **kwargs)

        _replace(pipeline, "run_stage", run_stage)


def installed() -> bool:
    """Whether :func:`install` has wrapped the work functions (a profiled run)."""
    return bool(_INSTALLED)


def uninstall() -> None:
    """Put back every function :func:`install` wrapped."""
    while _INSTALLED:
        owner, attribute, original = _INSTALLED.pop()
        setattr(owner, attribute, original)


def write(profiler: Profiler, folder: Path) -> tuple[Path, Path]:
    """Write ``folder/profile.json`` and ``folder/profile.md``; returns both paths."""
    folder = Path(folder)
    json_path, md_path = folder / "profile.json", folder / "profile.md"
    write_text(json_path, jsonout.dumps(profiler.report(), indent=2) + "\n")
    write_text(md_path, profiler.markdown())
    return json_path, md_path
