"""A colour camera's rolling-shutter readout time, measured on a recording with reference poses.

Between frames i and j = i + gap of a moving camera, each band of image rows is seen at its own pose when the
rows are read one after another. The relative pose fitted on the top third of the rows (PnP on DIS optical flow
from i to j, with frame i's depth) and the one fitted on the bottom third then differ by about

    exp(-(w_j - w_i) r d),

w the camera's angular velocity (its own frame, from the reference poses), r the readout time in frames and d =
2/3 the distance between the two bands' centres as a share of the image height (both frames read alike, depth
rows at the colour rows' times, as Kinect v1's are). The least-squares fit of the bands' rotation difference on
w_j - w_i over every pair gives r:

    python bench/rolling_shutter_readout.py --recording /tmp/fr1_rpy/data --camera fr1 --first 100 --count 100

Prints the readout in frames and in milliseconds (the recording's median frame interval) and the fit's correlation
(near 0: no rolling shutter, or too little change of speed). The velocities are central differences of the
reference poses over two frames, which smooth a shaky path's changes of speed and so lengthen the estimate: on a
synthetic hand-held clip read out in 25 ms (0.75 frames) it gives 0.97 frames, and 0.735 from the path's
instantaneous velocities. Noise in the reference poses shortens it instead. Several stretches (``--first``) and gaps
give a range, not a calibration. The recording is read, never written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from taichi_gs.flow import dis_flow  # noqa: E402
from taichi_gs.geometry import so3_exp, so3_log  # noqa: E402
from taichi_gs.io.load import load_sequence  # noqa: E402

BAND_DISTANCE = 2.0 / 3.0  # between the centres of the top and bottom thirds, as a share of the image height
MIN_POINTS = 200
STRIDE_PX = 4


def angular_velocity(poses: np.ndarray, i: int) -> np.ndarray:
    """Rotation per frame of camera i (its own frame), from its neighbours' camera-to-world poses."""
    a, b = max(i - 1, 0), min(i + 1, len(poses) - 1)
    return so3_log(poses[a][:3, :3].T @ poses[b][:3, :3]) / (b - a)


def band_rotations(gray_i: np.ndarray, gray_j: np.ndarray, depth_i: np.ndarray, K: np.ndarray,
                   start: np.ndarray) -> list[np.ndarray] | None:
    """The rotation of frame i's camera into frame j's fitted on the top and on the bottom third of j's rows, or
    None where a band has too few points; ``start`` (4 x 4, i to j) seeds the fits."""
    h, w = depth_i.shape
    flow = dis_flow(gray_i, gray_j, "medium")
    v, u = np.mgrid[0:h:STRIDE_PX, 0:w:STRIDE_PX]
    z = depth_i[v, u]
    fu, fv = u + flow[v, u, 0], v + flow[v, u, 1]
    ok = np.isfinite(z) & (z > 0.3) & (z < 4.0) & (fu > 2) & (fu < w - 3) & (fv > 2) & (fv < h - 3)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)
    rvec0, _ = cv2.Rodrigues(start[:3, :3])
    rotations = []
    for lo, hi in ((0, h // 3), (2 * h // 3, h)):
        band = ok & (fv >= lo) & (fv < hi)
        if band.sum() < MIN_POINTS:
            return None
        seen = np.stack([fu[band], fv[band]], axis=-1).astype(np.float64)
        found, rvec, tvec, inliers = cv2.solvePnPRansac(points[band].astype(np.float64), seen, K, None, rvec0.copy(),
                                                        start[:3, 3].reshape(3, 1).copy(), True, 200, 1.5, 0.99)
        if not found or inliers is None or len(inliers) < MIN_POINTS // 2:
            return None
        rvec, _ = cv2.solvePnPRefineLM(points[band][inliers[:, 0]].astype(np.float64), seen[inliers[:, 0]], K, None,
                                       rvec, tvec)
        rotations.append(so3_exp(rvec.ravel()))
    return rotations


def readout_frames(sequence, gap: int) -> tuple[float, float, int]:
    """(readout in frames, the fit's correlation, pairs used) over the pairs (i, i + gap) of ``sequence``."""
    poses, K = sequence.gt_poses, sequence.K()
    gray = [cv2.cvtColor((np.clip(sequence.color(i), 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
            for i in range(len(sequence))]
    differences, accelerations = [], []
    for i in range(1, len(sequence) - gap - 1):
        j = i + gap
        if not (np.isfinite(poses[i]).all() and np.isfinite(poses[j]).all()):
            continue
        bands = band_rotations(gray[i], gray[j], sequence.depth(i), K, np.linalg.inv(poses[j]) @ poses[i])
        if bands is None:
            continue
        differences.append(so3_log(bands[1] @ bands[0].T))
        accelerations.append(angular_velocity(poses, j) - angular_velocity(poses, i))
    d, a = np.ravel(differences), np.ravel(accelerations)
    if d.size == 0:
        raise SystemExit("no frame pair had enough depth and flow in both bands")
    slope = float(a @ d / (a @ a))
    return -slope / BAND_DISTANCE, float(np.corrcoef(a, d)[0, 1]), len(differences)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recording", type=Path, required=True, help="a sequence folder with reference poses")
    parser.add_argument("--camera", default=None, help="as taichi-gs --camera (e.g. fr1)")
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--count", type=int, default=100)
    parser.add_argument("--gap", type=int, nargs="+", default=[1, 2], help="frame gaps of the pairs")
    args = parser.parse_args()
    sequence = load_sequence(args.recording, camera=args.camera, first=args.first, count=args.count)
    if sequence.gt_poses is None:
        raise SystemExit(f"{args.recording} has no reference poses")
    interval_ms = 1000.0 * float(np.median(np.diff(sequence.timestamps)))
    for gap in args.gap:
        frames, correlation, pairs = readout_frames(sequence, gap)
        print(f"gap {gap}: readout {frames:.3f} frames = {frames * interval_ms:.1f} ms "
              f"(frame interval {interval_ms:.1f} ms; correlation {correlation:.2f}; {pairs} pairs)")


if __name__ == "__main__":
    main()
