"""Does stage 2 keep stage 1's poses good? Stage 1 then stage 2 on given sequences, with the ablation
of issue 11's two stage-2 changes [ours].

    python bench/refine_keep.py SEQ [SEQ ...] [--frames 12] [--out /tmp/bench_refine_keep]

For each sequence (any folder `taichi-gs` reads; cut to its first ``--frames`` frames): stage 1 with
the defaults, then stage 2 (`fast` preset, trained for 60 N iterations) from its poses with the method's
1 cm pose steps and with the default 0.1 mm steps, each without and with the acceptance test (the test is the same function
`run_refine` calls at its end, applied to the same refined trajectory, so one refinement gives both
rows), and (unless ``--no-gt``) from exact ground truth with the default steps. Prints a Markdown table: ATE and RPE after
SE(3) alignment, whether the acceptance test kept the refined poses, and the verification scores.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from taichi_gs.evaluate import ate, rpe
from taichi_gs.geometry import invert
from taichi_gs.io.load import load_sequence
from taichi_gs.stages.pose import PoseConfig, fuse_points, run_pose
from taichi_gs.stages.refine import FAST_TRAINING_PER_FRAME, PRESETS, run_refine
from taichi_gs.stages.refine.accept import accept_refined_poses

STEPS = {"1 cm steps (method)": (1e-2, 1e-5), "0.1 mm steps (default)": (1e-4, 1e-6)}


def cells(poses: np.ndarray, gt: np.ndarray) -> str:
    trans, rot = rpe(poses, gt)
    return f"{ate(poses, gt) * 1000:.2f} | {trans * 1000:.2f} | {rot:.3f}"


def sequence_rows(folder: Path, frames: int, out: Path, from_gt: bool = True) -> None:
    """Stage 1, then stage 2 variants on one sequence; prints one table row each."""
    sequence = load_sequence(folder, count=frames)
    name = f"{folder.name} ({len(sequence)} fr, {sequence.depth(0).shape[1]}x{sequence.depth(0).shape[0]})"
    gt = invert(sequence.gt_poses[0]) @ sequence.gt_poses
    pose_config = PoseConfig()
    stage1 = run_pose(sequence, out / folder.name / "stage1", pose_config).poses
    stage1 = invert(stage1[0]) @ stage1
    print(f"| {name} | stage 1 | {cells(stage1, gt)} | - |", flush=True)
    # the fast preset's schedule as it trains (the preset itself hands stage 1's output over untrained)
    base = dataclasses.replace(PRESETS["fast"], voxel_size=pose_config.voxel_size_m, accept_neighbours=0,
                               iterations_per_frame=FAST_TRAINING_PER_FRAME)
    for start_name, start in (("stage 1", stage1), ("ground truth", gt))[:2 if from_gt else 1]:
        points, colors = fuse_points(sequence, start, pose_config)
        for label, (lr, lr_final) in STEPS.items():
            if start_name == "ground truth" and lr != 1e-4:
                continue
            config = dataclasses.replace(base, lr_pose=lr, lr_pose_final=lr_final)
            refined = run_refine(sequence, start, points, colors, out / folder.name / f"{start_name}_{lr:g}", config).poses
            print(f"| {name} | from {start_name}, {label} | {cells(refined, gt)} | - |")
            kept, acceptance = accept_refined_poses(sequence, start, refined, PRESETS["fast"].accept_neighbours)
            verdict = "kept" if acceptance.kept_refined else "rejected"
            print(f"| {name} | from {start_name}, {label} + acceptance | {cells(kept, gt)} | {verdict} "
                  f"({acceptance.refined_score:.5f} vs {acceptance.stage1_score:.5f}) |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("sequences", nargs="+", type=Path)
    parser.add_argument("--frames", type=int, default=12, help="first N frames of each sequence (0 = all)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_refine_keep"))
    parser.add_argument("--no-gt", action="store_true", help="skip the run from exact ground truth")
    args = parser.parse_args()
    print("| sequence | poses | ATE (mm) | RPE trans (mm) | RPE rot (deg) | acceptance (score refined vs initial) |")
    print("|---|---|---|---|---|---|", flush=True)
    for folder in args.sequences:
        sequence_rows(folder, args.frames, args.out, from_gt=not args.no_gt)


if __name__ == "__main__":
    main()
