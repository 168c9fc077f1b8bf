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

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ... import profiling
from ...errors import InputError
from ...io.sequence import Sequence
from ...photometric import IDENTITY, identity_penalty
from ...rolling_shutter import (
    DeskewedSequence,
    deskewing_motions,
    readout_motions,
    stage_readout_ms,
)
from ...splats import Splats
from .. import checkpoint
from ..declaration import StageContext, StageDeclaration, StageInputs, StageRun
from ..divergence import DivergenceGuard
from ..row_adam import RowAdam
from ..schedule import exp_decay, training_scale, views_for_span
from .config import PRESETS, DeblurConfig, scaled_schedule, with_headroom
from .density import density_schedule, fill_uncovered
from .density_control import DensitySchedule, footprint_limit
from .exposures import (
    DepthMoments,
    Exposures,
    capped_bend,
    colour_step,
    exposure_px,
    keep_open,
    shrink_mid,
    velocity_twists,
)
from .frames import (
    _Frames,
    _load_frames,
    _phase,
    _scene_extent,
    _Shutter,
    choose_split,
    load_stage2,
    loss_mask,
    training_frame,
    with_sh_degree,
)
from .gauge import back_to_stage_2s_frame, scaled_twists
from .model import (
    BlurScene,
    BlurStep,
    FrozenAnchors,
    Rates,
    anchor_count,
    warped_views,
)
from .outputs import DeblurResult, _step_warnings, _write_outputs
from .rprop import Rprop

