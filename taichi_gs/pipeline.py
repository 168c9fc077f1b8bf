"""Runs the three stages in a row: output folder layout, resolved config, provenance and resume.

A stage is *done* when ``OUT/<stage>/done.json`` exists, its outputs are all present, and the
fingerprint it records (``provenance.py``: input sequence, loading options, config, upstream files)
equals the one of the run asked for now. ``done.json`` is written last (atomically), so a run killed
anywhere leaves the stage not done; rerunning then continues the stage from its own cache or
checkpoint (stage 1's per-pair files, stages 2 and 3's ``checkpoint.npz``), which belong to the
fingerprint in ``OUT/<stage>/inputs.json``: a stage whose inputs changed starts from scratch. When
a stage runs, every later stage is cleared, since its inputs change.

Nothing here is specific to one stage: each stage declares itself once in its own module
(``stages/declaration.py``), and this module loops over the declarations.
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from . import profiling
from .config import read_config, write_config
from .errors import InputError
from .io.atomic import write_text
from .io import jsonout
from .io.sequence import Sequence
from .stages.declaration import STAGE_NAMES as STAGES
from .stages.declaration import ProgressFactory, StageContext, StageRun, declared, later_stages
from .validation import validate_sections

log = logging.getLogger("taichi_gs")
DONE_FILE = "done.json"
CONFIG_FILE = "config.toml"
RUN_INFO = "run.json"
INPUTS_FILE = "inputs.json"


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
    from .io.load import load_sequence
    from .io.sequence import IntrinsicsOverride

    record = _read_run_info(run_dir) if gt is None or (run_dir / RUN_INFO).is_file() else {}
    options = dict(record.get("load_options") or {})
    folder = gt if gt is not None else Path(record["sequence"])
    if gt is not None:
        options.pop("format", None)
        options.pop("camera", None)
        options.pop("depth_latency", None)
    elif options.get("format") == "7scenes" and options.get("camera") is None:
        options["camera"] = "shipped"  # recorded before 7-Scenes was read registered by default
    elif options.get("format") == "tum" and "depth_latency" not in options:
        options["depth_latency"] = 0.0  # recorded with none (before TUM fr1 was paired by its depth latency)
    try:
        override = IntrinsicsOverride(**options.pop("override", {}))
        return load_sequence(folder, override, **options)
    except TypeError as err:
        raise InputError(run_dir / RUN_INFO, f"unknown loading options ({err})",
                         "rerun 'taichi-gs reconstruct SEQUENCE --out' on this folder to rewrite it") from None


def resolve_sections(preset: str, config_file: Path | None = None, only: tuple[str, ...] = STAGES) -> dict[str, Any]:
    """The preset's configs of the ``only`` stages, overridden by a TOML file's tables (the file
    may hold every stage's table; all are checked, those of other stages are not used)."""
    sections = {}
    for stage in STAGES:
        presets = declared(stage).presets
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

    upstream = declared(stage).inputs(out, section, poses, points)
    return stage_fingerprint(stage, sequence, _config_record(section), upstream.files, upstream.folders)


def stage_done(out: Path, stage: str, fingerprint: dict[str, Any]) -> bool:
    """True when the stage finished with these inputs and config and all its outputs are present."""
    stage_dir = out / stage
    if not all((stage_dir / name).is_file() for name in declared(stage).outputs):
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
    later = later_stages(stage)
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


@profiling.stage_scope
def run_stage(stage: str, sequence: Sequence, out: Path, section: Any, progress: ProgressFactory,
              poses: Path | None = None, points: Path | None = None, threads: int | None = None) -> str:
    """Run one stage on ``sequence`` into ``out`` with its resolved config (``resolve_stage``), write
    its ``config.toml`` and mark it done; returns a one-line summary. ``poses``/``points`` replace
    stage 1's outputs as stage 2's inputs; ``threads`` (one under --profile) the thread count of its config,
    which its results do not depend on. Caches and checkpoints of earlier runs are resumed only if
    made from the same inputs; later stages are cleared."""
    start = time.perf_counter()
    fingerprint = stage_inputs(stage, sequence, out, section, poses, points)
    _prepare_stage_dir(out, stage, fingerprint)
    write_config(out / stage / CONFIG_FILE, {stage: section})
    result = _execute(stage, StageContext(sequence, out, section, progress, poses, points, threads))
    _mark_done(out, stage, section, fingerprint, time.perf_counter() - start, _arch(), result.summary, result.warnings)
    return result.summary


def _execute(stage: str, context: StageContext) -> StageRun:
    """The stage's own work, its warnings logged."""
    result = declared(stage).run(context)
    for warning in result.warnings:
        log.warning("%s: %s", stage, warning)
    return result


def reconstruct(
    sequence: Sequence, out: Path, sections: dict[str, Any], progress: ProgressFactory,
    force: str | None = None, on_stage: Callable[[StageReport], None] | None = None, threads: int | None = None,
) -> list[StageReport]:
    """Run pose, refine and deblur into ``out``, skipping stages already done with the same inputs
    and config.

    ``force``: rerun from this stage on; ``threads``: as for :func:`run_stage`. Writes ``out/config.toml``
    (the resolved config) and ``out/run.json`` (the input sequence). Returns one report per stage.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    check_run_input(out, sequence)
    if force is not None:
        if force not in STAGES:
            raise InputError(None, f"unknown stage {force!r} for --force", f"use one of {', '.join(STAGES)}")
        clear_stages(out, force)
    write_run_info(out, sequence)
    write_config(out / CONFIG_FILE, sections)
    reports: list[StageReport] = []
    for stage in STAGES:
        section = resolve_stage(stage, sections, out)
        fingerprint = stage_inputs(stage, sequence, out, section)
        if stage_done(out, stage, fingerprint):
            done = read_done(out, stage) or {}
            report = StageReport(stage, False, float(done.get("seconds", 0.0)), float(done.get("peak_rss_mb", 0.0)),
                                 str(done.get("summary", "")))
        else:
            start = time.perf_counter()
            summary = run_stage(stage, sequence, out, section, progress, threads=threads)
            report = StageReport(stage, True, time.perf_counter() - start, peak_rss_mb(), summary)
        reports.append(report)
        if on_stage is not None:
            on_stage(report)
    return reports


def resolve_stage(stage: str, sections: dict[str, Any], out: Path | None = None) -> Any:
    """A stage's config with the values that depend on earlier stages filled in (by the stage's own
    rule: refine's voxel size comes from stage 1's, as run in ``out`` when it ran there)."""
    return declared(stage).resolve(sections[stage], sections, out)


def iter_stage_records(out: Path) -> Iterator[tuple[str, dict[str, Any]]]:
    """(stage, done record) for every finished stage of a run folder."""
    for stage in STAGES:
        record = read_done(out, stage)
        if record is not None:
            yield stage, record
