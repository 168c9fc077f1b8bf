"""Benchmark stage 2 (global refinement) on synthetic sequences with extreme blur.

    python bench/refine.py [--size 320x240] [--frames 10] [--turn-frames 40] [--out /tmp/bench_refine]
    python bench/refine.py --timing-only

For each trajectory kind (translation, turn, handheld) it refines, with the `fast` preset's schedule as it
trains (60 N iterations; the preset itself hands stage 1's output over untrained):
- from perturbed ground truth: a drift growing to 3 cm / 2 deg at the last frame plus per-frame
  jitter of 1 cm / 0.5 deg rms per axis (first pose exact), the fused cloud built from those poses;
  with the scale fixed (the method) and free (the paper's ablation: anisotropic scales and
  rotations trained);
- from exact ground truth (does refinement keep good poses?);
- from stage 1's own output (`--stage1`, slower: runs stage 1 first).
The synthetic ``turn`` is one 360-degree turn over however many frames it is generated with; it is
generated with ``--turn-frames`` frames and its first ``--frames`` are used.
Then seconds per iteration at 320x240 and 640x480 (a few iterations), and the peak resident memory
of a 640x480 iteration with one million Gaussians in view. Prints Markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import time
from pathlib import Path

import numpy as np

from taichi_gs.evaluate import ate, rpe
from taichi_gs.geometry import invert
from taichi_gs.io.load import load_sequence
from taichi_gs.kernels import runtime
from taichi_gs.stages.pose import PoseConfig, fuse_points, run_pose
from taichi_gs.stages.refine import FAST_TRAINING_PER_FRAME, PRESETS, RefineConfig, run_refine
from taichi_gs.standins import perturbed
from taichi_gs.synth import SynthConfig, generate

VOXEL = 0.02


def synthetic(kind: str, size: tuple[int, int], frames: int, turn_frames: int, root: Path):
    """A generated sequence cut to ``frames``, and its ground truth relative to the first frame."""
    generated = max(frames, turn_frames) if kind == "turn" else frames
    folder = root / f"{kind}_{size[0]}x{size[1]}_{generated}"
    if not (folder / "frames.txt").is_file():
        generate(SynthConfig(width=size[0], height=size[1], frames=generated, trajectory=kind, blur="extreme", seed=0), folder)
    sequence = load_sequence(folder, count=frames)
    return sequence, invert(sequence.gt_poses[0]) @ sequence.gt_poses


def refine_row(label: str, sequence, gt: np.ndarray, start: np.ndarray, config: RefineConfig, out: Path) -> str:
    """Refine from ``start`` (cloud fused from it) and format one table row."""
    points, colors = fuse_points(sequence, start, PoseConfig(voxel_size_m=config.voxel_size))
    t0 = time.perf_counter()
    result = run_refine(sequence, start, points, colors, out, config)
    wall = time.perf_counter() - t0
    (tb, rb), (ta, ra) = rpe(start, gt), rpe(result.poses, gt)
    depth = [h["depth"] for h in result.loss_history]
    row = (f"| {label} | {ate(start, gt) * 1000:.2f} → {ate(result.poses, gt) * 1000:.2f} | {tb * 1000:.2f} → {ta * 1000:.2f} "
           f"| {rb:.3f} → {ra:.3f} | {np.mean(depth[:3]) * 1000:.1f} → {np.mean(depth[-5:]) * 1000:.1f} "
           f"| {len(points)} → {result.gaussians} | {result.seconds_per_iteration:.3f} | {wall:.0f} |")
    print(row, flush=True)
    return row


def suite(args, root: Path) -> None:
    size = tuple(int(x) for x in args.size.split("x"))
    # the fast preset's schedule as it trains (the preset itself hands stage 1's output to stage 3 untrained)
    fixed = dataclasses.replace(PRESETS["fast"], voxel_size=VOXEL, iterations_per_frame=FAST_TRAINING_PER_FRAME)
    free = dataclasses.replace(fixed, free_scale=True)
    print(f"\n{size[0]}x{size[1]}, {args.frames} frames, extreme blur, `fast` preset trained for {fixed.iterations_per_frame} N iterations\n")
    print("| sequence / start / scale | ATE (mm) | RPE trans (mm) | RPE rot (deg) | depth L1 (mm) | Gaussians | s/iter | wall (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for kind in args.kinds.split(","):
        sequence, gt = synthetic(kind, size, args.frames, args.turn_frames, root)
        label = f"{kind} ({360 / max(args.frames, args.turn_frames):g} deg/frame)" if kind == "turn" else kind
        start = perturbed(gt)
        refine_row(f"{label} / perturbed / fixed", sequence, gt, start, fixed, root / f"{kind}_fixed")
        if kind in args.free_kinds.split(","):
            refine_row(f"{label} / perturbed / free", sequence, gt, start, free, root / f"{kind}_free")
        if kind in args.gt_kinds.split(","):
            refine_row(f"{label} / exact GT / fixed", sequence, gt, gt.copy(), fixed, root / f"{kind}_gt")
        if args.stage1:
            stage1 = run_pose(sequence, root / f"{kind}_stage1", PoseConfig(voxel_size_m=VOXEL)).poses
            refine_row(f"{label} / stage 1 / fixed", sequence, gt, stage1, fixed, root / f"{kind}_stage1")


def timing(root: Path) -> None:
    """Seconds per iteration at two sizes (few iterations) and peak memory with 1M Gaussians."""
    from taichi_gs.splats import logit
    from taichi_gs.stages.refine.model import DepthRefiner

    print("\n| size | frames | Gaussians | s/iter (fast preset, 8 N iterations) |\n|---|---|---|---|")
    for size in ((320, 240), (640, 480)):
        sequence, gt = synthetic("handheld", size, 4, 0, root)
        config = dataclasses.replace(PRESETS["fast"], voxel_size=VOXEL, iterations_per_frame=8, prune_every_per_frame=4,
                                     reset_every_per_frame=6)
        points, colors = fuse_points(sequence, gt, PoseConfig(voxel_size_m=VOXEL))
        result = run_refine(sequence, gt, points, colors, root / f"timing_{size[0]}", config)
        print(f"| {size[0]}x{size[1]} | 4 | {len(points)} → {result.gaussians} | {result.seconds_per_iteration:.3f} |", flush=True)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    n = 1_000_000
    rng = np.random.default_rng(0)
    means = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-1.5, 1.5, n), rng.uniform(1, 5, n)]).astype(np.float32)
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    model = DepthRefiner(means, np.full(n, logit(0.5), np.float32), VOXEL / 2, K, 640, 480)
    depth = np.full((480, 640), 3.0, np.float32)
    t0 = time.perf_counter()
    for _ in range(3):
        model.step([depth], [np.eye(4)], 1.0, 0.3, 0.1, {"means": 1e-4, "opacity_logits": 0.05})
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"\n1M Gaussians in view at 640x480: {(time.perf_counter() - t0) / 3:.2f} s/iter; "
          f"peak RSS {peak:.0f} MiB (before building them: {before:.0f} MiB)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--turn-frames", type=int, default=40)
    parser.add_argument("--kinds", default="translation,turn,handheld")
    parser.add_argument("--free-kinds", default="translation,turn,handheld", help="kinds also run with free scale")
    parser.add_argument("--gt-kinds", default="handheld", help="kinds also refined from exact ground truth")
    parser.add_argument("--stage1", action="store_true", help="also refine stage 1's output (runs stage 1)")
    parser.add_argument("--timing-only", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_refine"))
    args = parser.parse_args()
    runtime.init("cpu")
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.timing_only:
        suite(args, args.out)
    timing(args.out)


if __name__ == "__main__":
    main()
