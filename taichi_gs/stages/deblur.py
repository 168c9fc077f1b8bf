"""Stage 3: deblurring. Each training frame's blurred colour is modelled as the mean of k sharp
renders at virtual poses ``T_t exp((1 - tau) d_s + tau d_e)``, tau in linspace(0, 1, k), between
its exposure start and end; the loss is (1 - l_B) L1 + l_B D-SSIM of that mean against the input,
plus l_D times the masked depth L1 of the mid-exposure render. All Gaussian parameters (with
3DGS-style densification and pruning) and both exposure offsets of every training frame are
trained. Every ``holdout_every``-th frame (1, 1 + h, ...) is held out (or, with ``holdout =
"sharpest"``, for real data, the sharpest frame of each window of h frames that lies between two
training frames); its camera comes from stage 2 and, optionally, a test-time refinement of its own
exposure against its blurred frame with the scene frozen (no ground truth places a camera).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..deblur_model import BlurScene, FrozenAnchors, Rates, anchor_count, warped_views
from ..density import DensitySchedule, footprint_limit
from ..errors import InputError
from ..geometry import median_depths, virtual_pose
from ..io.atomic import write_text
from ..io import jsonout
from ..io.ply import read_splats, write_splats
from ..io.sequence import SOURCED, Sequence
from ..io.trajectory import check_frame_times, format_tum, read_tum, write_tum
from ..io.images import encode_depth, to_uint8, write_png
from ..noreference import laplacian_variance, sharpest_holdout
from ..photometric import IDENTITY, apply_affine, identity_penalty
from ..rolling_shutter import DeskewedSequence, deskewing_motions, readout_motions, readout_skews, stage_readout_ms
from ..plots import image_grid, line_plot
from ..splats import Splats
from . import checkpoint
from .deblur_config import PRESETS, DeblurConfig, scaled_schedule, with_headroom
from .declaration import StageContext, StageDeclaration, StageInputs, StageRun
from .divergence import DivergenceGuard
from .gauge import FrameShift, back_to_stage_2s_frame
from .exposures import Exposures, colour_step, exposure_px, keep_open, shrink_mid
from .row_adam import RowAdam
from .rprop import Rprop
from .schedule import downsample_depth, exp_decay, scaled_intrinsics, training_scale, views_for_span


PARAMETER_CHECK_EVERY = 50  # iterations between divergence checks of the parameters (a device copy)


@dataclass
class DeblurResult:
    mid_poses: np.ndarray  # (N, 4, 4) mid-exposure camera-to-world
    exposure: np.ndarray  # (N, 2, 4, 4) start and end
    train: list[int]
    test: list[int]
    loss_history: list[dict[str, float]]
    gaussians: int
    seconds_per_iteration: float
    warnings: list[str] = field(default_factory=list)
    readout_ms: float = 0.0  # the rolling shutter's readout modelled (0: a global shutter)

    def summary(self) -> str:
        """One line for the console; ``warnings`` are reported separately, one per line."""
        shutter = f", rolling shutter {self.readout_ms:g} ms" if self.readout_ms > 0 else ""
        return (f"{self.gaussians} Gaussians, {len(self.train)} train / {len(self.test)} test views, "
                f"{self.seconds_per_iteration * 1000:.0f} ms/iteration{shutter}")


def split_frames(n_frames: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """(train, test) frame indices: frames 1, 1 + h, 1 + 2h, ... are test views (none if h is 0)."""
    test = list(range(1, n_frames, holdout_every)) if holdout_every > 0 else []
    held_out = set(test)
    train = [i for i in range(n_frames) if i not in held_out]
    if not train:
        raise InputError(None, f"no training frames left with holdout_every={holdout_every}",
                         "use --holdout none or a larger value")
    return train, test


def training_frame(train: list[int], iteration: int, rng: np.random.Generator, seed: int, epochs: bool) -> int:
    """The frame trained at ``iteration``: uniform at random, or (``epochs``) every training view once
    per epoch of len(train) iterations, in an order that depends only on ``seed`` and the epoch."""
    if not epochs:
        return train[int(rng.integers(len(train)))]
    epoch, place = divmod(iteration, len(train))
    return train[int(np.random.default_rng([seed, epoch]).permutation(len(train))[place])]


def choose_split(colors: list[np.ndarray], holdout: str, holdout_every: int) -> tuple[list[int], list[int], list[float]]:
    """(train, test, sharpness): ``holdout`` "every" takes :func:`split_frames`; "sharpest" holds out
    the sharpest frame (``noreference.laplacian_variance``) of each window of ``holdout_every`` frames
    that lies between two training frames (:func:`noreference.sharpest_holdout`)."""
    sharpness = [laplacian_variance(c) for c in colors]
    if holdout == "every":
        return (*split_frames(len(colors), holdout_every), sharpness)
    if holdout != "sharpest":
        raise InputError(None, f"unknown holdout mode {holdout!r}", 'set [deblur] holdout to "every" or "sharpest"')
    if holdout_every == 1 or len(colors) < 2:
        raise InputError(None, f"cannot hold out the sharpest of every {holdout_every} of {len(colors)} frames",
                         "use holdout_every >= 2 (or 0) and at least 2 frames")
    return (*sharpest_holdout(sharpness, holdout_every), sharpness)


def load_stage2(out_dir: Path, frame_times: np.ndarray) -> tuple[np.ndarray, Splats]:
    """Stage-2 poses (N, 4, 4) and splats from OUT/refine/, made for the frames stamped ``frame_times``."""
    poses_path, splats_path = out_dir / "refine" / "trajectory.txt", out_dir / "refine" / "splats.ply"
    for path in (poses_path, splats_path):
        if not path.is_file():
            raise InputError(path, "stage-2 output missing", "run 'taichi-gs refine' first")
    timestamps, poses = read_tum(poses_path)
    check_frame_times(poses_path, timestamps, frame_times, "rerun stage 2 on this sequence")
    splats = read_splats(splats_path)
    if len(splats) == 0:
        raise InputError(splats_path, "no Gaussians", "rerun stage 2")
    return poses, splats


def with_sh_degree(splats: Splats, degree: int) -> Splats:
    """The splats with SH bands up to ``degree`` (higher bands added as zeros or dropped)."""
    m = (degree + 1) ** 2
    sh = np.zeros((len(splats), m, 3), np.float32)
    keep = min(m, splats.sh.shape[1])
    sh[:, :keep] = splats.sh[:, :keep]
    return dataclasses.replace(splats, sh=sh)


def _downsample_color(color: np.ndarray, scale: int) -> np.ndarray:
    """Area average over scale x scale blocks (pixel i covers inputs scale*i .. scale*i + scale - 1)."""
    if scale == 1:
        return color
    h, w = color.shape[0] // scale, color.shape[1] // scale
    return cv2.resize(color[: h * scale, : w * scale], (w, h), interpolation=cv2.INTER_AREA)


def _area_intrinsics(K: np.ndarray, scale: int) -> np.ndarray:
    """Intrinsics of the block-averaged image (block centre at scale*i + (scale - 1)/2)."""
    K = scaled_intrinsics(K, scale)
    K[0, 2] += (scale // 2 - (scale - 1) / 2) / scale
    K[1, 2] += (scale // 2 - (scale - 1) / 2) / scale
    return K


@dataclass
class _Frames:
    """The sequence at training resolution."""

    colors: list[np.ndarray]
    depths: list[np.ndarray]
    median_depth: np.ndarray
    K: np.ndarray
    sourced: np.ndarray | None = None  # H x W bool: pixels the losses use (None: all)


def _load_frames(sequence: Sequence, scale: int, sourced: np.ndarray | None,
                 depth_source: Sequence | DeskewedSequence | None = None) -> _Frames:
    """The frames at 1/``scale`` resolution, depth read from ``depth_source`` (None: ``sequence``); ``sourced``
    (full resolution, or None) is shrunk alike, a pixel kept only if its whole block is sourced."""
    colors = [_downsample_color(sequence.color(i), scale) for i in range(len(sequence))]
    h, w = colors[0].shape[:2]
    depth_source = sequence if depth_source is None else depth_source
    depths = [downsample_depth(depth_source.depth(i), scale)[:h, :w] for i in range(len(sequence))]
    if sourced is not None:
        sourced = _downsample_color(sourced.astype(np.float32), scale) >= SOURCED
    return _Frames(colors, depths, median_depths(depths), _area_intrinsics(sequence.K(), scale), sourced)


def loss_mask(sequence: Sequence, config: DeblurConfig) -> np.ndarray | None:
    """Full-resolution pixels stage 3's photometric losses use: ``Sequence.sourced_pixels`` with
    ``sourced_pixels_only``, else None (all)."""
    if not config.sourced_pixels_only:
        return None
    sourced = sequence.sourced_pixels()
    return None if sourced.all() else sourced


def _scene_extent(poses: np.ndarray, means: np.ndarray) -> float:
    """Radius of the scene: the 90th percentile distance of the Gaussians from the cameras' centroid."""
    centre = poses[:, :3, 3].mean(axis=0)
    return float(max(np.percentile(np.linalg.norm(means - centre, axis=1), 90), 1e-3))


