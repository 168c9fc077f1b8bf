"""Stage 2: global refinement of camera poses and geometry with fixed-scale Gaussians.

One isotropic Gaussian per fused point (scale fixed at s/2, opacity 0.5); only positions, opacities
and camera poses are trained, against each frame's input depth, with a masked depth L1 loss and the
opacity binarisation loss o^2 (1 - o)^2. The first camera is held fixed to pin the gauge. Gaussians
with opacity under 0.8 are pruned every 100 N iterations and opacities reset to 0.5 every 200 N,
600 N iterations in all (N frames); the `fast` preset scales this schedule down for CPU runs.
"""

from __future__ import annotations

import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..config import tomllib
from ..errors import InputError
from ..geometry import se3_exp
from ..io.atomic import atomic_path, write_text
from ..io.ply import read_point_cloud, write_point_cloud, write_splats
from ..io.sequence import Sequence
from ..io.trajectory import read_tum, write_tum
from ..plots import line_plot
from ..refine_model import DepthRefiner
from ..splats import splats_from_points


@dataclass(frozen=True)
class RefineConfig:
    """Every number stage 2 uses; defaults follow the method (`paper` preset)."""

    voxel_size: float = 0.0  # s in metres; 0 = take the voxel size stage 1 used
    initial_opacity: float = 0.5
    iterations_per_frame: int = 600
    prune_every_per_frame: int = 100
    reset_every_per_frame: int = 200
    prune_opacity: float = 0.8
    lambda_depth: float = 1.0
    lambda_opacity: float = 0.1
    lr_means: float = 1.6e-4  # times the scene extent, decayed to lr_means_final
    lr_means_final: float = 1.6e-6
    lr_opacity: float = 0.05
    lr_pose: float = 1e-3  # decayed exponentially to lr_pose_final
    lr_pose_final: float = 1e-5
    resolution_scale: int = 1  # render at 1/scale of the input resolution
    seed: int = 0
    checkpoint_every: int = 500
    max_depth: float = 0.0  # ignore input depth beyond this (0 = keep all)


PRESETS = {
    "paper": RefineConfig(),
    "fast": RefineConfig(iterations_per_frame=60, prune_every_per_frame=20, reset_every_per_frame=40,
                         resolution_scale=2, checkpoint_every=200),
}


@dataclass
class RefineResult:
    poses: np.ndarray
    loss_history: list[dict[str, float]]
    gaussians: int
    seconds_per_iteration: float


def _exp_decay(start: float, end: float, fraction: float) -> float:
    return float(np.exp(np.log(start) * (1.0 - fraction) + np.log(end) * fraction))


