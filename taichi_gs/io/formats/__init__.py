"""Readers of public RGB-D layouts, each returning a ``Sequence``; the layout is recognised from a
folder's contents or named with ``--format``.

Every reader module has ``NAME``, ``detect(root) -> bool`` (the folder holds this layout's marker
files) and ``open_sequence(root, options) -> Sequence``.
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

from ...errors import InputError
from ..sequence import Sequence
from . import own, replica, scannet, sevenscenes, stray, tum
from .common import ReadOptions

READERS: dict[str, ModuleType] = {m.NAME: m for m in (own, tum, sevenscenes, scannet, replica, stray)}
FORMATS = tuple(READERS)

__all__ = ["FORMATS", "READERS", "ReadOptions", "detect_format", "open_format"]


def detect_format(root: Path) -> str:
    """The one layout whose marker files ``root`` holds; an error if none or several match."""
    found = [name for name, reader in READERS.items() if reader.detect(root)]
    if not found:
        raise InputError(root, "no known RGB-D layout found (frames.txt, rgb.txt, frame-*.color.*, color/+depth/, "
                         "results/+traj.txt, depth/+confidence/)",
                         f"give a folder in one of the layouts {', '.join(FORMATS)} (see README 'Input formats')")
    if len(found) > 1:
        raise InputError(root, f"holds the marker files of several layouts at once ({', '.join(found)})",
                         "pass --format NAME to choose one, or move the other layout's files out")
    return found[0]


def open_format(root: Path, options: ReadOptions, name: str | None = None) -> Sequence:
    """Open ``root`` with the reader ``name`` (default: the detected one)."""
    if name is None:
        name = detect_format(root)
    elif name not in READERS:
        raise InputError(root, f"unknown --format {name!r}", f"use one of {', '.join(FORMATS)}")
    sequence = READERS[name].open_sequence(root, options)
    sequence.source = {**sequence.source, "format": name}
    return sequence