def run_deblur(
    sequence: Sequence,
    out_dir: Path,
    config: DeblurConfig,
    progress: Callable[..., None] | None = None,
) -> DeblurResult:
    """Train the sharp scene and every training frame's exposure from OUT/refine/; write OUT/deblur/."""
    if config.k < 1:
        raise InputError(None, f"k must be at least 1, got {config.k}", "set [deblur] k or --k to 1 or more")
    out_dir = Path(out_dir)
    poses, splats = load_stage2(out_dir, sequence.timestamps)
    stage_dir = out_dir / "deblur"
    stage_dir.mkdir(parents=True, exist_ok=True)
    sourced = loss_mask(sequence, config)
    readout_ms = stage_readout_ms(config.readout_ms, config.camera_readout and config.warp_views, sequence.source)
    motions = readout_motions(poses, sequence.timestamps, readout_ms / 1000.0)
    depth_source = None
    if readout_ms > 0 and config.deskew_depth:
        depth_source = DeskewedSequence(sequence, deskewing_motions(sequence, motions)[0])
    frames = _load_frames(sequence, config.resolution_scale, sourced, depth_source)
    train, test, sharpness = choose_split(frames.colors, config.holdout, config.holdout_every)
    config = with_headroom(scaled_schedule(config, len(train)), len(splats))
    height, width = frames.colors[0].shape[:2]
    splats = with_sh_degree(splats, config.sh_degree)
    extent = _scene_extent(poses, splats.means)
    shutter = _Shutter(motions, frames.median_depth)
    model = BlurScene(splats, frames.K, width, height, sourced=frames.sourced,
                      warp_margin=warp_margin(config, shutter.skew_px(frames.K[0, 0], config)))
    centres = poses[train, :3, 3]
    if config.init_max_px > 0:
        limit = footprint_limit(model.arrays()["means"], centres, frames.K[0, 0], config.init_max_px)
        model.density.split_oversized(model.store, limit, config.max_gaussians, np.random.default_rng([config.seed, 1]))
    if config.spatial_order:
        model.order_in_space()
    exposures = Exposures(poses, config)
    rng = np.random.default_rng(config.seed)
    history: list[dict[str, float]] = []
    first = 0

    checkpoint_path = stage_dir / "checkpoint.npz"
    saved = checkpoint.load(checkpoint_path, config)
    if saved is not None and exposures.matches(saved.arrays):
        first, history = saved.iteration, saved.records["history"]
        exposures.load_state(saved.arrays)
        model.load_state(saved.prefixed("model"))
        rng.bit_generator.state = saved.records["rng"]

    guard = DivergenceGuard("stage 3 (deblur)", splats.means.mean(axis=0), extent)
    full, phase = frames, {config.resolution_scale: frames}
    t0 = time.perf_counter()
    for it in range(first, config.iterations):
        fraction = it / max(config.iterations - 1, 1)
        scale = training_scale(it, config.iterations, config.resolution_scale, config.coarse_scale,
                               config.coarse_fraction)
        frames, model = _phase(sequence, sourced, model, phase, scale)
        frame = training_frame(train, it, rng, config.seed, config.epoch_sampling)
        rates = Rates(means=exp_decay(config.lr_means, config.lr_means_final, fraction) * extent,
                      quats=config.lr_quats, log_scales=config.lr_scales, opacity_logits=config.lr_opacity,
                      colors=config.lr_colors)
        d = exposures.offsets[frame]
        k, anchors = _exposure_sampling(d, frames, frame, config, fraction)
        # the density schedule in this phase's pixels (coarse-to-fine changes the training width)
        density = density_schedule(config, extent, model.width, centres, frames.K[0, 0])
        step = model.step(frames.colors[frame], frames.depths[frame], poses[frame], d[0], d[1],
                          k, config.lambda_dssim, config.lambda_depth, rates, exposures.colour(frame),
                          anchors=anchors, fallback_depth=frames.median_depth[frame],
                          observe=density.observes(it + 1), readout_motion=shutter.motions[frame])
        guard.check_step(it, sum(step.losses.values()), (step.grad_start, step.grad_end))
        if it >= config.exposure_from:
            lr_exposure = exp_decay(config.lr_exposure, config.lr_exposure_final, fraction)
            exposures.update(frame, step.grad_start, step.grad_end, step.grad_colour, lr_exposure, full.K[0, 0],
                             full.median_depth[frame])
        loss = (1 - config.lambda_dssim) * step.losses["l1"] + config.lambda_dssim * step.losses["dssim"] \
            + config.lambda_depth * step.losses["depth"]
        if (it + 1) % 10 == 0 or it == config.iterations - 1:
            history.append({"iteration": it + 1, "loss": loss, "psnr": step.psnr, **step.losses, "gaussians": model.count})
        also = None
        if config.densify_by != "gradient" and density.densifies(it + 1):
            also = error_rows(model, frames, train, exposures, config, rng)
        model.density.step(it + 1, model.store, density, rng, also)
        if config.fill_uncovered and density.densifies(it + 1):
            for f in rng.choice(train, size=min(config.fill_frames, len(train)), replace=False):
                fill_uncovered(model, frames.colors[f], frames.depths[f], exposures.mid_pose(f),
                               frames.K, config.fill_stride, config.max_gaussians, rng,
                               min(config.fill_stride, config.split_px or config.fill_stride))
        if config.prune_weight_share > 0 and density.last_densification(it + 1):
            weights = model.blending_weights(exposures.mid_poses(train))
            model.density.drop_lightest(model.store, weights, config.prune_weight_share)
        if config.spatial_order and density.densifies(it + 1):
            model.order_in_space()
        if progress is not None:
            progress(it + 1, config.iterations, loss=loss, psnr=step.psnr, gaussians=model.count)
        if (it + 1) % PARAMETER_CHECK_EVERY == 0 or (it + 1) % config.checkpoint_every == 0 \
                or it == config.iterations - 1:
            params = model.arrays()
            guard.check_parameters(it, params["means"], exposures.offsets, *params.values())
        if (it + 1) % config.checkpoint_every == 0 and it + 1 < config.iterations:
            checkpoint.save(checkpoint_path, it + 1, config,
                            {**exposures.state(), **checkpoint.prefixed("model", model.state())},
                            {"history": history, "rng": rng.bit_generator.state})
    seconds = (time.perf_counter() - t0) / max(config.iterations - first, 1)

    frames, model = _phase(sequence, sourced, model, phase, config.resolution_scale)
    for frame in test:
        if config.test_fit_from_neighbours:
            exposures.start_from_neighbours(frame, train)
        exposures.offsets[frame], exposures.colours[frame] = _refine_test_exposure(
            model, frames, poses[frame], exposures.offsets[frame], exposures.start[frame], frame, config,
            shutter.motions[frame])
    warnings = _step_warnings(exposures.offsets, train, frames, config)
    splats, shift = model.splats(), None
    if config.keep_frame:
        splats, exposures.poses, exposures.offsets, shift = back_to_stage_2s_frame(
            splats, poses, exposures.offsets, train, config.keep_frame_scale_error)
    result = DeblurResult(
        mid_poses=np.stack(exposures.mid_poses()), exposure=exposures.ends(),
        train=train, test=test, loss_history=history, gaussians=model.count, seconds_per_iteration=seconds,
        warnings=warnings, readout_ms=readout_ms,
    )
    _write_outputs(stage_dir, sequence, splats, exposures, result, config, sharpness, shift, shutter)
    checkpoint_path.unlink(missing_ok=True)
    return result