PARAMETER_CHECK_EVERY = 50  # iterations between divergence checks of the parameters (a device copy)
MAX_SKEW_MARGIN_SCALE = 4.0  # [ours] a rolling shutter widens the anchors' margin by at most this many warp_px


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
    splats = with_sh_degree(splats, config.sh_degree)
    extent = _scene_extent(poses, splats.means)
    shutter = _Shutter(motions, frames.median_depth, MAX_SKEW_MARGIN_SCALE * config.warp_px)
    centres = poses[train, :3, 3]
    model = _initial_model(splats, frames, centres, shutter, config)
    exposures = Exposures(poses, config)
    rng = np.random.default_rng(config.seed)
    checkpoint_path = stage_dir / "checkpoint.npz"
    first, history = _resume(checkpoint_path, config, exposures, model, rng)

    guard = DivergenceGuard("stage 3 (deblur)", splats.means.mean(axis=0), extent)
    full, phase = frames, {config.resolution_scale: frames}
    t0 = time.perf_counter()
    for it in range(first, config.iterations):
        fraction = it / max(config.iterations - 1, 1)
        # sample: the phase's resolution (coarse-to-fine), the frame, and the density schedule in its pixels
        scale = training_scale(it, config.iterations, config.resolution_scale, config.coarse_scale,
                               config.coarse_fraction)
        frames, model = _phase(sequence, sourced, model, phase, scale, depth_source)
        frame = training_frame(train, it, rng, config.seed, config.epoch_sampling)
        density = density_schedule(config, extent, model.width, centres, frames.K[0, 0])
        # step: the scene's Adam step on the frame's re-blurred render
        step = _train_step(model, frames, frame, exposures, config, fraction, extent, density.observes(it + 1),
                           shutter.motions[frame])
        guard.check_step(it, sum(step.losses.values()), (step.grad_start, step.grad_end))
        # update: the frame's exposure and colour, once the scene has settled
        if it >= config.exposure_from:
            lr_exposure = exp_decay(config.lr_exposure, config.lr_exposure_final, fraction)
            exposures.update(frame, step.grad_start, step.grad_end, step.grad_colour, lr_exposure, full.K[0, 0],
                             full.median_depth[frame])
        loss = (1 - config.lambda_dssim) * step.losses["l1"] + config.lambda_dssim * step.losses["dssim"] \
            + config.lambda_depth * step.losses["depth"]
        if (it + 1) % 10 == 0 or it == config.iterations - 1:
            history.append({"iteration": it + 1, "loss": loss, "psnr": step.psnr, **step.losses, "gaussians": model.count})
        # density: densify and prune, fill, drop the lightest, reorder
        _densify(model, density, it + 1, frames, train, exposures, config, rng)
        if progress is not None:
            progress(it + 1, config.iterations, loss=loss, psnr=step.psnr, gaussians=model.count)
        # checkpoint: the parameters checked, the state saved
        if (it + 1) % PARAMETER_CHECK_EVERY == 0 or (it + 1) % config.checkpoint_every == 0 \
                or it == config.iterations - 1:
            params = model.arrays()
            guard.check_parameters(it, params["means"], exposures.offsets, *params.values())
        if (it + 1) % config.checkpoint_every == 0 and it + 1 < config.iterations:
            checkpoint.save(checkpoint_path, it + 1, config,
                            {**exposures.state(), **checkpoint.prefixed("model", model.state())},
                            {"history": history, "rng": rng.bit_generator.state})
    seconds = (time.perf_counter() - t0) / max(config.iterations - first, 1)

    frames, model = _phase(sequence, sourced, model, phase, config.resolution_scale, depth_source)
    depth_moments = DepthMoments(velocity_twists(poses, sequence.timestamps), sequence.depth_offsets())
    for frame in test:
        if config.test_fit_from_neighbours:
            exposures.start_from_neighbours(frame, train)
        exposures.offsets[frame], exposures.colours[frame], exposures.bends[frame] = _refine_test_exposure(
            model, frames, poses[frame], exposures.offsets[frame], exposures.start[frame], frame, config,
            shutter.motions[frame], depth_moments)
    warnings = _step_warnings(exposures.offsets, train, frames, config)
    splats, shift = model.splats(), None
    if config.keep_frame:
        splats, exposures.poses, exposures.offsets, shift = back_to_stage_2s_frame(
            splats, poses, exposures.offsets, train, config.keep_frame_scale_error)
        exposures.bends = scaled_twists(exposures.bends, shift.scale)
    result = DeblurResult(
        mid_poses=np.stack(exposures.mid_poses()), exposure=exposures.ends(),
        train=train, test=test, loss_history=history, gaussians=model.count, seconds_per_iteration=seconds,
        warnings=warnings, readout_ms=readout_ms,
    )
    _write_outputs(stage_dir, sequence, splats, exposures, result, config, sharpness, shift, shutter)
    checkpoint_path.unlink(missing_ok=True)
    return result


def _initial_model(splats: Splats, frames: _Frames, centres: np.ndarray, shutter: _Shutter,
                   config: DeblurConfig) -> BlurScene:
    """The trainable scene at training resolution; with ``init_max_px`` its Gaussians wider than that seen from
    the nearest training camera (``centres``) split, with ``spatial_order`` in Morton order."""
    height, width = frames.colors[0].shape[:2]
    model = BlurScene(splats, frames.K, width, height, sourced=frames.sourced,
                      warp_margin=warp_margin(config, shutter.skew_px(frames.K[0, 0])))
    if config.init_max_px > 0:
        limit = footprint_limit(model.arrays()["means"], centres, frames.K[0, 0], config.init_max_px)
        model.density.split_oversized(model.store, limit, config.max_gaussians, np.random.default_rng([config.seed, 1]))
    if config.spatial_order:
        model.order_in_space()
    return model


def _resume(path: Path, config: DeblurConfig, exposures: Exposures, model: BlurScene,
            rng: np.random.Generator) -> tuple[int, list[dict[str, float]]]:
    """(first iteration, loss history) of a run: a checkpoint's made with ``config`` (the exposures, the
    scene and the RNG restored from it), else (0, [])."""
    saved = checkpoint.load(path, config)
    if saved is None or not exposures.matches(saved.arrays):
        return 0, []
    exposures.load_state(saved.arrays)
    model.load_state(saved.prefixed("model"))
    rng.bit_generator.state = saved.records["rng"]
    return saved.iteration, saved.records["history"]


