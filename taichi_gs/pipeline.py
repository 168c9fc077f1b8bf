"""Runs the three stages in a row: output folder layout, resolved config, and resume.

A stage is *done* when ``OUT/<stage>/done.json`` exists, its outputs are all present, and the
config it records equals the config asked for now. ``done.json`` is written last (atomically), so a
run killed anywhere leaves the stage not done; rerunning then continues the stage from its own
cache or checkpoint (stage 1's per-pair files, stages 2 and 3's ``checkpoint.npz``). When a stage
reruns, every later stage starts again from scratch, since its inputs changed.
"""

from __future__ import annotations

import dataclasses
import json
import resource
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from .config import read_config, write_config
from .errors import InputError
from .io.atomic import write_text
from .io.sequence import Sequence

STAGES = ("pose", "refine", "deblur")
DONE_FILE = "done.json"
STAGE_OUTPUTS = {
    "pose": ("trajectory.txt", "points.ply", "pairs.json"),
    "refine": ("trajectory.txt", "splats.ply", "points.ply"),
    "deblur": ("trajectory.txt", "exposure.txt", "splats.ply", "split.json"),
}
RUN_INFO = "run.json"
STAGE_TITLES = {"pose": "stage 1: pose", "refine": "stage 2: refine", "deblur": "stage 3: deblur"}

# progress_factory(description, total) -> context manager yielding update(done, total, **info)
ProgressFactory = Callable[[str, int], AbstractContextManager[Callable[..., None]]]


@dataclass
class StageReport:
    """What running (or skipping) one stage gave."""

    stage: str
    ran: bool
    seconds: float
    peak_rss_mb: float
    summary: str


def write_run_info(run_dir: Path, sequence_folder: Path, source: dict[str, Any] | None = None) -> None:
    """Record which sequence a run folder was made from and how it was read (format, every, scale,
    camera, intrinsics flags: ``Sequence.source``), so later commands reopen it the same way."""
    info = {"sequence": str(Path(sequence_folder).resolve()), **(source or {})}
    write_text(run_dir / RUN_INFO, json.dumps(info, indent=2) + "\n")


def sequence_folder(run_dir: Path, gt: Path | None = None) -> Path:
    """The input sequence of a run: ``gt`` if given, else the one recorded in RUN_DIR/run.json."""
    if gt is not None:
        return gt
    return Path(_run_info(run_dir)["sequence"])


def _run_info(run_dir: Path) -> dict[str, Any]:
    info = run_dir / RUN_INFO
    if not info.is_file():
        raise InputError(run_dir, f"no {RUN_INFO} naming the input sequence", "pass --gt SEQUENCE_FOLDER")
    try:
        record = json.loads(info.read_text())
    except ValueError:
        record = None
    if not isinstance(record, dict) or "sequence" not in record:
        raise InputError(info, "is not a run record naming the input sequence", "rerun 'taichi-gs reconstruct' or pass --gt")
    return record


def open_run_sequence(run_dir: Path, gt: Path | None = None) -> Sequence:
    """The input sequence of a run, read as the run read it (run.json's format, every, scale, camera,
    intrinsics flags). With ``gt`` (another copy of the input), only every and scale are reused."""
    from .io.sequence import IntrinsicsOverride, load_sequence

    if gt is not None:
        record = _run_info(run_dir) if (run_dir / RUN_INFO).is_file() else {}
        return load_sequence(gt, every=int(record.get("every", 1)), scale=float(record.get("scale", 1.0)))
    record = _run_info(run_dir)
    return load_sequence(record["sequence"], IntrinsicsOverride(**record.get("intrinsics", {})),
                         format=record.get("format"), camera=record.get("camera"),
                         every=int(record.get("every", 1)), scale=float(record.get("scale", 1.0)))


def stage_presets(stage: str) -> dict[str, Any]:
    """A stage's configs by preset name ("fast": CPU-sized schedules; "paper": the method's)."""
    if stage == "pose":
        from .stages.pose import PoseConfig

        return {"fast": PoseConfig(), "paper": PoseConfig(icp_max_points=0)}  # paper: ICP on every point
    if stage == "refine":
        from .stages.refine import PRESETS

        return PRESETS
    from .stages.deblur import PRESETS

    return PRESETS


def resolve_sections(preset: str, config_file: Path | None = None, only: tuple[str, ...] = STAGES) -> dict[str, Any]:
    """The preset's configs of the ``only`` stages, overridden by a TOML file's tables (the file
    may hold every stage's table; all are checked, those of other stages are not used)."""
    sections = {}
    for stage in STAGES:
        presets = stage_presets(stage)
        if preset not in presets:
            raise InputError(None, f"unknown preset {preset!r}", f"use one of {', '.join(presets)}")
        sections[stage] = presets[preset]
    if config_file is not None:
        sections = read_config(config_file, sections)
    return {stage: sections[stage] for stage in only}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024


def _config_record(section: Any) -> dict[str, Any]:
    return json.loads(json.dumps(dataclasses.asdict(section), default=list))


def stage_done(out: Path, stage: str, section: Any) -> bool:
    """True when the stage finished with this config and all its outputs are present."""
    stage_dir = out / stage
    marker = stage_dir / DONE_FILE
    if not marker.is_file() or not all((stage_dir / name).is_file() for name in STAGE_OUTPUTS[stage]):
        return False
    try:
        recorded = json.loads(marker.read_text())
    except ValueError:
        return False
    return recorded.get("config") == _config_record(section)