def _views(d: np.ndarray, focal: float, depth: float, config: DeblurConfig, fraction: float = 1.0) -> int:
    """Virtual views for one exposure: ``config.k``, or with ``adaptive_k`` the 1 px rule at this resolution
    (its step widened by ``early_step_scale`` before ``early_views_fraction`` of the training)."""
    if not config.adaptive_k:
        return config.k
    step = config.max_step_px * (config.early_step_scale if fraction < config.early_views_fraction else 1.0)
    return views_for_span(exposure_px(d[0], d[1], focal, depth), step, config.k_min, config.k)


def _exposure_sampling(d: np.ndarray, frames: _Frames, frame: int, config: DeblurConfig,
                       fraction: float = 1.0) -> tuple[int, int]:
    """(virtual views, anchor renders) of one step on ``frame``'s exposure ``d`` (:func:`_views`, :func:`_anchors`;
    with ``odd_views`` an even count one higher where that interpolates no more views)."""
    focal, depth = frames.K[0, 0], frames.median_depth[frame]
    k = _views(d, focal, depth, config, fraction)
    anchors = _anchors(d, focal, depth, config, k)
    if config.odd_views and k % 2 == 0 and k < config.k:  # below k: adaptive; rendered views never qualify
        more = _anchors(d, focal, depth, config, k + 1)
        if warped_views(k + 1, more) <= warped_views(k, anchors):
            return k + 1, more
    return k, anchors


