"""Runs the three stages in a row: output folder layout, resolved config, provenance and resume.

A stage is *done* when ``OUT/<stage>/done.json`` exists, its outputs are all present, and the
fingerprint it records (``provenance.py``: input sequence, loading options, config, upstream files)
equals the one of the run asked for now. ``done.json`` is written last (atomically), so a run killed
anywhere leaves the stage not done; rerunning then continues the stage from its own cache or
checkpoint (stage 1's per-pair files, stages 2 and 3's ``checkpoint.npz``), which belong to the
fingerprint in ``OUT/<stage>/inputs.json``: a stage whose inputs changed starts from scratch. When
a stage runs, every later stage is cleared, since its inputs change.
"""

from __future__ import annotations

import dataclasses
import json
import logging
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
from .io import jsonout
from .io.sequence import Sequence
from .validation import validate_sections

log = logging.getLogger("taichi_gs")
STAGES = ("pose", "refine", "deblur")
DONE_FILE = "done.json"
STAGE_OUTPUTS = {
    "pose": ("trajectory.txt", "points.ply", "pairs.json"),
    "refine": ("trajectory.txt", "splats.ply", "points.ply"),
    "deblur": ("trajectory.txt", "exposure.txt", "splats.ply", "split.json"),
}
RUN_INFO = "run.json"
INPUTS_FILE = "inputs.json"
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


def write_run_info(run_dir: Path, sequence: Sequence) -> None:
    """Record which sequence a run folder was made from, and how it was loaded, so later commands
    (refine, deblur, eval, render, export) reopen exactly the same sequence."""
    record = {"sequence": str(Path(sequence.root).resolve()), "load_options": sequence.load_options}
    write_text(run_dir / RUN_INFO, jsonout.dumps(record, indent=2) + "\n")


def _read_run_info(run_dir: Path) -> dict[str, Any]:
    info = run_dir / RUN_INFO
    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder not found", "give the --out folder of an earlier run")
    if not info.is_file():
        raise InputError(run_dir, f"no {RUN_INFO} naming the input sequence",
                         "give a folder written by 'taichi-gs pose' or 'taichi-gs reconstruct'")
    try:
        record = json.loads(info.read_text(encoding="utf-8"))
        if not isinstance(record, dict) or not isinstance(record.get("sequence"), str):
            raise ValueError("no sequence entry")
    except (ValueError, UnicodeDecodeError) as err:
        raise InputError(info, f"corrupt run record ({err})",
                         "rerun 'taichi-gs reconstruct SEQUENCE --out' on this folder to rewrite it") from None
    return record


def check_run_input(run_dir: Path, sequence: Sequence) -> None:
    """Refuse to put a different input sequence into a run folder that holds another one's results."""
    info = run_dir / RUN_INFO
    if not info.is_file():
        return
    recorded = _read_run_info(run_dir)["sequence"]
    given = str(Path(sequence.root).resolve())
    if recorded != given and any((run_dir / stage).is_dir() for stage in STAGES):
        raise InputError(run_dir, f"holds the results of another input sequence ({recorded})",
                         "give another --out, or delete this folder first")


def open_run_sequence(run_dir: Path, gt: Path | None = None) -> Sequence:
    """The input sequence of a run, reopened with the options it was loaded with (format, camera,
    every, scale, intrinsics flags, ...). ``gt`` (another copy of the input, perhaps in another
    layout) replaces the recorded folder; its format and camera are detected afresh."""
    from .io.sequence import IntrinsicsOverride, load_sequence

    record = _read_run_info(run_dir) if gt is None or (run_dir / RUN_INFO).is_file() else {}
    options = dict(record.get("load_options") or {})
    folder = gt if gt is not None else Path(record["sequence"])
    if gt is not None:
        options.pop("format", None)
        options.pop("camera", None)
    try:
        override = IntrinsicsOverride(**options.pop("override", {}))
        return load_sequence(folder, override, **options)
    except TypeError as err:
        raise InputError(run_dir / RUN_INFO, f"unknown loading options ({err})",
                         "rerun 'taichi-gs reconstruct SEQUENCE --out' on this folder to rewrite it") from None


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
    validate_sections(sections, config_file)
    return {stage: sections[stage] for stage in only}


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far, in MiB."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss / (1024 * 1024) if sys.platform == "darwin" else rss / 1024


def _config_record(section: Any) -> dict[str, Any]:
    return json.loads(jsonout.dumps(dataclasses.asdict(section)))


def stage_inputs(stage: str, sequence: Sequence, out: Path, section: Any, poses: Path | None = None,
                 points: Path | None = None) -> dict[str, Any]:
    """The fingerprint record of a stage run with these inputs (see ``provenance.py``)."""
    from .provenance import stage_fingerprint

    upstream: dict[str, Path] = {}
    dirs: list[Path] = []
    if stage == "pose" and getattr(section, "flow_dir", ""):
        dirs.append(Path(section.flow_dir))
    elif stage == "refine":
        upstream = {"poses": poses or out / "pose" / "trajectory.txt", "points": points or out / "pose" / "points.ply"}
    elif stage == "deblur":
        upstream = {"poses": out / "refine" / "trajectory.txt", "splats": out / "refine" / "splats.ply"}
    return stage_fingerprint(stage, sequence, _config_record(section), upstream, dirs)


def stage_done(out: Path, stage: str, fingerprint: dict[str, Any]) -> bool:
    """True when the stage finished with these inputs and config and all its outputs are present."""
    stage_dir = out / stage
    if not all((stage_dir / name).is_file() for name in STAGE_OUTPUTS[stage]):
        return False
    recorded = read_done(out, stage)
    return recorded is not None and recorded.get("fingerprint") == fingerprint["sha256"]


