"""Training checkpoints of stages 2 and 3: one ``.npz`` holding the iteration, the config it was
made with, numeric state (model, optimisers, per-frame parameters) and JSON records (history, RNG).

A checkpoint resumes a run only when it was made with the same config and layout (``FORMAT``);
anything else starts afresh.
It is written atomically, so a run killed while saving keeps the previous one.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .. import profiling
from ..io.atomic import atomic_path

FORMAT = 2  # the layout of the arrays; bump when a model's state() changes its keys
_RESERVED = ("format", "iteration", "config")
_RECORD = "record_"


@dataclass
class Checkpoint:
    """What ``load`` gives back: the iteration to resume at, the arrays and the records saved."""

    iteration: int
    arrays: dict[str, np.ndarray]
    records: dict[str, Any]

    def prefixed(self, prefix: str) -> dict[str, np.ndarray]:
        """The arrays saved under ``prefix_`` (e.g. a model's ``state()``), without the prefix."""
        return {k[len(prefix) + 1:]: v for k, v in self.arrays.items() if k.startswith(prefix + "_")}


def prefixed(prefix: str, arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """``arrays`` keyed ``prefix_<key>``, to save several states side by side."""
    return {f"{prefix}_{k}": v for k, v in arrays.items()}


@profiling.timed("checkpoints (I/O)")
def save(path: Path, iteration: int, config: Any, arrays: dict[str, np.ndarray], records: dict[str, Any]) -> None:
    """Write a checkpoint of ``config``'s run after ``iteration`` iterations."""
    clash = [k for k in arrays if k in _RESERVED or k.startswith(_RECORD)]
    if clash:
        raise ValueError(f"checkpoint array names {clash} are reserved")
    encoded = {_RECORD + k: json.dumps(v) for k, v in records.items()}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, format=FORMAT, iteration=iteration, config=json.dumps(dataclasses.asdict(config)), **arrays, **encoded)


def load(path: Path, config: Any) -> Checkpoint | None:
    """The checkpoint at ``path`` if there is one made with ``config`` in this layout, else None."""
    if not path.is_file():
        return None
    with np.load(path, allow_pickle=False) as state:
        if "format" not in state.files or int(state["format"]) != FORMAT:
            return None
        if json.loads(str(state["config"])) != json.loads(json.dumps(dataclasses.asdict(config))):
            return None
        arrays = {k: state[k] for k in state.files if k not in _RESERVED and not k.startswith(_RECORD)}
        records = {k[len(_RECORD):]: json.loads(str(state[k])) for k in state.files if k.startswith(_RECORD)}
        return Checkpoint(int(state["iteration"]), arrays, records)