MAX_SKEW_MARGIN_SCALE = 4.0  # [ours] a rolling shutter widens the anchors' margin by at most this many warp_px


def warp_margin(config: DeblurConfig, shutter_px: float = 0.0) -> int:
    """[ours] Pixels added on each side of an anchor render (0 without ``warp_views``); ``shutter_px`` more
    for a rolling shutter's rows (:func:`rolling_shutter.readout_px`)."""
    return math.ceil(config.warp_px + shutter_px) + 2 if config.warp_views else 0


def _anchors(d: np.ndarray, focal: float, depth: float, config: DeblurConfig, k: int) -> int:
    """[ours] Anchor renders of one exposure with ``warp_views`` (0: render all k views): the fewest that
    leave every virtual view within ``warp_px`` of its anchor, ceil(span / (2 warp_px)), made odd so that one
    sits at mid-exposure (``deblur_model.anchor_count``)."""
    if not config.warp_views:
        return 0
    return anchor_count(k, math.ceil(exposure_px(d[0], d[1], focal, depth) / (2.0 * config.warp_px)))


def _phase(sequence: Sequence, sourced: np.ndarray | None, model: BlurScene, cache: dict[int, _Frames],
           scale: int) -> tuple[_Frames, BlurScene]:
    """[ours] Coarse-to-fine: the frames at resolution divisor ``scale`` (loaded once) and ``model``
    moved to that resolution (the same Gaussians, Adam moments and densification statistics)."""
    if scale not in cache:
        cache[scale] = _load_frames(sequence, scale, sourced)
    frames = cache[scale]
    height, width = frames.colors[0].shape[:2]
    if (model.width, model.height) != (width, height):
        moved = BlurScene(model.splats(), frames.K, width, height, sourced=frames.sourced,
                          warp_margin=model.warp_margin)
        moved.load_state(model.state())
        model = moved
    return frames, model


