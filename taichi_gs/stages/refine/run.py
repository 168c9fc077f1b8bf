"""Stage 2: global refinement of camera poses and geometry with fixed-scale Gaussians.

One isotropic Gaussian per fused point (scale fixed at s/2, opacity 0.5); only positions, opacities
and camera poses are trained, against each frame's input depth, with a masked depth L1 loss and the
opacity binarisation loss o^2 (1 - o)^2. The first camera is held fixed to pin the gauge. Gaussians
with opacity under 0.8 are pruned every 100 N iterations and opacities reset to 0.5 every 200 N,
600 N iterations in all (N frames); the `fast` preset scales this schedule down for CPU runs.

Our choices, each measured against ground truth (bench/refine.py, tests/test_refine.py):
- the depth compared is the alpha-normalised blend D / alpha on pixels with alpha >= 0.5, plus a
  coverage term mean(1 - alpha) where the input has depth: the raw blend D is short wherever alpha
  < 1, which biased every pose gradient; normalising alone left holes (opacity 0.5 is a fixed
  point of the binarisation loss) that pruning then opened;
- input depth next to depth steps is ignored: a splat render smears edges over its footprint;
- each pose takes Adam steps on a camera-frame twist (translation along the camera axes, rotation
  about its centre) with per-component rates in metres and radians, exponentially decayed, and
  stays fixed for a short warm-up while opacities settle; the step starts at 0.1 mm, below stage 1's
  error, because Adam's normalised step makes a pose wander by about the learning rate along the
  directions depth alone does not constrain (issue 11: 1 cm steps moved exact poses 2-5 mm);
- the refined trajectory is kept only if stage 1's depth + colour verification score of its
  relative poses is no worse than the initial poses' (stages/refine/accept.py).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ... import profiling
from ...config import tomllib
from ...errors import InputError
from ...geometry import adjoint, invert, median_depths, se3_exp, se3_log
from ...io import jsonout
from ...io.atomic import write_text
from ...io.ply import read_point_cloud, write_point_cloud, write_splats
from ...io.sequence import Sequence
from ...io.trajectory import check_frame_times, read_tum, write_tum
from ...plots import line_plot
from ...rolling_shutter import DeskewedSequence, deskewing_motions, readout_motions, stage_readout_ms
from ...splats import Splats, splats_from_points
from .. import checkpoint
from ..declaration import StageContext, StageDeclaration, StageInputs, StageRun
from ..divergence import DivergenceGuard
from ..row_adam import RowAdam
from ..schedule import ConvergenceWatch, downsample_depth, exp_decay, scaled_intrinsics
from .accept import accept_refined_poses
from .config import PRESETS, RefineConfig
from .model import DepthRefiner

FOOTPRINT_FRAMES = 8  # frames whose depth sets the Gaussians' footprint in pixels (evenly spread)
PARAMETER_CHECK_EVERY = 50  # iterations between divergence checks of the parameters (a device copy)


@dataclass
class RefineResult:
    poses: np.ndarray
    loss_history: list[dict[str, float]]
    gaussians: int
    seconds_per_iteration: float
    iterations: int = 0  # iterations run in all (below the cap when the convergence stop ended it)


def _without_edges(depth: np.ndarray, ratio: float, radius: int) -> np.ndarray:
    """Depth with pixels near a depth step (max - min over a (2r+1)^2 window > ratio * depth) set to 0.

    A splat render smears each edge over the Gaussians' footprint, so these pixels bias the pose."""
    kernel = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    depth = depth.astype(np.float32)
    high = cv2.dilate(depth, kernel)
    low = cv2.erode(np.where(depth > 0, depth, np.float32(np.inf)), kernel)
    return np.where(high - low > ratio * depth, 0.0, depth).astype(np.float32)