def read_done(out: Path, stage: str) -> dict[str, Any] | None:
    """The done record of a finished stage (config, seconds, peak memory, arch), or None."""
    marker = out / stage / DONE_FILE
    try:
        return json.loads(marker.read_text()) if marker.is_file() else None
    except ValueError:
        return None


def _mark_done(out: Path, stage: str, section: Any, seconds: float, arch: str, summary: str) -> None:
    record = {"config": _config_record(section), "seconds": seconds, "peak_rss_mb": peak_rss_mb(), "arch": arch,
              "summary": summary}
    write_text(out / stage / DONE_FILE, json.dumps(record, indent=2) + "\n")


def clear_stages(out: Path, first: str) -> None:
    """Delete the outputs, caches and checkpoints of ``first`` and every later stage."""
    for stage in STAGES[STAGES.index(first):]:
        if (out / stage).is_dir():
            shutil.rmtree(out / stage)


def _arch() -> str:
    from .kernels import runtime

    backend = runtime.current()
    return backend.arch if backend is not None else "none"


def run_stage(stage: str, sequence: Sequence, out: Path, section: Any, progress: ProgressFactory,
              poses: Path | None = None, points: Path | None = None) -> tuple[Any, str]:
    """Run one stage on ``sequence`` into ``out`` and mark it done; returns (its config as run, a
    one-line summary). ``poses``/``points`` replace stage 1's outputs as stage 2's inputs."""
    start = time.perf_counter()
    if stage == "pose":
        from .stages.pose import run_pose

        with progress(STAGE_TITLES[stage], len(sequence) - 1) as update:
            result = run_pose(sequence, out, section, progress=lambda done, total: update(done, total))
        weak = sum(1 for p in result.pairs if p.get("weak"))
        summary = f"{len(sequence) - 1} pairs, {weak} weak"
    elif stage == "refine":
        from .stages.refine import load_stage1, run_refine

        _, initial, cloud, colors, voxel = load_stage1(out, poses, points)
        if section.voxel_size <= 0:
            section = dataclasses.replace(section, voxel_size=voxel)
        write_config(out / "refine" / "config.toml", {"refine": section})
        with progress(STAGE_TITLES[stage], section.iterations_per_frame * len(sequence)) as update:
            result = run_refine(sequence, initial, cloud, colors, out, section, progress=update)
        summary = f"{result.gaussians} Gaussians, {result.seconds_per_iteration * 1000:.1f} ms/iteration"
    elif stage == "deblur":
        from .stages.deblur import run_deblur

        write_config(out / "deblur" / "config.toml", {"deblur": section})
        with progress(STAGE_TITLES[stage], 1) as update:
            result = run_deblur(sequence, out, section, progress=update)
        summary = result.summary()
    else:
        raise ValueError(f"unknown stage {stage!r}")
    _mark_done(out, stage, section, time.perf_counter() - start, _arch(), summary)
    return section, summary


def reconstruct(
    sequence: Sequence, out: Path, sections: dict[str, Any], progress: ProgressFactory,
    force: str | None = None, on_stage: Callable[[StageReport], None] | None = None,
) -> list[StageReport]:
    """Run pose, refine and deblur into ``out``, skipping stages already done with the same config.

    ``force``: rerun from this stage on. Writes ``out/config.toml`` (the resolved config) and
    ``out/run.json`` (the input sequence). Returns one report per stage.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if force is not None:
        if force not in STAGES:
            raise InputError(None, f"unknown stage {force!r} for --force", f"use one of {', '.join(STAGES)}")
        clear_stages(out, force)
    write_run_info(out, sequence.root, getattr(sequence, "source", None))
    write_config(out / "config.toml", sections)
    reports: list[StageReport] = []
    upstream_ran = False
    for stage in STAGES:
        section = resolve_stage(stage, sections)
        if not upstream_ran and stage_done(out, stage, section):
            done = read_done(out, stage) or {}
            report = StageReport(stage, False, float(done.get("seconds", 0.0)), float(done.get("peak_rss_mb", 0.0)),
                                 str(done.get("summary", "")))
        else:
            if upstream_ran or (out / stage / DONE_FILE).is_file():
                clear_stages(out, stage)  # inputs or config changed: no stale cache may be resumed
            start = time.perf_counter()
            _, summary = run_stage(stage, sequence, out, section, progress)
            report = StageReport(stage, True, time.perf_counter() - start, peak_rss_mb(), summary)
            upstream_ran = True
        reports.append(report)
        if on_stage is not None:
            on_stage(report)
    return reports


def resolve_stage(stage: str, sections: dict[str, Any]) -> Any:
    """A stage's config with values that depend on earlier stages filled in (refine's voxel size)."""
    section = sections[stage]
    if stage == "refine" and section.voxel_size <= 0:
        section = dataclasses.replace(section, voxel_size=sections["pose"].voxel_size_m)
    return section


def iter_stage_records(out: Path) -> Iterator[tuple[str, dict[str, Any]]]:
    """(stage, done record) for every finished stage of a run folder."""
    for stage in STAGES:
        record = read_done(out, stage)
        if record is not None:
            yield stage, record
