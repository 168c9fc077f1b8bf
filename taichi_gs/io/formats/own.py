"""taichi-gs's own layout (frames.txt, intrinsics.json; see ``io.sequence``)."""

from __future__ import annotations

from pathlib import Path

from ..sequence import Sequence, _open_own_layout
from .common import ReadOptions

NAME = "taichi-gs"


def detect(root: Path) -> bool:
    return (root / "frames.txt").is_file()


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    return _open_own_layout(root, options.override)