def read_done(out: Path, stage: str) -> dict[str, Any] | None:
    """The done record of a finished stage (config, seconds, peak memory, arch), or None."""
    marker = out / stage / DONE_FILE
    try:
        record = json.loads(marker.read_text()) if marker.is_file() else None
    except (ValueError, UnicodeDecodeError):
        return None
    return record if isinstance(record, dict) else None


def _mark_done(out: Path, stage: str, section: Any, fingerprint: dict[str, Any], seconds: float, arch: str,
               summary: str, warnings: list[str]) -> None:
    record = {"config": _config_record(section), "fingerprint": fingerprint["sha256"], "seconds": seconds,
              "peak_rss_mb": peak_rss_mb(), "arch": arch, "summary": summary, "warnings": warnings}
    write_text(out / stage / DONE_FILE, jsonout.dumps(record, indent=2) + "\n")


def _prepare_stage_dir(out: Path, stage: str, fingerprint: dict[str, Any]) -> None:
    """Keep the stage's caches and checkpoint only if they were made from the same inputs; clear
    every later stage; record the inputs the stage now runs on."""
    stage_dir = out / stage
    marker = stage_dir / INPUTS_FILE
    try:
        recorded = json.loads(marker.read_text()).get("sha256") if marker.is_file() else None
    except (ValueError, UnicodeDecodeError, AttributeError):
        recorded = None
    if stage_dir.is_dir() and recorded != fingerprint["sha256"]:
        shutil.rmtree(stage_dir)
    else:
        (stage_dir / DONE_FILE).unlink(missing_ok=True)
    later = STAGES[STAGES.index(stage) + 1:]
    if later:
        clear_stages(out, later[0])
    write_text(marker, jsonout.dumps(fingerprint, indent=2) + "\n")


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
    one-line summary). ``poses``/``points`` replace stage 1's outputs as stage 2's inputs. Caches and
    checkpoints of earlier runs are resumed only if made from the same inputs; later stages are cleared."""
    start = time.perf_counter()
    fingerprint = stage_inputs(stage, sequence, out, section, poses, points)
    _prepare_stage_dir(out, stage, fingerprint)
    section, summary, warnings = _execute(stage, sequence, out, section, progress, poses, points)
    _mark_done(out, stage, section, fingerprint, time.perf_counter() - start, _arch(), summary, warnings)
    return section, summary


def _execute(stage: str, sequence: Sequence, out: Path, section: Any, progress: ProgressFactory,
             poses: Path | None, points: Path | None) -> tuple[Any, str, list[str]]:
    """The stage's own work: (its config as run, a one-line summary, its warnings)."""
    if stage == "pose":
        from .stages.pose import run_pose

        with progress(STAGE_TITLES[stage], len(sequence) - 1) as update:
            result = run_pose(sequence, out, section, progress=lambda done, total: update(done, total))
        weak = sum(1 for p in result.pairs if p.get("weak"))
        summary = f"{len(sequence) - 1} pairs, {weak} weak"
    elif stage == "refine":
        from .stages.refine import load_stage1, run_refine

        _, initial, cloud, colors, voxel = load_stage1(out, poses, points)
        run_section = section if section.voxel_size > 0 else dataclasses.replace(section, voxel_size=voxel)
        write_config(out / "refine" / "config.toml", {"refine": run_section})
        with progress(STAGE_TITLES[stage], run_section.iterations_per_frame * len(sequence)) as update:
            result = run_refine(sequence, initial, cloud, colors, out, run_section, progress=update)
        summary = f"{result.gaussians} Gaussians, {result.seconds_per_iteration * 1000:.1f} ms/iteration"
        section = run_section
    elif stage == "deblur":
        from .stages.deblur import run_deblur

        write_config(out / "deblur" / "config.toml", {"deblur": section})
        with progress(STAGE_TITLES[stage], 1) as update:
            result = run_deblur(sequence, out, section, progress=update)
        summary = result.summary()
    else:
        raise ValueError(f"unknown stage {stage!r}")
    warnings = [str(w) for w in getattr(result, "warnings", [])]
    for warning in warnings:
        log.warning("%s: %s", stage, warning)
    return section, summary, warnings


def reconstruct(
    sequence: Sequence, out: Path, sections: dict[str, Any], progress: ProgressFactory,
    force: str | None = None, on_stage: Callable[[StageReport], None] | None = None,
) -> list[StageReport]:
    """Run pose, refine and deblur into ``out``, skipping stages already done with the same inputs
    and config.

    ``force``: rerun from this stage on. Writes ``out/config.toml`` (the resolved config) and
    ``out/run.json`` (the input sequence). Returns one report per stage.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    check_run_input(out, sequence)
    if force is not None:
        if force not in STAGES:
            raise InputError(None, f"unknown stage {force!r} for --force", f"use one of {', '.join(STAGES)}")
        clear_stages(out, force)
    write_run_info(out, sequence)
    write_config(out / "config.toml", sections)
    reports: list[StageReport] = []
    for stage in STAGES:
        section = resolve_stage(stage, sections)
        fingerprint = stage_inputs(stage, sequence, out, section)
        if stage_done(out, stage, fingerprint):
            done = read_done(out, stage) or {}
            report = StageReport(stage, False, float(done.get("seconds", 0.0)), float(done.get("peak_rss_mb", 0.0)),
                                 str(done.get("summary", "")))
        else:
            start = time.perf_counter()
            _, summary = run_stage(stage, sequence, out, section, progress)
            report = StageReport(stage, True, time.perf_counter() - start, peak_rss_mb(), summary)
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
