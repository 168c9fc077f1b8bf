"""How much a motion-capture reference jitters, and the RPE rotation that jitter alone leaves (issue 11).

    python bench/mocap_jitter.py GROUNDTRUTH.txt

GROUNDTRUTH.txt is a TUM trajectory sampled faster than the camera (TUM RGB-D's motion capture: 100 Hz). The
orientation's k-th differences over regular samples cancel a smooth motion and keep white noise, whose variance
they multiply by C(2k, k) (6, 20, 70 for k = 2, 3, 4); a robust spread (MAD) of each body axis divided by that
gives the noise per sample. When the three orders agree, noise dominates them. A frame's reference pose is slerped
between two samples (on average 2/3 of a sample's noise variance), so a consecutive frame pair's relative rotation
carries sqrt(4/3 * sum of the axes' variances) of jitter (RMS angle): an estimate that is exact still reads that
much RPE rotation against this reference.
"""

from __future__ import annotations

import argparse
from math import comb
from pathlib import Path

import numpy as np

from taichi_gs.geometry import so3_log
from taichi_gs.io.trajectory import read_tum_rows, tum_rows_to_poses

REGULAR = (0.8, 1.2)  # a step counts as regular within this fraction of the median sample interval
ORDERS = (2, 3, 4)


def jitter_per_axis_deg(times: np.ndarray, rotations: np.ndarray, order: int) -> np.ndarray:
    """Orientation noise per sample (deg, body x / y / z) of the sampled ``rotations`` (N x 3 x 3) from
    ``order``-th differences over regular stretches."""
    steps = np.diff(times)
    regular = (steps > REGULAR[0] * np.median(steps)) & (steps < REGULAR[1] * np.median(steps))
    increments = np.degrees([so3_log(a.T @ b) for a, b in zip(rotations[:-1], rotations[1:])])
    differences, usable = increments, regular
    for _ in range(order - 1):
        differences, usable = np.diff(differences, axis=0), usable[:-1] & usable[1:]
    spread = 1.4826 * np.median(np.abs(differences[usable] - np.median(differences[usable], axis=0)), axis=0)
    return spread / np.sqrt(comb(2 * order, order))


def rpe_rotation_floor_deg(jitter_deg: np.ndarray) -> float:
    """RPE rotation (RMS angle, deg) that per-sample jitter leaves on frame pairs slerped from the samples."""
    return float(np.sqrt(4.0 / 3.0 * np.sum(np.square(jitter_deg))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("groundtruth", type=Path)
    args = parser.parse_args()
    rows = read_tum_rows(args.groundtruth)
    rows = rows[np.argsort(rows[:, 0])]
    times, rotations = rows[:, 0], tum_rows_to_poses(rows)[:, :3, :3]
    print(f"{len(rows)} samples, median interval {1000 * np.median(np.diff(times)):.2f} ms")
    print("| difference order | jitter per sample, body x / y / z (deg) | RPE rotation floor (deg) |")
    print("|---|---|---|")
    for order in ORDERS:
        jitter = jitter_per_axis_deg(times, rotations, order)
        print(f"| {order} | {' / '.join(f'{j:.3f}' for j in jitter)} | {rpe_rotation_floor_deg(jitter):.3f} |")


if __name__ == "__main__":
    main()
