"""A motion-capture reference re-read on the camera's own clock, for ``bench/pose.py --reference`` (issue 11).

    python bench/retime_reference.py GROUNDTRUTH.txt RGB.txt [--shift-ms -10] --out R.txt

TUM RGB-D's colour stamps scatter about a regular 30 Hz clock (fr1_rpy: by about a millisecond), and at
50-100 deg/s a millisecond is 0.05-0.1 deg of rotation. Here each frame's time is its
place on a straight line fitted through the stamps of the frames around it (``WINDOW`` either side, counted in
periods so that a dropped frame does not bend the line), plus ``--shift-ms``. The motion capture is slerped at
that time and written at the frame's own stamp, so ``bench/pose.py --sequence ... --reference R.txt`` scores a run
against it beside the reference as shipped. Frames whose time falls outside the capture are left out.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from taichi_gs.io.trajectory import interpolate_poses
from taichi_gs.io.trajectory import read_tum_rows, tum_rows_to_poses, write_tum

WINDOW = 15  # frames either side of a frame whose stamps the line is fitted through
TOLERANCE_S = 0.02  # a time this far outside the capture still takes its first or last sample


def regular_times(stamps: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """Each stamp's place on a line fitted through the stamps within ``window`` frames of it, the frames counted in
    whole periods from it (so a gap of a dropped frame counts as two periods). The period is the median over spans
    of ``window`` frames: consecutive stamps can follow a pattern (TUM fr1: 32, 32, 36 ms) whose median is not it."""
    period = float(np.median((stamps[window:] - stamps[:-window]) / window)) if len(stamps) > window \
        else float(np.median(np.diff(stamps)))
    times = np.empty(len(stamps))
    for i, stamp in enumerate(stamps):
        near = stamps[max(0, i - window): i + window + 1]
        periods = np.round((near - stamp) / period)
        offset = np.polyfit(periods, near - stamp, 1)[1]  # relative to the stamp: seconds since 1970 lose digits
        times[i] = stamp + offset  # the line at 0 periods from this frame
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("groundtruth", type=Path)
    parser.add_argument("frames", type=Path, help="the colour frames' list (TUM rgb.txt)")
    parser.add_argument("--shift-ms", type=float, default=0.0, help="added to every regular time")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    rows = read_tum_rows(args.groundtruth)
    rows = rows[np.argsort(rows[:, 0])]
    stamps = read_tum_rows(args.frames, columns=1)[:, 0]  # rgb.txt: the time stamp leads each line
    regular = regular_times(stamps)
    poses = interpolate_poses(rows[:, 0], tum_rows_to_poses(rows), regular + args.shift_ms / 1000.0, TOLERANCE_S)
    covered = np.all(np.isfinite(poses), axis=(1, 2))
    write_tum(args.out, stamps[covered], poses[covered],
              header=f"{args.groundtruth.name} at {args.frames.name}'s regular times {args.shift_ms:+g} ms, camera-to-world")
    print(f"{args.out}: {covered.sum()} of {len(stamps)} frames; stamps minus regular times: "
          f"{1000 * np.std(stamps - regular):.2f} ms standard deviation")


if __name__ == "__main__":
    main()
