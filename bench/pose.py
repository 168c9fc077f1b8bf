"""Benchmark stage 1 (local pose) on synthetic blurred sequences against Open3D baselines.

    python bench/pose.py [--quick] [--frames 16] [--turn-frames 40] [--out /tmp/bench_pose]
    python bench/pose.py --sequence FOLDER [--sequence FOLDER ...]   # any sequence with ground truth

The synthetic ``turn`` makes one full 360-degree turn over however many frames it is generated with,
so its rate is set apart from the benchmarked length: it is generated with ``--turn-frames`` frames
(40: 9 deg per frame, 270 deg/s at 30 fps, a fast hand-held pan) and its first ``--frames`` are used.

Methods, each chaining relative poses t -> t+1 from identity:
- ours: the stage as shipped (DIS medium flow, L_F then L_F + 75 L_I + 25 L_C, then ICP)
- ours no-L_C: depth-consistency weight 0
- ours flow-only: no ICP (the solver's estimate)
- ours no seeded retry: weak pairs are not redone with DIS seeded by the constant-velocity prior
- ours + RGB-D refine: Open3D's hybrid RGB-D odometry as a last step, started from the ICP estimate
- ours DIS-ultrafast / GT-flow: flow quality (GT flow from the exact sharp depth and GT motion)
- ICP only: the same multi-scale point-to-plane ICP, started from identity
- O3D hybrid: open3d compute_rgbd_odometry, RGBDOdometryJacobianFromHybridTerm, levels [20, 10, 5]
Prints a Markdown table: ATE (m), RPE translation (m), RPE rotation (deg), seconds per pair.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np

from taichi_gs.evaluate import ate, rpe
from taichi_gs.flow import rigid_flow, write_flow
from taichi_gs.geometry import invert
from taichi_gs.icp import depth_cloud, multiscale_point_to_plane, reliable_depth_mask, rgbd_odometry
from taichi_gs.io.sequence import load_sequence
from taichi_gs.stages.pose import PoseConfig, chain_poses, run_pose

OURS = {
    "ours": {},
    "ours no-L_C": {"depth_consistency_weight": 0.0},
    "ours flow-only (no ICP)": {"use_icp": False},
    "ours no seeded retry": {"seeded_retry": False},
    "ours + RGB-D refine": {"rgbd_refine": True},
    "ours DIS-ultrafast": {"flow_preset": "ultrafast"},
    "ours GT-flow": {"flow_dir": "GT"},
}


def gt_flows(sequence, depths: list[np.ndarray], folder: Path) -> None:
    """Flows implied by ground-truth motion and noise-free depth, forward and backward, as .npy per pair."""
    K, poses = sequence.intrinsics.K(), sequence.gt_poses
    for k in range(len(poses) - 1):
        for a, b, tag in ((k, k + 1, ""), (k + 1, k, "_backward")):
            write_flow(folder / f"{k:06d}{tag}.npy", rigid_flow(depths[a], K, invert(poses[b]) @ poses[a]))


def run_ours(sequence, overrides: dict, flow_dir: Path, work: Path) -> tuple[np.ndarray, float, str]:
    if overrides.get("flow_dir") == "GT":
        overrides = {**overrides, "flow_dir": str(flow_dir)}
    config = dataclasses.replace(PoseConfig(), **overrides)
    result = run_pose(sequence, work, config)
    weak = sum(p["weak"] for p in result.pairs)
    seeded = sum(p["flow_seed"] != "none" for p in result.pairs)
    return result.poses, float(np.mean([p["seconds"] for p in result.pairs])), f"{weak} ({seeded} seeded)"


def run_icp_only(sequence, config: PoseConfig) -> tuple[np.ndarray, float, str]:
    K = sequence.intrinsics.K()
    relatives, seconds = [], []
    for k in range(len(sequence) - 1):
        start = time.perf_counter()
        clouds = []
        for i in (k, k + 1):
            depth = sequence.depth(i)
            clouds.append(depth_cloud(depth, K, reliable_depth_mask(depth, config.min_depth_m, config.max_depth_m, config.depth_edge_ratio)))
        result = multiscale_point_to_plane(
            clouds[0], clouds[1], np.eye(4), tuple(s * config.icp_voxel_m for s in config.icp_scales), config.icp_iterations,
            config.icp_distance_factor, config.icp_normal_radius_factor, config.icp_normal_max_nn, config.icp_max_points)
        relatives.append(result.transform)
        seconds.append(time.perf_counter() - start)
    return chain_poses(relatives), float(np.mean(seconds)), "-"


def run_open3d_hybrid(sequence) -> tuple[np.ndarray, float, str]:
    """Open3D's RGB-D odometry (hybrid term, levels [20, 10, 5]) per pair from identity; failures count identity."""
    K = sequence.intrinsics.K()
    relatives, seconds, failed = [], [], 0
    for k in range(len(sequence) - 1):
        start = time.perf_counter()
        T = rgbd_odometry(sequence.color(k), sequence.depth(k), sequence.color(k + 1), sequence.depth(k + 1), K, np.eye(4))
        failed += T is None
        relatives.append(np.eye(4) if T is None else T)
        seconds.append(time.perf_counter() - start)
    return chain_poses(relatives), float(np.mean(seconds)), str(failed)


