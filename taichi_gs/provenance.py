"""What a stage's results were made from: fingerprints of its inputs.

A stage's fingerprint hashes everything its outputs depend on: the input sequence (its folder, layout,
how it was loaded, intrinsics and depth scale, timestamps, and every frame file's name, size and
modification time), the stage's config, and the content of the upstream files it reads (stage 1's
trajectory and cloud for stage 2, stage 2's trajectory and splats for stage 3, precomputed flows).
``pipeline.py`` stores it in ``OUT/<stage>/inputs.json`` when the stage starts (its caches and
checkpoints belong to it) and in ``done.json`` when it ends; any difference reruns the stage.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from .io.readout import READOUT_KEY
from .io.sequence import Sequence


def _digest(value: Any) -> str:
    return hashlib.sha256(json.dumps(value, sort_keys=True, default=str).encode()).hexdigest()


def _stat(path: Path) -> list[Any]:
    stat = path.stat()
    return [path.name, stat.st_size, stat.st_mtime_ns]


def file_digest(path: Path) -> str:
    """SHA-256 of a file's content."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def sequence_record(sequence: Sequence) -> dict[str, Any]:
    """The facts about an input sequence that stage results depend on (readable, for done.json)."""
    files = [[_stat(rgb), _stat(depth)] for rgb, depth in zip(sequence.rgb_paths, sequence.depth_paths)]
    record = {
        "root": str(Path(sequence.root).resolve()),
        "layout": sequence.layout,
        "load_options": sequence.load_options,
        "intrinsics": dataclasses.asdict(sequence.intrinsics),
        "frames": len(sequence),
        "timestamps_sha256": _digest([round(float(t), 6) for t in sequence.timestamps]),
        "files_sha256": _digest(files),
    }
    readout_ms = sequence.source.get(READOUT_KEY)
    if readout_ms is not None:  # the own layout's rolling-shutter readout (only then: other records keep theirs)
        record[READOUT_KEY] = readout_ms
    return record


def stage_fingerprint(stage: str, sequence: Sequence, config: dict[str, Any],
                      upstream_files: Mapping[str, Path] | None = None,
                      upstream_dirs: Iterable[Path] = ()) -> dict[str, Any]:
    """Fingerprint record of one stage: {"sha256": ..., "inputs": {...}} (the inputs, readable).

    ``upstream_files`` (role -> path) are hashed by content; ``upstream_dirs`` (e.g. precomputed
    flows) by the name, size and modification time of every file in them."""
    inputs = {
        "stage": stage,
        "sequence": sequence_record(sequence),
        "config": config,
        "upstream": {role: file_digest(Path(p)) for role, p in (upstream_files or {}).items() if Path(p).is_file()},
        "upstream_dirs": [_digest(sorted(_stat(p) for p in Path(d).iterdir() if p.is_file()))
                          for d in upstream_dirs if Path(d).is_dir()],
    }
    return {"sha256": _digest(inputs), "inputs": inputs}