def nearest_filled(depth: np.ndarray) -> np.ndarray:
    """``depth`` with every 0 replaced by the nearest (L2) positive value; all zeros stay zeros."""
    valid = depth > 0
    if valid.all() or not valid.any():
        return depth
    _, labels = cv2.distanceTransformWithLabels((~valid).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    lookup = np.zeros(labels.max() + 1, depth.dtype)
    lookup[labels[valid]] = depth[valid]
    return lookup[labels]


def fill_uncovered(model: BlurScene, color: np.ndarray, depth: np.ndarray, cam_to_world: np.ndarray, K: np.ndarray,
                   stride: int, max_gaussians: int, rng: np.random.Generator, radius_px: float | None = None) -> int:
    """Add Gaussians where the render of a view has alpha < 0.5 (among the pixels the camera saw, if the
    model has a sourced mask): one per ``stride`` pixels (a random phase), coloured by the input, at
    the sensor depth, else the scene's rendered depth (alpha >= 0.5), else the nearest pixel's such
    depth; radius (sigma) ``radius_px`` pixels' footprint (default: the stride). Returns how many."""
    rendered, alpha = model.coverage(cam_to_world)
    known = np.where(depth > 0, depth, np.where(alpha >= 0.5, rendered, 0.0))
    grid = np.zeros(alpha.shape, bool)
    oy, ox = rng.integers(stride, size=2)
    grid[oy::stride, ox::stride] = True
    if model.sourced is not None:
        grid &= model.sourced
    v, u = np.nonzero((alpha < 0.5) & grid)
    room = max(max_gaussians - model.count, 0)
    if len(v) == 0 or room == 0 or not (known > 0).any():
        return 0
    if len(v) > room:
        keep = rng.choice(len(v), size=room, replace=False)
        v, u = v[keep], u[keep]
    z = nearest_filled(known)[v, u].astype(np.float64)
    points = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    model.add_gaussians(points @ cam_to_world[:3, :3].T + cam_to_world[:3, 3], color[v, u],
                        (radius_px or stride) * z / K[0, 0], opacity=0.5)
    return len(v)


def error_rows(model: BlurScene, frames: _Frames, train: list[int], exposures: Exposures, config: DeblurConfig,
               rng: np.random.Generator) -> np.ndarray:
    """[ours] The ``error_densify_share`` of the Gaussians with the most re-blur error mass
    (``BlurScene.error_mass``, summed over ``error_densify_frames`` random training views), most first."""
    mass = np.zeros(model.count)
    for f in rng.choice(train, size=min(config.error_densify_frames, len(train)), replace=False):
        d = exposures.offsets[f]
        k = _views(d, frames.K[0, 0], frames.median_depth[f], config)
        mass += model.error_mass(frames.colors[f], exposures.poses[f], d[0], d[1], k, exposures.colour(f))
    ranked = np.argsort(-mass, kind="stable")[: int(config.error_densify_share * model.count)]
    return ranked[mass[ranked] > 0]


def density_schedule(config: DeblurConfig, extent: float, width: int, centres: np.ndarray,
                     focal: float) -> DensitySchedule:
    """The config's density control in the policy's units (pixels, metres); ``centres`` and ``focal``
    (training cameras, this resolution) for ``split_px``."""
    # mean pixel gradient -> NDC gradient as 3DGS measures it (d ndc = 2 / W d pixel)
    threshold = np.inf if config.densify_by == "error" else config.densify_grad * 2.0 / width
    return DensitySchedule(config.densify_from, config.densify_until, config.densify_every, threshold,
                           config.split_scale * extent, config.prune_opacity, config.prune_scale * extent,
                           config.max_gaussians, config.reset_opacity_every, config.split_px, centres, focal)


def _rprop_step(shape: tuple[int, ...], rate: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Rprop's step starting at ``rate``; a zero rate (allowed for every ``lr_``) keeps the value, as Adam's does."""
    return Rprop(shape, rate).step if rate > 0 else (lambda value, grad: value)


def _test_fit_steps(config: DeblurConfig) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray],
                                                    Callable[[np.ndarray, np.ndarray], np.ndarray]]:
    """The held-out fit's (exposure step, colour step), each ``(value, loss gradient) -> value``, by
    ``config.test_fit``; the colour step adds the identity pull."""
    if config.test_fit == "rprop":
        exposure, colour = _rprop_step((2, 6), config.lr_test_pose), _rprop_step((3, 4), config.lr_colour_affine)
        return exposure, lambda M, grad: colour(M, grad + identity_penalty(M, config.lambda_colour_affine)[1])
    exposure_adam, colour_adam = RowAdam(1, (2, 6)), RowAdam(1, (3, 4))
    return (lambda d, grad: exposure_adam.step(0, d, grad, config.lr_test_pose),
            lambda M, grad: colour_step(colour_adam, M, grad, 0, config))


def _refine_test_exposure(model: BlurScene, frames: _Frames, base: np.ndarray, d: np.ndarray, fallback: np.ndarray,
                          frame: int, config: DeblurConfig,
                          readout_motion: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Fit a held-out frame's exposure offsets (and, with ``colour_affine``, its colour transform),
    scene frozen, by re-blurring against its blurred input (``config.test_fit``: Adam or Rprop); a rolling
    shutter's ``readout_motion`` as in :meth:`BlurScene.step`."""
    exposure_step, colour_step = _test_fit_steps(config)
    colour = IDENTITY.copy()
    frozen = None
    if config.warp_views and config.test_fit_refresh_px > 0:
        frozen = FrozenAnchors(config.test_fit_refresh_px, frames.K[0, 0], frames.median_depth[frame])
    guard = DivergenceGuard(f"stage 3 (deblur) test-view exposure of frame {frame}", np.zeros(3), np.inf)
    for it in range(config.test_pose_iterations):
        k, anchors = _exposure_sampling(d, frames, frame, config)
        step = model.step(frames.colors[frame], frames.depths[frame], base, d[0], d[1], k,
                          config.lambda_dssim, 0.0, rates=None, colour=colour if config.colour_affine else None,
                          anchors=anchors, fallback_depth=frames.median_depth[frame], frozen=frozen,
                          readout_motion=readout_motion)
        guard.check_step(it, sum(step.losses.values()), (step.grad_start, step.grad_end))
        d = shrink_mid(exposure_step(d, np.stack([step.grad_start, step.grad_end])), config.mid_exposure_decay)
        d = keep_open(d, fallback, config.min_open_px, frames.K[0, 0], frames.median_depth[frame])
        if config.colour_affine:
            colour = colour_step(colour, step.grad_colour)
    return d, colour


def _step_warnings(offsets: np.ndarray, train: list[int], frames: _Frames, config: DeblurConfig) -> list[str]:
    """A warning if adjacent virtual views move more than ``max_step_px`` (k is then too small)."""
    if config.k < 2:
        return []
    steps = [exposure_px(*offsets[i], frames.K[0, 0], frames.median_depth[i]) / (config.k - 1) for i in train]
    worst = int(np.argmax(steps))
    if steps[worst] <= config.max_step_px:
        return []
    needed = math.ceil(steps[worst] * (config.k - 1) / config.max_step_px) + 1
    return [f"adjacent virtual views move up to {steps[worst]:.2f} px (frame {train[worst]}) at the training "
            f"resolution, more than {config.max_step_px:g} px: k = {config.k} is likely too small for this blur "
            f"(--k {needed} keeps the steps under {config.max_step_px:g} px)"]


@dataclass(frozen=True)
class _Shutter:
    """[ours] Each frame's rolling-shutter readout motion (N, 6; zeros: a global shutter) and its median sensor
    depth (N,): where the skew is measured, and where a re-blurred render's rows are warped from a surface-less
    pixel."""

    motions: np.ndarray
    median_depth: np.ndarray

    def skew_px(self, focal: float, config: DeblurConfig) -> float:
        """The most any frame's first or last row lies from its pose on the image (:func:`readout_px`, pixels at
        focal ``focal``), at most ``MAX_SKEW_MARGIN_SCALE`` x ``warp_px``: a pose jump between neighbours must not
        blow up the anchors' margin."""
        skew = float(readout_skews(self.motions, focal, self.median_depth).max())
        return min(skew, MAX_SKEW_MARGIN_SCALE * config.warp_px)


def _write_outputs(stage_dir: Path, sequence: Sequence, splats: Splats, exposures: Exposures, result: DeblurResult,
                   config: DeblurConfig, sharpness: list[float], shift: FrameShift | None, shutter: _Shutter) -> None:
    colours = exposures.trained_colours()
    write_splats(stage_dir / "splats.ply", splats)
    if shift is not None:
        write_text(stage_dir / "frame.json", jsonout.dumps(shift.as_dict(), indent=2) + "\n")
    else:
        (stage_dir / "frame.json").unlink(missing_ok=True)
    write_tum(stage_dir / "trajectory.txt", sequence.timestamps, result.mid_poses,
              header="taichi-gs stage 3 (deblur), mid-exposure camera-to-world")
    write_text(stage_dir / "exposure.txt", _format_exposure(sequence.timestamps, result.exposure))
    write_text(stage_dir / "split.json", jsonout.dumps({"train": result.train, "test": result.test,
                                                     "holdout_every": config.holdout_every, "holdout": config.holdout,
                                                     "laplacian_variance": sharpness}, indent=2) + "\n")
    if colours is not None:
        write_text(stage_dir / "colour_affine.json", jsonout.dumps(
            {"rows": "out = M[:, :3] @ rgb + M[:, 3]", "frames": {n: colours[i].round(6).tolist()
                                                                  for i, n in enumerate(sequence.names)}}) + "\n")
    _write_renders(stage_dir, sequence, splats, exposures.poses, exposures.offsets, config, result.test, colours,
                   shutter)
    history = result.loss_history
    if history:
        it = np.array([h["iteration"] for h in history], dtype=float)
        line_plot(stage_dir / "loss.png", {"loss": (it, np.array([h["loss"] for h in history]))},
                  "stage 3: deblurring loss", "iteration", "loss", log_y=True)
    write_text(stage_dir / "history.json", jsonout.dumps(history) + "\n")


def _format_exposure(timestamps: np.ndarray, exposure: np.ndarray) -> str:
    """``timestamp`` then start and end poses as ``tx ty tz qx qy qz qw`` each, one frame a line."""
    starts = format_tum(timestamps, exposure[:, 0]).splitlines()
    ends = format_tum(timestamps, exposure[:, 1]).splitlines()
    lines = ["# timestamp start(tx ty tz qx qy qz qw) end(tx ty tz qx qy qz qw), camera-to-world"]
    lines += [f"{s} {e.split(maxsplit=1)[1]}" for s, e in zip(starts, ends)]
    return "\n".join(lines) + "\n"


def _write_renders(stage_dir: Path, sequence: Sequence, splats: Splats, poses: np.ndarray, offsets: np.ndarray,
                   config: DeblurConfig, test: list[int], colours: np.ndarray | None, shutter: _Shutter) -> None:
    """Full-resolution sharp mid-exposure, re-blurred and depth renders of every frame, and a grid;
    with per-frame ``colours`` the colour renders are in each frame's own colour (its transform applied).
    The sharp renders are global-shutter; the re-blurred ones read their rows as ``shutter`` does, and with a
    rolling shutter ``renders/as_read/`` holds the sharp render read so (each row at its mid-exposure pose)."""
    first = sequence.color(0)
    K = sequence.K()
    shutil.rmtree(stage_dir / "renders" / "as_read", ignore_errors=True)  # an earlier run's, with another readout
    skew = shutter.skew_px(K[0, 0], config)
    full = BlurScene(splats, K, first.shape[1], first.shape[0], warp_margin=math.ceil(skew) + 2 if skew > 0 else 0)
    scale = sequence.intrinsics.depth_scale
    rows, names = [], []
    has_truth = sequence.sharp_paths is not None
    grid_frames = set(_grid_frames(len(sequence), test, config.grid_frames))
    for i, name in enumerate(sequence.names):
        sharp, depth = full.render(virtual_pose(poses[i], *offsets[i], 0.5))
        reblurred = full.render_blurred(poses[i], offsets[i, 0], offsets[i, 1], config.k, shutter.motions[i],
                                        shutter.median_depth[i])
        as_read = None
        if shutter.motions[i].any():  # the sharp render as the rolling shutter reads it: rows at their own poses
            as_read = full.render_blurred(poses[i], offsets[i, 0], offsets[i, 1], 1, shutter.motions[i],
                                          shutter.median_depth[i])
        if colours is not None:
            sharp, reblurred = apply_affine(sharp, colours[i]), apply_affine(reblurred, colours[i])
            as_read = None if as_read is None else apply_affine(as_read, colours[i])
        write_png(stage_dir / "renders" / "sharp" / f"{name}.png", to_uint8(sharp))
        write_png(stage_dir / "renders" / "reblurred" / f"{name}.png", to_uint8(reblurred))
        if as_read is not None:
            write_png(stage_dir / "renders" / "as_read" / f"{name}.png", to_uint8(as_read))
        write_png(stage_dir / "renders" / "depth" / f"{name}.png", encode_depth(depth, scale))
        if i in grid_frames:
            rows.append([sequence.color(i), sharp] + ([sequence.sharp(i)] if has_truth else []))
            names.append(name)
    titles = ["blurred input", "deblurred (ours)"] + (["sharp ground truth"] if has_truth else [])
    image_grid(stage_dir / "grid.png", rows, titles, names, min_width=0)


def _grid_frames(n_frames: int, test: list[int], count: int) -> list[int]:
    """A few frames spread over the sequence, test views first when there are any."""
    pool = test or list(range(n_frames))
    picks = np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)
    return [pool[p] for p in sorted(set(picks))]


def _run_stage(context: StageContext) -> StageRun:
    with context.progress(STAGE.title, 1) as update:
        result = run_deblur(context.sequence, context.out, context.config, progress=update)
    return StageRun(result.summary(), [str(w) for w in result.warnings])


def _stage_inputs(out: Path, config: DeblurConfig, poses: Path | None, points: Path | None) -> StageInputs:
    return StageInputs(files={"poses": out / "refine" / "trajectory.txt", "splats": out / "refine" / "splats.ply"})


STAGE = StageDeclaration(
    name="deblur", title="stage 3: deblur", config_type=DeblurConfig, presets=PRESETS,
    outputs=("trajectory.txt", "exposure.txt", "splats.ply", "split.json"), run=_run_stage, inputs=_stage_inputs,
)