def _downsample_depth(depth: np.ndarray, scale: int) -> np.ndarray:
    """Nearest-neighbour subsampling at pixel centres (keeps depth sharp, no mixing at edges)."""
    if scale == 1:
        return depth
    return np.ascontiguousarray(depth[scale // 2::scale, scale // 2::scale])


def _scaled_intrinsics(K: np.ndarray, scale: int) -> np.ndarray:
    """Intrinsics of the image subsampled at pixels scale*i + scale//2 (OpenCV convention)."""
    K = K.copy()
    K[0, 0] /= scale
    K[1, 1] /= scale
    K[0, 2] = (K[0, 2] - scale // 2) / scale
    K[1, 2] = (K[1, 2] - scale // 2) / scale
    return K


def load_stage1(out_dir: Path, poses_path: Path | None = None, points_path: Path | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Stage-1 timestamps, poses, fused points and colours, and the voxel size it used."""
    poses_path = poses_path or out_dir / "pose" / "trajectory.txt"
    points_path = points_path or out_dir / "pose" / "points.ply"
    for path in (poses_path, points_path):
        if not path.is_file():
            raise InputError(path, "stage-1 output missing", "run 'taichi-gs pose' first or pass --poses and --points")
    timestamps, poses = read_tum(poses_path)
    points, colors = read_point_cloud(points_path)
    if len(points) == 0:
        raise InputError(points_path, "point cloud is empty", "rerun stage 1; check the depth maps")
    voxel = 0.0
    stage1_config = out_dir / "pose" / "config.toml"
    if stage1_config.is_file():
        voxel = float(tomllib.loads(stage1_config.read_text()).get("pose", {}).get("voxel_size_m", 0.0))
    return timestamps, poses, points, colors, voxel


def run_refine(
    sequence: Sequence,
    initial_poses: np.ndarray,
    points: np.ndarray,
    colors: np.ndarray,
    out_dir: Path,
    config: RefineConfig,
    progress: Callable[..., None] | None = None,
) -> RefineResult:
    """Refine poses, positions and opacities; write OUT/refine/ and return the refined poses."""
    if len(initial_poses) != len(sequence):
        raise InputError(out_dir / "pose" / "trajectory.txt", f"{len(initial_poses)} poses for {len(sequence)} frames",
                         "rerun stage 1 on this sequence")
    if config.voxel_size <= 0:
        raise InputError(None, "voxel size unknown", "set [refine] voxel_size in the config")
    stage_dir = out_dir / "refine"
    stage_dir.mkdir(parents=True, exist_ok=True)
    n_frames = len(sequence)
    total = config.iterations_per_frame * n_frames
    prune_every = config.prune_every_per_frame * n_frames
    reset_every = config.reset_every_per_frame * n_frames

    scale = config.resolution_scale
    K = _scaled_intrinsics(sequence.K(), scale)
    depths = [_downsample_depth(sequence.depth(i), scale) for i in range(n_frames)]
    if config.max_depth > 0:
        depths = [np.where(d <= config.max_depth, d, 0.0).astype(np.float32) for d in depths]
    height, width = depths[0].shape

    splats = splats_from_points(points, colors, scale=config.voxel_size / 2, opacity=config.initial_opacity)
    extent = float(np.linalg.norm(initial_poses[:, :3, 3] - initial_poses[:, :3, 3].mean(axis=0), axis=1).max())
    extent = max(extent * 1.1, 1.0)
    model = DepthRefiner(splats.means, splats.opacity_logits, scale=config.voxel_size / 2, K=K, width=width, height=height)
    poses = initial_poses.copy()
    pose_adam = np.zeros((n_frames, 2, 6))
    pose_steps = np.zeros(n_frames, dtype=np.int64)
    rng = np.random.default_rng(config.seed)
    history: list[dict[str, float]] = []
    start_iteration = 0

    checkpoint = stage_dir / "checkpoint.npz"
    if checkpoint.is_file():
        state = np.load(checkpoint, allow_pickle=False)
        if json.loads(str(state["config"])) == dataclasses.asdict(config) and len(state["poses"]) == n_frames:
            start_iteration = int(state["iteration"])
            poses, pose_adam, pose_steps = state["poses"], state["pose_adam"], state["pose_steps"]
            model.load_state({k[6:]: state[k] for k in state.files if k.startswith("model_")})
            rng = np.random.default_rng([config.seed, start_iteration])
            history = json.loads(str(state["history"]))

    t0 = time.perf_counter()
    for it in range(start_iteration, total):
        fraction = it / max(total - 1, 1)
        frame = int(rng.integers(n_frames))
        losses, pose_grad = model.step(
            depths[frame], poses[frame],
            lambda_depth=config.lambda_depth, lambda_opacity=config.lambda_opacity,
            lr_means=_exp_decay(config.lr_means, config.lr_means_final, fraction) * extent,
            lr_opacity=config.lr_opacity,
        )
        if not np.all(np.isfinite(pose_grad)) or not np.isfinite(losses["depth"]):
            raise FloatingPointError(f"stage 2 (refine) diverged at iteration {it}: non-finite loss or gradient")
        if frame != 0:
            lr_pose = _exp_decay(config.lr_pose, config.lr_pose_final, fraction)
            poses[frame] = _adam_pose_step(poses[frame], pose_grad, pose_adam[frame], pose_steps, frame, lr_pose)
        if (it + 1) % 10 == 0 or it == total - 1:
            history.append({"iteration": it + 1, **losses, "gaussians": model.count})
        if (it + 1) % prune_every == 0 and it + 1 < total:
            model.prune(config.prune_opacity)
        if (it + 1) % reset_every == 0 and it + 1 < total:
            model.reset_opacity(config.initial_opacity)
        if progress is not None:
            progress(it + 1, total, depth_l1=losses["depth"], gaussians=model.count)
        if (it + 1) % config.checkpoint_every == 0 and it + 1 < total:
            _save_checkpoint(checkpoint, it + 1, config, poses, pose_adam, pose_steps, model, history)
    seconds = (time.perf_counter() - t0) / max(total - start_iteration, 1)

    _write_outputs(stage_dir, sequence, poses, model, colors, splats, config, history)
    if checkpoint.is_file():
        checkpoint.unlink()
    return RefineResult(poses, history, model.count, seconds)


def _adam_pose_step(pose: np.ndarray, grad: np.ndarray, adam: np.ndarray, steps: np.ndarray, frame: int, lr: float,
                    beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8) -> np.ndarray:
    """Adam on the left-multiplied se(3) perturbation; the pose stays on SE(3) (update by exp)."""
    steps[frame] += 1
    t = steps[frame]
    adam[0] = beta1 * adam[0] + (1 - beta1) * grad
    adam[1] = beta2 * adam[1] + (1 - beta2) * grad**2
    m_hat = adam[0] / (1 - beta1**t)
    v_hat = adam[1] / (1 - beta2**t)
    return se3_exp(-lr * m_hat / (np.sqrt(v_hat) + eps)) @ pose


def _save_checkpoint(path: Path, iteration: int, config: RefineConfig, poses: np.ndarray, pose_adam: np.ndarray,
                     pose_steps: np.ndarray, model: DepthRefiner, history: list[dict[str, float]]) -> None:
    arrays = {f"model_{k}": v for k, v in model.state().items()}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, iteration=iteration, config=json.dumps(dataclasses.asdict(config)), poses=poses,
                     pose_adam=pose_adam, pose_steps=pose_steps, history=json.dumps(history), **arrays)


def _write_outputs(stage_dir: Path, sequence: Sequence, poses: np.ndarray, model: DepthRefiner, colors: np.ndarray,
                   splats, config: RefineConfig, history: list[dict[str, float]]) -> None:
    kept = model.kept_indices()
    final = splats.subset(kept)
    final.means = model.means().astype(np.float32)
    final.opacity_logits = model.opacity_logits().astype(np.float32)
    write_splats(stage_dir / "splats.ply", final)
    write_point_cloud(stage_dir / "points.ply", final.means, colors[kept])
    if history:
        it = np.array([h["iteration"] for h in history], dtype=float)
        line_plot(stage_dir / "loss.png", {
            "depth L1 (m)": (it, np.array([h["depth"] for h in history])),
            "opacity binarisation": (it, np.array([h["opacity"] for h in history])),
        }, "stage 2: refinement losses", "iteration", "loss", log_y=True)
    write_text(stage_dir / "history.json", json.dumps(history) + "\n")
    write_tum(stage_dir / "trajectory.txt", sequence.timestamps, poses, header="taichi-gs stage 2 (refine), camera-to-world")
