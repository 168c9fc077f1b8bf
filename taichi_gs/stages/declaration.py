"""A stage of the pipeline, declared once in its own module.

Each stage module (``pose``, ``refine``, ``deblur``) ends with ``STAGE = StageDeclaration(...)``:
its name, title, config class and presets, the files it must leave behind, the upstream files its
result depends on, how its config is completed from earlier stages, and how the pipeline runs it.
``pipeline.py`` loops over these declarations and knows nothing stage-specific.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# The stages in the order they run; each is the module ``taichi_gs.stages.<name>``.
STAGE_NAMES = ("pose", "refine", "deblur")

# progress_factory(description, total) -> context manager yielding update(done, total, **info)
ProgressFactory = Callable[[str, int], AbstractContextManager[Callable[..., None]]]


@dataclass(frozen=True)
class StageContext:
    """What the pipeline hands a stage's run: the input, the run folder, the resolved config."""

    sequence: Any  # io.sequence.Sequence
    out: Path
    config: Any
    progress: ProgressFactory
    poses: Path | None = None  # replaces stage 1's trajectory as stage 2's input
    points: Path | None = None  # replaces stage 1's fused cloud as stage 2's input
    threads: int | None = None  # the threads a stage may run on (one under --profile); None: its config's


@dataclass(frozen=True)
class StageRun:
    """What a stage's run gives back to the pipeline."""

    summary: str  # one line for the console and done.json
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class StageInputs:
    """The files outside the sequence that a stage's result depends on (see ``provenance.py``)."""

    files: dict[str, Path] = field(default_factory=dict)  # hashed by content
    folders: list[Path] = field(default_factory=list)  # fingerprinted by file names, sizes and times


def _as_given(config: Any, sections: Mapping[str, Any], out: Path | None) -> Any:
    return config


@dataclass(frozen=True)
class StageDeclaration:
    """One stage: everything the pipeline needs to run, skip, resume or clear it."""

    name: str
    title: str
    config_type: type
    presets: Mapping[str, Any]  # "fast" (CPU-sized) and "paper" (the method's)
    outputs: tuple[str, ...]  # files in OUT/<name>/ that a finished stage leaves
    run: Callable[[StageContext], StageRun]
    # the upstream files of a run: (run folder, config, --poses, --points) -> StageInputs
    inputs: Callable[[Path, Any, Path | None, Path | None], StageInputs]
    # the config with values that depend on earlier stages filled in: (config, all sections, run folder)
    resolve: Callable[[Any, Mapping[str, Any], Path | None], Any] = _as_given


def declared(name: str) -> StageDeclaration:
    """The declaration of stage ``name`` (its module is imported on first use)."""
    if name not in STAGE_NAMES:
        raise ValueError(f"unknown stage {name!r}; stages are {', '.join(STAGE_NAMES)}")
    return importlib.import_module(f"{__package__}.{name}").STAGE


def later_stages(name: str) -> tuple[str, ...]:
    """The stages that run after ``name`` and consume its outputs."""
    return STAGE_NAMES[STAGE_NAMES.index(name) + 1:]