def load_stage1(out_dir: Path, frame_times: np.ndarray, poses_path: Path | None = None,
                points_path: Path | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Stage-1 poses, and fused points and colours (``poses_path``/``points_path`` replace them). Stage 1's own
    trajectory must be stamped ``frame_times``, the frames it is read for; a ``poses_path`` file is taken pose by
    frame, as given."""
    own = poses_path is None
    poses_path = poses_path or out_dir / "pose" / "trajectory.txt"
    points_path = points_path or out_dir / "pose" / "points.ply"
    for path in (poses_path, points_path):
        if not path.is_file():
            raise InputError(path, "stage-1 output missing", "run 'taichi-gs pose' first or pass --poses and --points")
    timestamps, poses = read_tum(poses_path)
    if own:
        check_frame_times(poses_path, timestamps, frame_times, "rerun 'taichi-gs pose' on this sequence")
    points, colors = read_point_cloud(points_path)
    if len(points) == 0:
        raise InputError(points_path, "point cloud is empty", "rerun stage 1; check the depth maps")
    return poses, points, colors


def resolve_config(config: RefineConfig, sections: Mapping[str, Any], out_dir: Path | None) -> RefineConfig:
    """``voxel_size = 0`` becomes the voxel of the cloud stage 1 fused: the one recorded in the run
    folder's ``pose/config.toml`` when stage 1 ran there, else the ``[pose]`` table's."""
    if config.voxel_size > 0:
        return config
    voxel = sections["pose"].voxel_size_m if "pose" in sections else 0.0
    recorded = out_dir / "pose" / "config.toml" if out_dir is not None else None
    if recorded is not None and recorded.is_file():
        voxel = float(tomllib.loads(recorded.read_text()).get("pose", {}).get("voxel_size_m", voxel))
    return dataclasses.replace(config, voxel_size=voxel)


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
    splats = splats_from_points(points, colors, scale=config.voxel_size / 2, opacity=config.initial_opacity)
    if total == 0:  # [ours] hand over: stage 1's poses and fused cloud go to stage 3 untrained
        _write_outputs(stage_dir, sequence, initial_poses, splats, colors, [])
        return RefineResult(initial_poses.copy(), [], len(splats), 0.0, 0)

    prune_every = config.prune_every_per_frame * n_frames
    reset_every = config.reset_every_per_frame * n_frames
    K, depths = _training_depths(sequence, config)
    height, width = depths[0].shape
    extent = float(np.linalg.norm(initial_poses[:, :3, 3] - initial_poses[:, :3, 3].mean(axis=0), axis=1).max())
    extent = max(extent * 1.1, 1.0)
    model = DepthRefiner(splats.means, splats.opacity_logits, scale=config.voxel_size / 2, K=K, width=width,
                         height=height, free_scale=config.free_scale, min_alpha=config.min_alpha,
                         spatial_order=config.spatial_order)
    poses = initial_poses.copy()
    pose_adam = RowAdam(n_frames, (6,), eps=1e-12)
    history: list[dict[str, float]] = []
    start_iteration = 0

    checkpoint_path = stage_dir / "checkpoint.npz"
    saved = checkpoint.load(checkpoint_path, config)
    if saved is not None and len(saved.arrays["poses"]) == n_frames:
        start_iteration, poses, history = saved.iteration, saved.arrays["poses"].copy(), saved.records["history"]
        pose_adam.load_state(saved.arrays, "pose")
        model.load_state(saved.prefixed("model"))

    centre = points.mean(axis=0)
    guard = DivergenceGuard("stage 2 (refine)", centre, max(extent, float(np.linalg.norm(points - centre, axis=1).max())))
    views = min(config.views_per_step, n_frames)
    watch = _convergence_watch(config, n_frames)
    done = total
    t0 = time.perf_counter()
    for it in range(start_iteration, total):
        fraction = it / max(total - 1, 1)
        frames = np.random.default_rng([config.seed, it]).choice(n_frames, size=views, replace=False)
        losses, pose_grads = model.step(
            [depths[f] for f in frames], [poses[f] for f in frames],
            lambda_depth=config.lambda_depth, lambda_coverage=config.lambda_coverage,
            lambda_opacity=config.lambda_opacity, lrs=_gaussian_lrs(config, fraction, extent),
        )
        guard.check_step(it, losses["depth"], pose_grads)
        if fraction >= config.pose_warmup_fraction:
            lr = _pose_lrs(config, fraction)
            for f, grad in zip(frames, pose_grads):
                if f != 0:
                    prior = _pose_prior_gradient(poses[f], initial_poses[f], config)
                    poses[f] = _adam_pose_step(poses[f], grad, pose_adam, f, lr, prior)
        if (it + 1) % 10 == 0 or it == total - 1:
            history.append({"iteration": it + 1, **losses, "gaussians": model.count})
        if (it + 1) % prune_every == 0 and it + 1 < total:
            model.prune(config.prune_opacity)
        if (it + 1) % reset_every == 0 and it + 1 < total:
            model.reset_opacity(config.initial_opacity)
            watch.disturbed(it + 1)
        if progress is not None:
            progress(it + 1, total, depth_l1=losses["depth"], gaussians=model.count)
        if (it + 1) % PARAMETER_CHECK_EVERY == 0 or (it + 1) % config.checkpoint_every == 0 or it == total - 1:
            guard.check_parameters(it, model.means(), poses, model.opacity_logits())
        if (it + 1) % config.checkpoint_every == 0 and it + 1 < total:
            checkpoint.save(checkpoint_path, it + 1, config,
                            {"poses": poses, **pose_adam.state("pose"), **checkpoint.prefixed("model", model.state())},
                            {"history": history})
        if fraction >= config.pose_warmup_fraction and watch.update(it + 1, losses["depth"], poses):
            done = it + 1
            break
    seconds = (time.perf_counter() - t0) / max(done - start_iteration, 1)
    poses = _accepted_poses(sequence, initial_poses, poses, config, stage_dir)

    _write_outputs(stage_dir, sequence, poses, _trained_splats(model, splats, config), colors[model.kept_indices()],
                   history)
    checkpoint_path.unlink(missing_ok=True)
    return RefineResult(poses, history, model.count, seconds, done)


def gaussian_footprint_px(sequence: Sequence, scale_m: float) -> tuple[float, float]:
    """[ours] How wide stage 2's Gaussians (sigma ``scale_m``) are in pixels of the input frames at the
    sequence's median depth, and that depth in metres: the fused cloud's voxel is in metres, so the same
    Gaussian is finer in pixels far away and at low resolution."""
    frames = np.unique(np.linspace(0, len(sequence) - 1, min(FOOTPRINT_FRAMES, len(sequence))).round().astype(int))
    depth = float(np.median(median_depths([sequence.depth(int(i)) for i in frames])))
    return scale_m * sequence.intrinsics.fx / depth, depth


def _convergence_watch(config: RefineConfig, n_frames: int) -> ConvergenceWatch:
    """[ours] The convergence stop of the schedule (window 0: never stops before the cap)."""
    return ConvergenceWatch(config.converge_window_per_frame * n_frames, config.converge_rel_tol,
                            config.converge_pose_m, config.converge_pose_deg)


def _accepted_poses(sequence: Sequence, initial_poses: np.ndarray, poses: np.ndarray, config: RefineConfig,
                    stage_dir: Path) -> np.ndarray:
    """[ours] The refined poses if they pass the acceptance test, else the initial ones; the scores go to
    ``stage_dir/acceptance.json``. Unchanged when ``accept_neighbours`` is 0."""
    if config.accept_neighbours <= 0:
        return poses
    chosen, acceptance = accept_refined_poses(sequence, initial_poses, poses, config.accept_neighbours)
    write_text(stage_dir / "acceptance.json", jsonout.dumps(acceptance.to_dict()) + "\n")
    return chosen


def _training_depths(sequence: Sequence, config: RefineConfig) -> tuple[np.ndarray, list[np.ndarray]]:
    """Intrinsics and every frame's input depth at the training resolution, with the ignored pixels at 0."""
    depths = [downsample_depth(sequence.depth(i), config.resolution_scale) for i in range(len(sequence))]
    if config.max_depth > 0:
        depths = [np.where(d <= config.max_depth, d, 0.0).astype(np.float32) for d in depths]
    if config.edge_ratio > 0:
        depths = [_without_edges(d, config.edge_ratio, config.edge_radius) for d in depths]
    return scaled_intrinsics(sequence.K(), config.resolution_scale), depths


def _gaussian_lrs(config: RefineConfig, fraction: float, extent: float) -> dict[str, float]:
    """Learning rates of the Gaussian parameters at this point of the schedule."""
    return {
        "means": exp_decay(config.lr_means, config.lr_means_final, fraction) * extent,
        "opacity_logits": config.lr_opacity,
        "log_scales": config.lr_log_scales,
        "quats": config.lr_quats,
    }


def _pose_lrs(config: RefineConfig, fraction: float) -> np.ndarray:
    """Per-component pose learning rates [translation (m) x3, rotation (rad) x3], decayed after the warm-up."""
    warm = config.pose_warmup_fraction
    lr = exp_decay(config.lr_pose, config.lr_pose_final, (fraction - warm) / max(1.0 - warm, 1e-9))
    return np.array([lr] * 3 + [lr * config.pose_rotation_per_m] * 3)


def _pose_prior_gradient(pose: np.ndarray, initial: np.ndarray, config: RefineConfig) -> np.ndarray | None:
    """Camera-frame gradient of the pose prior, w [e_t / sigma_t^2, e_r / sigma_r^2] (first order), or None when off."""
    if config.pose_prior_weight <= 0:
        return None
    e = se3_log(invert(initial) @ pose)
    sigma = np.array([config.pose_prior_sigma_m] * 3 + [np.radians(config.pose_prior_sigma_deg)] * 3)
    return config.pose_prior_weight * e / sigma**2


def _adam_pose_step(pose: np.ndarray, grad: np.ndarray, adam: RowAdam, frame: int, lr: np.ndarray,
                    prior: np.ndarray | None = None) -> np.ndarray:
    """Adam on the camera-frame se(3) perturbation ``pose @ exp(delta)`` (translation along the
    camera's axes, rotation about its centre); the pose stays on SE(3) (update by exp).

    ``grad`` is the rasterizer's gradient for the world-frame perturbation ``exp(delta) @ pose``;
    the camera-frame one is ``Ad(pose)^T grad``; ``prior`` (camera frame) is added to it."""
    grad = adjoint(pose).T @ grad
    if prior is not None:
        grad = grad + prior
    return pose @ se3_exp(-lr * adam.direction(frame, grad))


def _trained_splats(model: DepthRefiner, splats: Splats, config: RefineConfig) -> Splats:
    """The initial ``splats`` that survived pruning, with the trained parameters of ``model``."""
    final = splats.subset(model.kept_indices())
    final.means = model.means().astype(np.float32)
    final.log_scales = model.log_scales().astype(np.float32)
    if config.free_scale:
        final.quats = model.quats().astype(np.float32)
    final.opacity_logits = model.opacity_logits().astype(np.float32)
    return final


@profiling.timed("outputs (renders, PLY, plots: I/O)")
def _write_outputs(stage_dir: Path, sequence: Sequence, poses: np.ndarray, splats: Splats, colors: np.ndarray,
                   history: list[dict[str, float]]) -> None:
    """The stage's files: ``splats`` (with ``colors`` per Gaussian for points.ply), ``poses``, the loss history."""
    write_splats(stage_dir / "splats.ply", splats)
    write_point_cloud(stage_dir / "points.ply", splats.means, colors)
    if history:
        it = np.array([h["iteration"] for h in history], dtype=float)
        line_plot(stage_dir / "loss.png", {
            "depth L1 (m)": (it, np.array([h["depth"] for h in history])),
            "opacity binarisation": (it, np.array([h["opacity"] for h in history])),
        }, "stage 2: refinement losses", "iteration", "loss", log_y=True)
    write_text(stage_dir / "history.json", jsonout.dumps(history) + "\n")
    write_tum(stage_dir / "trajectory.txt", sequence.timestamps, poses, header="taichi-gs stage 2 (refine), camera-to-world")


def deskewed_for_training(sequence: Sequence, initial_poses: np.ndarray, config: RefineConfig) -> tuple[Any, float]:
    """The sequence stage 2 trains on and its rolling shutter's readout (ms): with a readout and training, the
    frames de-skewed by the readout motions of ``initial_poses``; else ``sequence`` itself and 0."""
    readout_ms = stage_readout_ms(config.readout_ms, config.camera_readout, sequence.source)
    if readout_ms <= 0 or config.iterations_per_frame == 0:
        return sequence, 0.0
    motions = readout_motions(initial_poses, sequence.timestamps, readout_ms / 1000.0)
    return DeskewedSequence(sequence, deskewing_motions(sequence, motions)[0]), readout_ms


def _run_stage(context: StageContext) -> StageRun:
    initial, cloud, colors = load_stage1(context.out, context.sequence.timestamps, context.poses, context.points)
    config = context.config
    sequence, readout_ms = deskewed_for_training(context.sequence, initial, config)
    with context.progress(STAGE.title, config.iterations_per_frame * len(context.sequence)) as update:
        result = run_refine(sequence, initial, cloud, colors, context.out, config, progress=update)
    scale = config.voxel_size / 2
    pixels, depth = gaussian_footprint_px(context.sequence, scale)
    footprint = f"sigma {scale * 100:.2g} cm = {pixels:.2f} px at the median depth {depth:.2f} m"
    if result.iterations == 0:
        return StageRun(f"{result.gaussians} Gaussians from stage 1's cloud ({footprint}), not trained "
                        "(iterations_per_frame = 0)")
    milliseconds = result.seconds_per_iteration * 1000
    shutter = f", frames de-skewed for a rolling shutter of {readout_ms:g} ms" if readout_ms > 0 else ""
    return StageRun(f"{result.gaussians} Gaussians ({footprint}), {milliseconds:.1f} ms/iteration{shutter}")


def _stage_inputs(out: Path, config: RefineConfig, poses: Path | None, points: Path | None) -> StageInputs:
    return StageInputs(files={"poses": poses or out / "pose" / "trajectory.txt",
                              "points": points or out / "pose" / "points.ply"})


STAGE = StageDeclaration(
    name="refine", title="stage 2: refine", config_type=RefineConfig, presets=PRESETS,
    outputs=("trajectory.txt", "splats.ply", "points.ply"), run=_run_stage, inputs=_stage_inputs,
    resolve=resolve_config,
)