def _train_step(model: BlurScene, frames: _Frames, frame: int, exposures: Exposures, config: DeblurConfig,
                fraction: float, extent: float, observe: bool, readout_motion: np.ndarray) -> BlurStep:
    """One training step on ``frame`` at ``fraction`` of the run: its exposure's views sampled
    (:func:`_exposure_sampling`), the scene's parameters stepped at their rates (the means' decayed and
    in units of the scene ``extent``), the exposure's and colour's gradients returned."""
    rates = Rates(means=exp_decay(config.lr_means, config.lr_means_final, fraction) * extent,
                  quats=config.lr_quats, log_scales=config.lr_scales, opacity_logits=config.lr_opacity,
                  colors=config.lr_colors)
    d = exposures.offsets[frame]
    k, anchors = _exposure_sampling(d, frames, frame, config, fraction)
    return model.step(frames.colors[frame], frames.depths[frame], exposures.poses[frame], d[0], d[1], k,
                      config.lambda_dssim, config.lambda_depth, rates, exposures.colour(frame), anchors=anchors,
                      fallback_depth=frames.median_depth[frame], observe=observe, readout_motion=readout_motion)


def _densify(model: BlurScene, density: DensitySchedule, done: int, frames: _Frames, train: list[int],
             exposures: Exposures, config: DeblurConfig, rng: np.random.Generator) -> None:
    """Density control after ``done`` iterations: 3DGS's (and [ours] ``densify_by`` error's) growth and
    pruning, [ours] ``fill_uncovered``, ``prune_weight_share`` after the last densification, and
    ``spatial_order``."""
    also = None
    if config.densify_by != "gradient" and density.densifies(done):
        also = error_rows(model, frames, train, exposures, config, rng)
    model.density.step(done, model.store, density, rng, also)
    if config.fill_uncovered and density.densifies(done):
        for f in rng.choice(train, size=min(config.fill_frames, len(train)), replace=False):
            fill_uncovered(model, frames.colors[f], frames.depths[f], exposures.mid_pose(f), frames.K,
                           config.fill_stride, config.max_gaussians, rng,
                           min(config.fill_stride, config.split_px or config.fill_stride))
    if config.prune_weight_share > 0 and density.last_densification(done):
        weights = model.blending_weights(exposures.mid_poses(train))
        model.density.drop_lightest(model.store, weights, config.prune_weight_share)
    if config.spatial_order and density.densifies(done):
        model.order_in_space()


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



def warp_margin(config: DeblurConfig, shutter_px: float = 0.0) -> int:
    """[ours] Pixels added on each side of an anchor render (0 without ``warp_views``); ``shutter_px`` more
    for a rolling shutter's rows (:func:`rolling_shutter.readout_px`)."""
    return math.ceil(config.warp_px + shutter_px) + 2 if config.warp_views else 0


def _anchors(d: np.ndarray, focal: float, depth: float, config: DeblurConfig, k: int) -> int:
    """[ours] Anchor renders of one exposure with ``warp_views`` (0: render all k views): the fewest that
    leave every virtual view within ``warp_px`` of its anchor, ceil(span / (2 warp_px)), made odd so that one
    sits at mid-exposure (``model.anchor_count``)."""
    if not config.warp_views:
        return 0
    return anchor_count(k, math.ceil(exposure_px(d[0], d[1], focal, depth) / (2.0 * config.warp_px)))


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


def _rprop_step(shape: tuple[int, ...], rate: float) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """Rprop's step starting at ``rate``; a zero rate (allowed for every ``lr_``) keeps the value, as Adam's does."""
    return Rprop(shape, rate).step if rate > 0 else (lambda value, grad: value)


