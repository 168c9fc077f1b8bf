"""Benchmark stage 3 (deblurring) on synthetic extreme-blur sequences: held-out views against the
sharp ground truth.

    .venv/bin/python bench/deblur.py [--trajectories handheld translation turn] [--frames 12]
        [--width 160] [--height 120] [--iterations 600] [--k 7] [--out /tmp/bench_deblur]

Stage 3 is measured alone: OUT/refine/ is a stand-in built from the ground-truth mid-exposure poses
and the fused sensor depth (taichi_gs/standins.py), so pose errors of stages 1-2 do not enter.
Every third frame (1, 4, 7, ...) is a test view; its camera is the stand-in pose, refined at test
time against its own blurred frame (scene frozen). Methods:
- blurred input: the input frame itself (colour) and the input sensor depth (the floor)
- k = 1 fit: the same training with one view per exposure (no blur model)
- ours no-depth: l_D = 0
- ours: the stage as configured (fast preset, with the sizes given on the command line)
- ours + colour affine / fill uncovered / epochs / all: the real-data options (DeblurConfig
  colour_affine, fill_uncovered, epoch_sampling) switched on
- ours + init split / split px / footprint: DeblurConfig init_max_px / split_px = 1 px, and both
Prints a Markdown table: PSNR (dB), SSIM, inverse-depth RMSE (1/m; against the exact ray-cast
depth at the ground-truth mid pose) over the test views, and seconds per training iteration.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import platform
import sys
from pathlib import Path

import cv2
import numpy as np

from taichi_gs import synth
from taichi_gs.evaluate import inverse_depth_rmse, psnr, ssim
from taichi_gs.io.load import load_sequence
from taichi_gs.stages.deblur import PRESETS, run_deblur
from taichi_gs.stages.deblur.frames import split_frames
from taichi_gs.standins import write_refine_outputs

METHODS = {"k = 1 fit (no blur model)": {"k": 1}, "ours no-depth": {"lambda_depth": 0.0}, "ours": {},
           # the real-data options of stage 3, each alone and together (ablation on synthetic data)
           "ours + colour affine": {"colour_affine": True}, "ours + fill uncovered": {"fill_uncovered": True},
           "ours + epochs": {"epoch_sampling": True},
           "ours + all": {"colour_affine": True, "fill_uncovered": True, "epoch_sampling": True},
           # splat footprint (issue 16): split Gaussians wider than 1 px before training / in densification
           "ours + init split": {"init_max_px": 1.0}, "ours + split px": {"split_px": 1.0},
           "ours + footprint": {"init_max_px": 1.0, "split_px": 1.0}}


def truth(sequence, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Sharp colour (from the sequence) and exact depth (ray cast at the true mid pose) of frame i."""
    width, height = sequence.intrinsics.width, sequence.intrinsics.height
    seed = int(json.loads((sequence.root / "synth.json").read_text())["config"]["seed"])
    _, depth = synth.render_view(sequence.gt_poses[i], sequence.K(), width, height, seed)
    return sequence.sharp(i), depth


def scores(images, depths, truths) -> tuple[float, float, float]:
    return (float(np.mean([psnr(im, t[0]) for im, t in zip(images, truths)])),
            float(np.mean([ssim(im, t[0]) for im, t in zip(images, truths)])),
            float(np.mean([inverse_depth_rmse(d, t[1]) for d, t in zip(depths, truths)])))


def read_outputs(stage: Path, sequence, frames: list[int]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    images, depths = [], []
    for i in frames:
        name = sequence.names[i]
        images.append(cv2.cvtColor(cv2.imread(str(stage / "renders" / "sharp" / f"{name}.png")), cv2.COLOR_BGR2RGB) / 255.0)
        raw = cv2.imread(str(stage / "renders" / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED)
        depths.append(raw.astype(np.float64) / sequence.intrinsics.depth_scale)
    return images, depths


def bench_sequence(folder: Path, work: Path, config) -> list[tuple[str, float, float, float, float | None]]:
    sequence = load_sequence(folder)
    test = split_frames(len(sequence), config.deblur.holdout_every)[1]
    truths = [truth(sequence, i) for i in test]
    floor = scores([sequence.color(i) for i in test], [sequence.depth(i) for i in test], truths)
    rows = [("blurred input (floor)", *floor, None)]
    for name, overrides in METHODS.items():
        if name not in config.methods:
            continue
        out = work / "".join(c if c.isalnum() else "_" for c in name) / folder.name
        write_refine_outputs(sequence, out, voxel=config.voxel)
        result = run_deblur(sequence, out, dataclasses.replace(config.deblur, **overrides))
        for warning in result.warnings:
            print(f"  {name}: warning: {warning}", file=sys.stderr)
        rows.append((name, *scores(*read_outputs(out / "deblur", sequence, test), truths), result.seconds_per_iteration))
        print(f"  {folder.name} {name}: {rows[-1][1]:.2f} dB, {result.seconds_per_iteration:.3f} s/it", file=sys.stderr)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trajectories", nargs="+", default=["handheld"], choices=synth.TRAJECTORIES)
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--iterations", type=int, default=600)
    parser.add_argument("--k", type=int, default=7)
    parser.add_argument("--voxel", type=float, default=0.04, help="voxel size (m) of the stand-in stage-2 splats")
    parser.add_argument("--out", type=Path, default=Path("/tmp/bench_deblur"))
    parser.add_argument("--methods", nargs="+", default=list(METHODS)[:3], help="run only these methods (exact names)")
    args = parser.parse_args()
    deblur = dataclasses.replace(PRESETS["fast"], k=args.k, iterations=args.iterations, resolution_scale=1,
                                 densify_from=args.iterations // 5, densify_until=args.iterations * 3 // 4,
                                 exposure_from=args.iterations // 5, checkpoint_every=10**9)
    config = argparse.Namespace(deblur=deblur, voxel=args.voxel, methods=args.methods)
    print(f"# stage 3 deblurring, {datetime.date.today()}, {platform.processor() or platform.machine()}, "
          f"{args.width}x{args.height}, {args.frames} frames, extreme blur, k={args.k}, {args.iterations} iterations")
    print("\n| sequence | method | PSNR (dB) | SSIM | inv-depth RMSE (1/m) | s/iteration |")
    print("|---|---|---|---|---|---|")
    for trajectory in args.trajectories:
        folder = args.out / "seq" / trajectory
        if not folder.is_dir():
            synth.generate(synth.SynthConfig(width=args.width, height=args.height, frames=args.frames,
                                             trajectory=trajectory, blur="extreme"), folder)
        for name, p, s, d, sec in bench_sequence(folder, args.out / "runs", config):
            print(f"| {trajectory} | {name} | {p:.2f} | {s:.3f} | {d:.4f} | {'-' if sec is None else f'{sec:.3f}'} |",
                  flush=True)


if __name__ == "__main__":
    main()
