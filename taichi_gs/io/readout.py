"""[ours] A colour camera's rolling-shutter readout as a sequence's reading gives it: the own layout's
intrinsics.json ``readout_ms`` (:data:`READOUT_KEY`, kept in ``Sequence.source``), else the measured readout of a
known camera the reading names (format and camera; ``rolling_shutter`` models it)."""

from __future__ import annotations

import math
from pathlib import Path

from ..errors import InputError
from .registration import intrinsics_entry

READOUT_KEY = "readout_ms"  # intrinsics.json: the colour camera's rolling-shutter readout (ms; 0: a global shutter)

# Readouts (ms) of the colour cameras of known (format, camera) readings: Kinect v1's, 25 ms, the best of 0, 15, 25
# and 35 ms on a TUM fr1 stretch and near bench/rolling_shutter_readout.py's estimates
# (docs/notebook/benchmarks-2026-11.md, "A rolling shutter in TUM's Kinect frames"). 7-Scenes was shot with a Kinect
# v1 as well.
KNOWN_READOUT_MS = {("tum", "fr1"): 25.0, ("7scenes", "registered"): 25.0, ("7scenes", "shipped"): 25.0}


def readout_in(json_path: Path) -> float | None:
    """The ``readout_ms`` entry of an own layout's intrinsics.json (None without the file or the entry)."""
    entry = intrinsics_entry(json_path, READOUT_KEY)
    if entry is None:
        return None
    try:
        readout_ms = float(entry)
    except (TypeError, ValueError):
        readout_ms = math.nan
    if not (math.isfinite(readout_ms) and 0.0 <= readout_ms < 1000.0):
        raise InputError(json_path, f"{READOUT_KEY} {entry!r} is not a readout in milliseconds",
                         f'write "{READOUT_KEY}": the ms the camera takes to read its rows top to bottom '
                         "(0: a global shutter), or leave it out")
    return readout_ms


def camera_readout_ms(source: dict) -> float:
    """The readout (ms) of a sequence's camera where its reading gives one (``Sequence.source``: the own
    layout's intrinsics.json ``readout_ms``) or names a known camera (format and camera;
    :data:`KNOWN_READOUT_MS`), else 0."""
    if READOUT_KEY in source:
        return float(source[READOUT_KEY])
    return KNOWN_READOUT_MS.get((source.get("format"), source.get("camera")), 0.0)
