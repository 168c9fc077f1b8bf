"""Benchmark stage 1 (local pose) on synthetic blurred sequences against Open3D baselines.

    python bench/pose.py [--quick] [--frames 20] [--out /tmp/bench_pose]
    python bench/pose.py --sequence FOLDER [--sequence FOLDER ...]   # any sequence with ground truth

Methods, each chaining relative poses t -> t+1 from identity:
- ours: the stage as shipped (DIS medium flow, L_F then L_F + 75 L_I + 25 L_C, then ICP)
- ours no-L_C: depth-consistency weight 0
- ours flow-only: no ICP (the solver's estimate)
- ours DIS-ultrafast / GT-flow: flow quality (GT flow from the exact sharp depth and GT motion)
- ICP only: the same multi-scale point-to-plane ICP, started from identity
- O3D hybrid: open3d compute_rgbd_odometry, RGBDOdometryJacobianFromHybridTerm, levels [20, 10, 5]
Prints a Markdown table: ATE (m), RPE translation (m), RPE rotation (deg), seconds per pair.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
from pathlib import Path

import numpy as np
import open3d as o3d

from taichi_gs.evaluate import ate, rpe
from taichi_gs.flow import write_flow
from taichi_gs.geometry import backproject, invert, project, transform
from taichi_gs.icp import depth_cloud, multiscale_point_to_plane, reliable_depth_mask
from taichi_gs.io.sequence import load_sequence
from taichi_gs.stages.pose import PoseConfig, chain_poses, run_pose

OURS = {
    "ours": {},
    "ours no-L_C": {"depth_consistency_weight": 0.0},
    "ours flow-only (no ICP)": {"use_icp": False},
    "ours DIS-ultrafast": {"flow_preset": "ultrafast"},
    "ours GT-flow": {"flow_dir": "GT"},
}


def gt_flows(sequence, depths: list[np.ndarray], folder: Path) -> None:
    """Flows implied by ground-truth motion and noise-free depth, forward and backward, as .npy per pair."""
    K, poses = sequence.intrinsics.K(), sequence.gt_poses
    for k in range(len(poses) - 1):
        for a, b, tag in ((k, k + 1, ""), (k + 1, k, "_backward")):
            write_flow(folder / f"{k:06d}{tag}.npy", motion_flow(depths[a], K, invert(poses[b]) @ poses[a]))


def motion_flow(depth: np.ndarray, K: np.ndarray, T: np.ndarray) -> np.ndarray:
    h, w = depth.shape
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    moved = project(transform(T, backproject(depth, K)), K)
    flow = np.stack([moved[..., 0] - u, moved[..., 1] - v], axis=-1)
    flow[depth <= 0] = np.nan
    return flow.astype(np.float32)


def run_ours(sequence, overrides: dict, flow_dir: Path, work: Path) -> tuple[np.ndarray, float, int]:
    if overrides.get("flow_dir") == "GT":
        overrides = {**overrides, "flow_dir": str(flow_dir)}
    config = dataclasses.replace(PoseConfig(), **overrides)
    result = run_pose(sequence, work, config)
    weak = sum(p["weak"] for p in result.pairs)
    return result.poses, float(np.mean([p["seconds"] for p in result.pairs])), weak


def run_icp_only(sequence, config: PoseConfig) -> tuple[np.ndarray, float, int]:
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
            config.icp_distance_factor, config.icp_normal_radius_factor, config.icp_normal_max_nn)
        relatives.append(result.transform)
        seconds.append(time.perf_counter() - start)
    return chain_poses(relatives), float(np.mean(seconds)), 0


def run_open3d_hybrid(sequence) -> tuple[np.ndarray, float, int]:
    intr = sequence.intrinsics
    camera = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    option = o3d.pipelines.odometry.OdometryOption(
        iteration_number_per_pyramid_level=o3d.utility.IntVector([20, 10, 5]), depth_diff_max=0.07, depth_min=0.1, depth_max=10.0)

    def rgbd(i: int):
        color = o3d.geometry.Image(np.ascontiguousarray((sequence.color(i) * 255).astype(np.uint8)))
        depth = o3d.geometry.Image(np.ascontiguousarray(sequence.depth(i), dtype=np.float32))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(color, depth, depth_scale=1.0, depth_trunc=10.0, convert_rgb_to_intensity=True)

    relatives, seconds, failed = [], [], 0
    for k in range(len(sequence) - 1):
        start = time.perf_counter()
        ok, T, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
            rgbd(k), rgbd(k + 1), camera, np.eye(4), o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(), option)
        failed += not ok
        relatives.append(T if ok else np.eye(4))
        seconds.append(time.perf_counter() - start)
    return chain_poses(relatives), float(np.mean(seconds)), failed


def evaluate(poses: np.ndarray, gt: np.ndarray) -> tuple[float, float, float]:
    trans, rot = rpe(poses, gt)
    return ate(poses, gt), trans, rot


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="320x240 only, extreme blur, 12 frames")
    parser.add_argument("--frames", type=int, default=20)
    parser.add_argument("--out", type=Path, default=None, help="keep sequences and outputs here")
    parser.add_argument("--trajectories", default="translation,turn,handheld")
    parser.add_argument("--sizes", default="320x240,640x480")
    parser.add_argument("--blurs", default="none,moderate,extreme")
    parser.add_argument("--methods", default=",".join([*OURS, "ICP only", "O3D hybrid"]))
    parser.add_argument("--sequence", type=Path, action="append", help="benchmark this folder instead of synthetic ones")
    args = parser.parse_args()
    methods = args.methods.split(",")
    root = args.out or Path(tempfile.mkdtemp(prefix="bench_pose_"))
    print("| sequence | method | ATE (m) | RPE trans (m) | RPE rot (deg) | s/pair | weak/failed pairs |")
    print("|---|---|---|---|---|---|---|")
    for name, sequence, clean_depths in sequences(args, root):
        flow_dir = root / name.replace(" ", "_") / "gt_flow"
        if "ours GT-flow" in methods:
            gt_flows(sequence, clean_depths, flow_dir)
        for method in methods:
            if method in OURS:
                poses, seconds, weak = run_ours(sequence, OURS[method], flow_dir, root / name.replace(" ", "_") / method.replace(" ", "_"))
            elif method == "ICP only":
                poses, seconds, weak = run_icp_only(sequence, PoseConfig())
            else:
                poses, seconds, weak = run_open3d_hybrid(sequence)
            a, t, r = evaluate(poses, sequence.gt_poses)
            print(f"| {name} | {method} | {a:.4f} | {t:.4f} | {r:.3f} | {seconds:.2f} | {weak} |", flush=True)


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
        for w, h in sizes:
            for blur in blurs:
                name = f"{trajectory} {w}x{h} {blur}"
                folder = root / name.replace(" ", "_") / "seq"
                generate(SynthConfig(width=w, height=h, frames=frames, trajectory=trajectory, blur=blur, seed=0), folder)
                sequence = load_sequence(folder)
                K = sequence.intrinsics.K()
                yield name, sequence, [render_view(p, K, w, h, 0)[1] for p in sequence.gt_poses]


if __name__ == "__main__":
    main()