def _test_fit_steps(config: DeblurConfig) -> tuple[Callable[[np.ndarray, np.ndarray], np.ndarray], ...]:
    """The held-out fit's (exposure step, bend step, colour step), each ``(value, loss gradient) -> value``, by
    ``config.test_fit``; the bend steps at the exposure's rate, the colour step adds the identity pull."""
    if config.test_fit == "rprop":
        exposure, bend = _rprop_step((2, 6), config.lr_test_pose), _rprop_step((6,), config.lr_test_pose)
        colour = _rprop_step((3, 4), config.lr_colour_affine)
        return exposure, bend, lambda M, grad: colour(M, grad + identity_penalty(M, config.lambda_colour_affine)[1])
    exposure_adam, bend_adam, colour_adam = RowAdam(1, (2, 6)), RowAdam(1, (6,)), RowAdam(1, (3, 4))
    return (lambda d, grad: exposure_adam.step(0, d, grad, config.lr_test_pose),
            lambda b, grad: bend_adam.step(0, b, grad, config.lr_test_pose),
            lambda M, grad: colour_step(colour_adam, M, grad, 0, config))


@profiling.timed("test-view exposure fits")
def _refine_test_exposure(model: BlurScene, frames: _Frames, base: np.ndarray, d: np.ndarray, fallback: np.ndarray,
                          frame: int, config: DeblurConfig, readout_motion: np.ndarray | None = None,
                          depth_moments: DepthMoments | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fit a held-out frame's exposure offsets (and, with ``colour_affine``, its colour transform; [ours] with
    ``test_fit_bend``, its path's bow, :func:`capped_bend`), scene frozen, by re-blurring against its blurred input
    (``config.test_fit``: Adam or Rprop); a rolling shutter's ``readout_motion`` as in :meth:`BlurScene.step`.
    With ``test_fit_lambda_depth``, the frame's depth pins the pose it shows (``depth_moments``; None:
    mid-exposure's). Returns (offsets, colour transform, bend)."""
    exposure_fit, bend_fit, colour_fit = _test_fit_steps(config)
    colour, bend = IDENTITY.copy(), np.zeros(6)  # the bend stays straight unless test_fit_bend fits it
    frozen = None
    if config.warp_views and config.test_fit_refresh_px > 0:
        frozen = FrozenAnchors(config.test_fit_refresh_px, frames.K[0, 0], frames.median_depth[frame])
    guard = DivergenceGuard(f"stage 3 (deblur) test-view exposure of frame {frame}", np.zeros(3), np.inf)
    shift = np.zeros(6) if depth_moments is None else depth_moments.shift(frame)
    for it in range(config.test_pose_iterations):
        k, anchors = _exposure_sampling(d, frames, frame, config)
        step = model.step(frames.colors[frame], frames.depths[frame], base, d[0], d[1], k,
                          config.lambda_dssim, 0.0, rates=None, colour=colour if config.colour_affine else None,
                          anchors=anchors, fallback_depth=frames.median_depth[frame], frozen=frozen,
                          readout_motion=readout_motion, bend=bend)
        loss, grad, grad_bend = sum(step.losses.values()), np.stack([step.grad_start, step.grad_end]), step.grad_bend
        if config.test_fit_lambda_depth > 0:
            depth_loss, g_start, g_end, g_bend = model.depth_instant_step(
                frames.depths[frame], base, d[0], d[1], shift, config.test_fit_lambda_depth, bend)
            loss, grad, grad_bend = loss + depth_loss, grad + np.stack([g_start, g_end]), grad_bend + g_bend
        guard.check_step(it, loss, grad)
        d = shrink_mid(exposure_fit(d, grad), config.mid_exposure_decay)
        d = keep_open(d, fallback, config.min_open_px, frames.K[0, 0], frames.median_depth[frame])
        if config.test_fit_bend > 0:
            bend = capped_bend(bend_fit(bend, grad_bend), d, config.test_fit_bend, frames.K[0, 0],
                               frames.median_depth[frame])
        if config.colour_affine:
            colour = colour_fit(colour, step.grad_colour)
    return d, colour, bend


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
