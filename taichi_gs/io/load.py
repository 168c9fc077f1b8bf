"""A sequence folder opened in any known layout (``io.formats``) and read as asked: ``--first``/``--count``,
``--every``, ``--scale``; its lists, files, intrinsics and depth scale checked."""

from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np

from ..errors import InputError
from .formats import ReadOptions, open_format
from .formats.common import MAX_TIME_DIFFERENCE
from .sequence import Intrinsics, IntrinsicsOverride, Sequence
from .transforms import Resize, scaled_size, then

MEDIAN_DEPTH_RANGE = (0.1, 100.0)  # metres: outside it the depth scale is surely wrong
INDOOR_MEDIAN_DEPTH = (0.25, 6.0)  # metres: indoor RGB-D sensors; outside it the scale is likely wrong
COMMON_DEPTH_SCALES = (1000.0, 5000.0, 6553.5, 4000.0, 10000.0, 1.0)  # mm, TUM, Replica, RealSense, ...


def load_sequence(
    folder: str | Path,
    override: IntrinsicsOverride | None = None,
    max_time_difference: float | None = None,
    trust_depth_scale: bool = False,
    *,
    format: str | None = None,
    camera: str | None = None,
    every: int = 1,
    scale: float = 1.0,
    first: int = 0,
    count: int = 0,
    depth_latency: float | None = None,
) -> Sequence:
    """Open a sequence folder in any known layout (detected, or ``format``; see ``io.formats``),
    keep every ``every``-th frame from frame ``first`` on (``count`` of them; 0: all), read at
    ``scale`` times the size; checks lists, files, intrinsics and depth scale. ``depth_latency``: TUM layout,
    seconds by which depth stamps trail what they show (None: the named camera's; see ``io.formats.tum``).

    The median valid depth must look like an indoor RGB-D capture (0.25-6 m), which catches the usual
    depth-scale mix-ups (1000 for 5000); ``trust_depth_scale`` relaxes that to 0.1-100 m for scenes
    that really are that close or far. The call's arguments are kept in ``sequence.load_options``.
    """
    root = Path(folder)
    max_time_difference = MAX_TIME_DIFFERENCE if max_time_difference is None else max_time_difference
    if not root.is_dir():
        raise InputError(root, "sequence folder not found", "give the folder holding the sequence (see README 'Input formats')")
    if every < 1:
        raise InputError(None, f"--every {every} is not a positive integer", "e.g. --every 2 keeps every second frame")
    if not (math.isfinite(scale) and 0.0 < scale <= 4.0):
        raise InputError(None, f"--scale {scale} is not in (0, 4]", "e.g. --scale 0.5 for half width and height")
    if first < 0 or count < 0:
        raise InputError(None, f"--first {first} / --count {count} is negative", "e.g. --first 100 --count 40")
    options = ReadOptions(override or IntrinsicsOverride(), camera, max_time_difference, depth_latency)
    listed = open_format(root, options, format)
    if first >= len(listed):
        raise InputError(listed.root, f"--first {first} is past the last of the sequence's {len(listed)} frames",
                         f"give --first below {len(listed)} (frames count from 0)")
    sequence = rescale(subsample(listed, every, first, count), scale)
    if options.override.values():
        sequence.source = {**sequence.source, "intrinsics": options.override.values()}
    if len(sequence) < 2:
        raise InputError(sequence.root, f"sequence has {len(sequence)} frame(s)", "give at least 2 frames")
    _check_depth_scale(sequence, trust_depth_scale)
    sequence.load_options = {"override": options.override.values(), "max_time_difference": max_time_difference,
                             "trust_depth_scale": trust_depth_scale, "format": sequence.source["format"],
                             "camera": sequence.source.get("camera"), "every": every, "scale": scale,
                             "first": first, "count": count}
    if sequence.source.get("depth_latency_s"):  # only then: older records, without it, keep their fingerprints
        sequence.load_options["depth_latency"] = sequence.source["depth_latency_s"]
    return sequence


def subsample(sequence: Sequence, every: int, first: int = 0, count: int = 0) -> Sequence:
    """Frames ``first``, ``first + every``, ... of a sequence, at most ``count`` of them (0: to the end);
    timestamps and ground truth kept."""
    if every == 1 and first == 0 and count == 0:
        return sequence
    picked = slice(first, None if count == 0 else first + count * every, every)
    cut = copy.copy(sequence)
    for attr in ("timestamps", "rgb_paths", "depth_paths", "names", "gt_poses", "exposure_poses", "sharp_paths",
                 "depth_timestamps"):
        value = getattr(sequence, attr)
        setattr(cut, attr, None if value is None else value[picked])
    cut.source = {**sequence.source, "every": every, "first": first, "count": count}
    return cut


def rescale(sequence: Sequence, scale: float) -> Sequence:
    """A sequence read at ``scale`` times its width and height (colour by area, depth by
    ``resize_depth``, intrinsics with the pixel-centre convention)."""
    if scale == 1.0:
        return sequence
    intr = sequence.intrinsics
    width, height = scaled_size(intr.width, intr.height, scale)
    scaled = copy.copy(sequence)
    scaled.intrinsics = scale_intrinsics(intr, width, height)
    scaled.transform = then(sequence.transform, Resize(width, height))
    scaled.source = {**sequence.source, "scale": scale}
    return scaled


def scale_intrinsics(intrinsics: Intrinsics, width: int, height: int) -> Intrinsics:
    """Intrinsics of the same camera on a resized width x height grid (pixel-centre convention)."""
    sx, sy = width / intrinsics.width, height / intrinsics.height
    return dataclasses.replace(intrinsics, width=width, height=height, fx=intrinsics.fx * sx, fy=intrinsics.fy * sy,
                               cx=(intrinsics.cx + 0.5) * sx - 0.5, cy=(intrinsics.cy + 0.5) * sy - 0.5)


def _check_depth_scale(sequence: Sequence, trusted: bool) -> None:
    """Median valid depth over a few frames must be plausible, or the scale is wrong."""
    picks = np.unique(np.linspace(0, len(sequence) - 1, num=min(5, len(sequence))).astype(int))
    depths = [sequence.depth(int(i)) for i in picks]
    valid = np.concatenate([d[d > 0] for d in depths])
    where = sequence.depth_paths[int(picks[0])]
    if valid.size == 0:
        raise InputError(where, "no valid depth in the sampled frames", "check the depth files (0 means invalid)")
    median = float(np.median(valid))
    lo, hi = MEDIAN_DEPTH_RANGE if trusted else INDOOR_MEDIAN_DEPTH
    if lo <= median <= hi:
        return
    scale = sequence.intrinsics.depth_scale
    raw = median * scale
    likely = min(COMMON_DEPTH_SCALES, key=lambda s: abs(np.log(raw / s / 2.0)))
    fix = f"the data look like --depth-scale {likely:g} (median {raw / likely:.2f} m)"
    if not trusted:
        fix += f"; if {median:.3g} m is right, add --trust-depth-scale"
    raise InputError(where, f"median depth is {median:.4g} m with depth_scale {scale:g}, implausible for an RGB-D sensor"
                     f" ({lo}-{hi} m)", fix)
