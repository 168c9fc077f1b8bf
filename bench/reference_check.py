"""How well do a sequence's reference poses, and a run's poses, explain the frames themselves? (issue 11)

    python bench/reference_check.py RUN [RUN ...] [--spans 1,2,4,8,16] [--points 4000]

RUN is a ``taichi-gs`` output folder (its ``run.json`` reopens the input as it was read). For every frame pair
(i, i + s) and every trajectory (the sequence's ground truth, the run's stage 1 and, where present, stage 2),
frame i's depth is moved into camera i + s and compared there with frame i + s: the median |depth difference|
(mm) and the median |grey difference| (0-255) over sampled pixels that land inside the image on depth within 5%
of their own. Pixels and pairs are the same for every trajectory.

Where the reference is exact (``taichi-gs synth``) both trajectories' residuals agree and stay flat with the
span. On real data a trajectory that explains both streams better than the reference at every span says the
reference has errors at the level at which it scores that trajectory; one that is better in one stream and worse
in the other says that the frames do not settle the difference. (An estimate fitted to the frames also fits their
noise, most at the spans it was fitted on; a reference taken at other times than a stream's frames, as TUM's at
the colour timestamps, cannot align that stream as well.) Beside the residuals: ATE against the reference after a
rigid and after a similarity alignment, with its scale (below 1: the estimate's translations spread wider than
the reference's; noise in the estimate alone pulls it below 1 when the true translation is small).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from taichi_gs.evaluate import ate
from taichi_gs.geometry import backproject, invert, project, transform
from taichi_gs.io.trajectory import read_tum
from taichi_gs.pipeline import open_run_sequence

MAX_DEPTH_GAP = 0.05  # a warped pixel counts where the two depths differ by less than this fraction


def trajectories(run: Path, sequence) -> dict[str, np.ndarray]:
    """The reference poses and each stage's trajectory found in ``run``, camera-to-world (N x 4 x 4)."""
    found = {"reference": sequence.gt_poses}
    for label, stage in (("stage 1", "pose"), ("stage 2", "refine")):
        path = run / stage / "trajectory.txt"
        if path.is_file():
            found[label] = read_tum(path)[1]
    return found


def sampled_pixels(depth: np.ndarray, count: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Rows and columns of up to ``count`` random pixels with valid depth."""
    rows, cols = np.nonzero(np.isfinite(depth) & (depth > 0))
    pick = rng.choice(len(rows), min(count, len(rows)), replace=False)
    return rows[pick], cols[pick]


def warp_residuals(pose_i: np.ndarray, pose_j: np.ndarray, frame_i: tuple, frame_j: tuple, K: np.ndarray,
                   pixels: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """|depth| (m) and |grey| (0-1) differences of frame i's sampled pixels moved into camera j."""
    (color_i, depth_i), (color_j, depth_j) = frame_i, frame_j
    rows, cols = pixels
    points = transform(invert(pose_j) @ pose_i, backproject(depth_i, K)[rows, cols])
    uv = np.round(project(points, K)).astype(int)
    h, w = depth_j.shape
    inside = (points[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    u, v, z = uv[inside, 0], uv[inside, 1], points[inside, 2]
    seen = depth_j[v, u]
    agree = (seen > 0) & (np.abs(z - seen) < MAX_DEPTH_GAP * seen)
    grey_i = color_i[rows[inside], cols[inside]].mean(axis=1)
    grey_j = color_j[v, u].mean(axis=1)
    return np.abs(z - seen)[agree], np.abs(grey_i - grey_j)[agree]


def similarity_ate(est: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    """(RMSE of positions after the best similarity transform, its scale), Umeyama with scale."""
    ok = np.all(np.isfinite(est[:, :3, 3]), axis=1) & np.all(np.isfinite(ref[:, :3, 3]), axis=1)
    x, y = est[ok, :3, 3], ref[ok, :3, 3]
    xc, yc = x - x.mean(0), y - y.mean(0)
    U, S, Vt = np.linalg.svd(yc.T @ xc / len(x))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    scale = float(np.trace(np.diag(S) @ D) / xc.var(0).sum())
    moved = scale * xc @ (U @ D @ Vt).T
    return float(np.sqrt(np.mean(np.sum((moved - yc) ** 2, axis=1)))), scale


def check(run: Path, spans: list[int], points: int) -> list[str]:
    """Markdown rows for one run: per trajectory, residuals per span, ATE and similarity ATE."""
    sequence = open_run_sequence(run)
    if sequence.gt_poses is None:
        raise SystemExit(f"{run}: the sequence has no reference poses")
    found = trajectories(run, sequence)
    K = sequence.intrinsics.K()
    n = len(sequence)
    frames = [(sequence.color(i), sequence.depth(i)) for i in range(n)]
    rng = np.random.default_rng(0)
    pixels = [sampled_pixels(depth, points, rng) for _, depth in frames]
    rows = []
    for label, poses in found.items():
        depth_cells, grey_cells = [], []
        for span in spans:
            depth_all, grey_all = [], []
            for i in range(n - span):
                j = i + span
                if not (np.all(np.isfinite(poses[i])) and np.all(np.isfinite(poses[j]))):
                    continue
                d, g = warp_residuals(poses[i], poses[j], frames[i], frames[j], K, pixels[i])
                depth_all.append(d)
                grey_all.append(g)
            depth_cells.append(f"{1000 * np.median(np.concatenate(depth_all)):.2f}" if depth_all else "-")
            grey_cells.append(f"{255 * np.median(np.concatenate(grey_all)):.2f}" if grey_all else "-")
        if label == "reference":
            errors = "- | -"
        else:
            sim, scale = similarity_ate(poses, sequence.gt_poses)
            errors = f"{1000 * ate(poses, sequence.gt_poses):.2f} | {1000 * sim:.2f} ({scale:.3f})"
        rows.append(f"| {run.name} | {label} | {' / '.join(depth_cells)} | {' / '.join(grey_cells)} | {errors} |")
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--spans", default="1,2,4,8,16", help="frame distances i -> i + s")
    parser.add_argument("--points", type=int, default=4000, help="sampled pixels per frame")
    args = parser.parse_args()
    spans = [int(s) for s in args.spans.split(",")]
    label = " / ".join(str(s) for s in spans)
    print(f"| run | trajectory | median depth residual mm, span {label} | median grey residual, span {label} | ATE mm | "
          "similarity ATE mm (scale) |")
    print("|---|---|---|---|---|---|")
    for run in args.runs:
        for row in check(run, spans, args.points):
            print(row, flush=True)


if __name__ == "__main__":
    main()