def evaluate(poses: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    trans, rot = rpe(poses, gt)
    return ate(poses, gt), trans, rot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="320x240 only, extreme blur, 12 frames")
    parser.add_argument("--frames", type=int, default=16, help="frames benchmarked per sequence")
    parser.add_argument("--turn-frames", type=int, default=40, help="frames per full turn (360 / this = deg per frame)")
    parser.add_argument("--out", type=Path, default=None, help="keep sequences and outputs here")
    parser.add_argument("--trajectories", default="translation,turn,handheld")
    parser.add_argument("--sizes", default="320x240,640x480")
    parser.add_argument("--blurs", default="none,moderate,extreme")
    parser.add_argument("--methods", default=",".join([*OURS, "ICP only", "O3D hybrid"]))
    parser.add_argument("--sequence", type=Path, action="append", help="benchmark this folder instead of synthetic ones")
    args = parser.parse_args()
    methods = args.methods.split(",")
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_pose_"))
    print("| sequence | method | ATE (m) | RPE trans (m) | RPE rot (deg) | s/pair | weak (seeded) / failed pairs |")
    print("|---|---|---|---|---|---|---|")
    for name, sequence, clean_depths in sequences(args, root):
        flow_dir = root / folder_name(name) / "gt_flow"
        if "ours GT-flow" in methods:
            gt_flows(sequence, clean_depths, flow_dir)
        for method in methods:
            if method in OURS:
                poses, seconds, weak = run_ours(sequence, OURS[method], flow_dir, root / folder_name(name) / folder_name(method))
            elif method == "ICP only":
                poses, seconds, weak = run_icp_only(sequence, PoseConfig())
            else:
                poses, seconds, weak = run_open3d_hybrid(sequence)
            a, t, r = evaluate(poses, sequence.gt_poses)
            print(f"| {name} | {method} | {a:.4f} | {t:.4f} | {r:.3f} | {seconds:.2f} | {weak} |", flush=True)


def folder_name(label: str) -> str:
    """A table label as one folder name."""
    return label.replace(" ", "_").replace("/", "_per_")


def sequences(args, root: Path):
    """(name, sequence, noise-free depths) of the given folders, or of generated synthetic ones."""
    if args.sequence:
        for folder in args.sequence:
            sequence = load_sequence(folder)
            yield folder.name, sequence, [sequence.depth(i) for i in range(len(sequence))]
        return
    from taichi_gs.synth import SynthConfig, generate, render_view

    sizes = [tuple(int(x) for x in s.split("x")) for s in args.sizes.split(",")]
    blurs, frames = args.blurs.split(","), args.frames
    if args.quick:
        sizes, blurs, frames = [(320, 240)], ["extreme"], 12
    for trajectory in args.trajectories.split(","):
        generated = max(frames, args.turn_frames) if trajectory == "turn" else frames
        label = f"turn {360 / generated:g}deg/frame" if trajectory == "turn" else trajectory
        for w, h in sizes:
            for blur in blurs:
                name = f"{label} {w}x{h} {blur}"
                folder = root / folder_name(name) / "seq"
                generate(SynthConfig(width=w, height=h, frames=generated, trajectory=trajectory, blur=blur, seed=0), folder)
                sequence = first_frames(load_sequence(folder), frames)
                K = sequence.intrinsics.K()
                yield name, sequence, [render_view(p, K, w, h, 0)[1] for p in sequence.gt_poses]


def first_frames(sequence, n: int):
    """A copy of a loaded sequence cut to its first n frames."""
    cut = copy.copy(sequence)
    for attr in ("timestamps", "rgb_paths", "depth_paths", "names", "gt_poses", "exposure_poses", "sharp_paths"):
        value = getattr(sequence, attr)
        setattr(cut, attr, None if value is None else value[:n])
    return cut


if __name__ == "__main__":
    main()
