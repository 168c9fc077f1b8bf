"""``taichi-gs import``: any readable sequence written out in taichi-gs's own layout.

Writes ``frames.txt`` (with each depth frame's own timestamp where the reading knows it), ``rgb/NAME.png``
(8-bit), ``depth/NAME.png`` (uint16 at the sequence's depth scale), ``intrinsics.json`` (with the camera's
rolling-shutter ``readout_ms`` where the reading gives or names one, e.g. ``--camera fr1``), and when the
input has them ``groundtruth.txt``, ``exposure.txt``, ``sharp/`` and ``sourced.png`` (the pixels that came
from the camera, when some did not: an undistorted frame's border), each frame as the reader gives it
(resampled, undistorted, masked, subsampled, scaled);
a sequence averaged into long exposures (``io.average``) also gets ``blur.json``.
Everything goes to a temporary folder beside OUT, renamed onto OUT at the end; the input is only read.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from ..errors import InputError
from .atomic import atomic_folder, write_text
from .average import AveragedSequence, blur_record
from .images import encode_depth, to_uint8, write_png
from .jsonout import write_json
from .readout import camera_readout_ms
from .sequence import Sequence
from .trajectory import format_tum


def import_sequence(sequence: Sequence, out: Path, progress: Callable[[int, int], None] | None = None) -> Path:
    """Write ``sequence`` to OUT in the taichi-gs layout; OUT must not exist (or be empty) and must
    lie outside the input folder."""
    out = Path(out)
    source, target = sequence.root.resolve(), out.resolve()
    if target == source or source in target.parents:
        raise InputError(out, "output folder lies inside the input folder", "choose an --out outside the input (inputs are never written to)")
    if target in source.parents:
        raise InputError(out, "output folder contains the input folder", "choose a new, empty --out folder")
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise InputError(out, "already exists and is not empty", "choose a new --out folder or delete this one")
    with atomic_folder(out) as staging:
        _write(sequence, staging, progress)
    return out


def _write(sequence: Sequence, dest: Path, progress: Callable[[int, int], None] | None) -> None:
    intr = sequence.intrinsics
    depth_times = sequence.depth_timestamps
    lines = ["# timestamp rgb depth" + (" depth_timestamp" if depth_times is not None else "")]
    for i, (name, t) in enumerate(zip(sequence.names, sequence.timestamps)):
        write_png(dest / "rgb" / f"{name}.png", to_uint8(sequence.color(i)))
        write_png(dest / "depth" / f"{name}.png", encode_depth(sequence.depth(i), intr.depth_scale))
        if sequence.sharp_paths is not None:
            write_png(dest / "sharp" / f"{name}.png", to_uint8(sequence.sharp(i)))
        lines.append(f"{t:.6f} rgb/{name}.png depth/{name}.png"
                     + (f" {depth_times[i]:.6f}" if depth_times is not None else ""))
        if progress is not None:
            progress(i + 1, len(sequence))
    write_text(dest / "frames.txt", "\n".join(lines) + "\n")
    write_text(dest / "intrinsics.json", intr.to_json(camera_readout_ms(sequence.source)))
    sourced = sequence.sourced_pixels()
    if not sourced.all():
        write_png(dest / "sourced.png", np.where(sourced, 255, 0).astype(np.uint8))
    if sequence.gt_poses is not None:
        known = np.all(np.isfinite(sequence.gt_poses.reshape(len(sequence), -1)), axis=1)
        if known.any():
            write_text(dest / "groundtruth.txt", format_tum(sequence.timestamps[known], sequence.gt_poses[known],
                                                            header="timestamp tx ty tz qx qy qz qw"))
    if sequence.exposure_poses is not None:
        start = format_tum(sequence.timestamps, sequence.exposure_poses[:, 0]).splitlines()
        end = format_tum(sequence.timestamps, sequence.exposure_poses[:, 1]).splitlines()
        rows = [f"{a} {b.split(maxsplit=1)[1]}" for a, b in zip(start, end)]
        write_text(dest / "exposure.txt", "\n".join(rows) + "\n")
    if isinstance(sequence, AveragedSequence):
        write_json(dest / "blur.json", blur_record(sequence))
