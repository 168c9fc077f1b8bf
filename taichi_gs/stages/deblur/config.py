"""Stage 3's settings: every number of the deblur stage, its presets, and the schedule and cap a run
resolves from its training views and stage 2's Gaussians. Why each preset value is what it is:
docs/presets.md."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from ...validation import (
    ANY,
    COUNT,
    FRACTION,
    LEARNING_RATE,
    NON_NEGATIVE,
    OPTIONAL_COUNT,
    POSITIVE,
    Rule,
    at_least,
    one_of,
    setting,
    within,
)


@dataclass(frozen=True)
class DeblurConfig:
    """Every number stage 3 uses; defaults follow the method and 3DGS (`paper` preset)."""

    RELATIONS: ClassVar[tuple[tuple[str, Callable[[Any], bool]], ...]] = (
        ("densify_from must not exceed densify_until", lambda c: c.densify_from <= c.densify_until),
        ("readout_ms (a rolling shutter) needs warp_views = true", lambda c: c.readout_ms == 0 or c.warp_views),
    )

    k: int = setting(15, COUNT)  # virtual sharp views per exposure
    # one test view per h frames; 0 = train on all
    holdout_every: int = setting(3, Rule((lambda v: v == 0 or v >= 2), "0 (no test views) or at least 2"))
    # "every": frames 1, 1 + h, ...; "sharpest": the sharpest of each h frames (real data)
    holdout: str = setting("every", one_of("every", "sharpest"))
    iterations: int = setting(30000, COUNT)
    lambda_dssim: float = setting(0.2, FRACTION)  # l_B
    lambda_depth: float = setting(0.1, NON_NEGATIVE)  # l_D
    sh_degree: int = setting(3, one_of(0, 1, 2, 3))
    lr_means: float = setting(1.6e-4, LEARNING_RATE)  # times the scene extent, decayed to lr_means_final
    lr_means_final: float = setting(1.6e-6, LEARNING_RATE)
    lr_colors: float = setting(0.0025, LEARNING_RATE)
    lr_opacity: float = setting(0.05, LEARNING_RATE)
    lr_scales: float = setting(0.005, LEARNING_RATE)
    lr_quats: float = setting(0.001, LEARNING_RATE)
    lr_exposure: float = setting(1e-3, LEARNING_RATE)  # Adam on the se(3) offsets, decayed to lr_exposure_final
    lr_exposure_final: float = setting(1e-4, LEARNING_RATE)
    # exposures stay at their start for this many iterations (the scene settles first)
    exposure_from: int = setting(0, OPTIONAL_COUNT)
    # offsets start at +-half this share of the motion to the neighbours
    initial_exposure_fraction: float = setting(0.5, FRACTION)
    min_open_px: float = setting(0.25, NON_NEGATIVE)  # exposures narrower than this on the image are re-opened to it
    max_step_px: float = setting(1.0, POSITIVE)  # warn when adjacent virtual views move more than this
    densify_from: int = setting(500, OPTIONAL_COUNT)
    densify_until: int = setting(15000, OPTIONAL_COUNT)
    densify_every: int = setting(100, COUNT)
    densify_grad: float = setting(0.0002, POSITIVE)  # 3DGS's threshold on the mean NDC positional gradient
    split_scale: float = setting(0.01, POSITIVE)  # clone below, split above this share of the scene extent
    prune_opacity: float = setting(0.005, FRACTION)
    prune_scale: float = setting(0.1, POSITIVE)  # drop Gaussians larger than this share of the scene extent
    max_gaussians: int = setting(2_000_000, COUNT)
    # [ours] the cap is at least this multiple of the Gaussians stage 2 hands over (0: max_gaussians alone), so
    # that a scene handed over above max_gaussians still densifies and fills its holes
    densify_headroom: float = setting(0.0, NON_NEGATIVE)
    reset_opacity_every: int = setting(3000, OPTIONAL_COUNT)  # 0 = never
    # test-time exposure refinement per held-out frame; 0 = off
    test_pose_iterations: int = setting(100, OPTIONAL_COUNT)
    lr_test_pose: float = setting(1e-3, LEARNING_RATE, POSITIVE)  # Adam's rate, or Rprop's first step
    # [ours] optimiser of the held-out fits: "adam" (the method's) or "rprop" (per-coordinate step sizes
    # from the gradient's sign history: the same deterministic loss every step, so fewer steps to converge)
    test_fit: str = setting("adam", one_of("adam", "rprop"))
    # [ours] a held-out frame's fit starts from the mid-exposure correction its training neighbours learned
    # (the mean of (d_s + d_e) / 2 of the nearest training frame on each side), not from its stage-2 pose
    test_fit_from_neighbours: bool = False
    # [ours] with warp_views, a held-out fit keeps its anchor renders across steps and warps every step's views
    # from them (no rasterizer pass while only the exposure moves), rendering them again once one would move
    # more than this many pixels (0: render the anchors at every step, as training does)
    test_fit_refresh_px: float = setting(0.0, NON_NEGATIVE)
    # [ours] weight of a depth term in the held-out fits: the masked depth L1 against the frame's depth of a render
    # at the pose that depth shows (exposures.DepthMoments: mid-exposure's, moved by the frame's velocity times the
    # depth's own time offset where the input gives one); 0: colour alone (the method's)
    test_fit_lambda_depth: float = setting(0.0, NON_NEGATIVE)
    # [ours] a held-out fit also bows its exposure's path (geometry.exposure_twist: 4 tau (1 - tau) bend, largest at
    # mid-exposure): a hand-held camera's path over a long exposure curves, and the centre frame lies on the curve,
    # not on the straight chord between the exposure's ends. The bow's image travel is kept to at most this share
    # of the exposure's (exposures.capped_bend); 0: a straight exposure (the method's)
    test_fit_bend: float = setting(0.0, NON_NEGATIVE)
    resolution_scale: int = setting(1, COUNT)  # train at 1/scale of the input resolution; outputs are full size
    seed: int = setting(0, ANY)
    checkpoint_every: int = setting(1000, COUNT)
    # [ours] a trained affine colour transform (3 x 4) per frame on the re-blurred render (exposure and
    # white-balance changes of real cameras), pulled to identity by lambda_colour_affine |M - I|^2
    colour_affine: bool = False
    lr_colour_affine: float = setting(0.005, LEARNING_RATE)
    lambda_colour_affine: float = setting(0.01, NON_NEGATIVE)
    # [ours] schedule: iterations = max(iterations, iterations_per_view x training views), with the
    # densification and exposure windows stretched alike (0 = fixed iterations)
    iterations_per_view: int = setting(0, OPTIONAL_COUNT)
    epoch_sampling: bool = False  # [ours] visit training views in shuffled epochs instead of at random
    # [ours] at each densification, in fill_frames random training views, add a Gaussian every
    # fill_stride pixels where the render's alpha is below 0.5 (no Gaussians: depth holes of the
    # sensor), at the view's sensor depth, else the scene's rendered depth, else the nearest such depth
    fill_uncovered: bool = False
    fill_frames: int = setting(2, COUNT)
    fill_stride: int = setting(2, COUNT)
    # [ours] splat footprint: before training, split Gaussians wider (largest sigma) than init_max_px
    # pixels at the training resolution, seen from the nearest training camera (stage 2's fixed-size
    # Gaussians are wider than the blur at 320x240); during densification, split instead of clone
    # those wider than split_px pixels (0 = off: 3DGS's world-size rule split_scale alone)
    init_max_px: float = setting(0.0, ANY)
    split_px: float = setting(0.0, ANY)
    grid_frames: int = setting(4, OPTIONAL_COUNT)
    # [ours] coarse-to-fine: the first coarse_fraction of the iterations train at 1/coarse_scale, then
    # 1/(coarse_scale/2), ... 1/2 of the training resolution (equal shares; 1 = off), the rest at it
    coarse_scale: int = setting(1, COUNT)
    coarse_fraction: float = setting(0.0, FRACTION)
    # [ours] k per exposure: each step renders the fewest views (k_min..k) whose neighbours lie at most
    # max_step_px apart at the resolution trained (the 1 px rule per frame and phase); off: always k
    adaptive_k: bool = False
    k_min: int = setting(3, COUNT)
    # [ours] fewer views while the scene is soft: for the first early_views_fraction of the iterations,
    # adaptive k allows early_step_scale x max_step_px between neighbouring views (0 = off)
    early_views_fraction: float = setting(0.0, FRACTION)
    early_step_scale: float = setting(2.0, at_least(1.0))
    # [ours] keep the Gaussians in Morton order of their centres in memory (at the start and after every
    # densification and fill): the same scene, fewer cache misses in the per-tile work
    spatial_order: bool = False
    # [ours] photometric losses over the pixels the camera saw only (``Sequence.sourced_pixels``): an
    # undistorted frame's unsourced border holds copies of its edge that no scene explains
    sourced_pixels_only: bool = False
    # [ours] which Gaussians densification grows: "gradient" (3DGS: mean positional gradient above
    # densify_grad), "error" (the error_densify_share of them that carry the most re-blur error: blending
    # weight x absolute error, summed over error_densify_frames random training views) or "both" (the
    # error's after the gradient's)
    densify_by: str = setting("gradient", one_of("gradient", "error", "both"))
    error_densify_share: float = setting(0.05, FRACTION)
    error_densify_frames: int = setting(4, COUNT)
    # [ours] after the last densification, drop the Gaussians of least blending weight (summed over the training
    # views' sharp mid-exposure renders: LightGaussian's global significance) that together make at most this
    # share of the images; the rest of the run trains and renders fewer Gaussians (0 = off). 0.01: 27-35% fewer
    # Gaussians, -0.04 to -0.07 dB held-out, 0.91-0.95x the stage-3 time (docs/notebook/benchmarks-2026-11.md,
    # "Significance pruning")
    prune_weight_share: float = setting(0.0, FRACTION)
    # [ours] warped virtual views: render only the fewest anchor views (padded by warp_px + 2 pixels; an odd
    # number, one at mid-exposure) that leave every virtual view within warp_px of one, and make the k views
    # by warping the anchors' renders through their depth (exact for rotations; disocclusions of
    # translations are approximated). 12 px: docs/notebook/benchmarks-2026-11.md, "One anchor at mid-exposure"
    warp_views: bool = False
    warp_px: float = setting(12.0, within(0.5, 64))
    # [ours] with warp_views and adaptive_k, an even count of views is raised by one (within k) where that
    # interpolates no more views: the added view puts one at each odd group's anchor pose, which the warp
    # reads instead of interpolating, so the exposure is sampled more finely at the same cost
    # (docs/notebook/benchmarks-2026-11.md, "Odd view counts")
    odd_views: bool = False
    # [ours] after training (and the held-out fits), move the scene and every exposure by the scale and
    # translation that map the training frames' mid-exposure centres back onto stage 2's (stages/gauge.py):
    # colour leaves that gauge free and the depth term lets it drift. The scale moves only where the fit
    # determines it to keep_frame_scale_error (standard error), else the translation alone. Colour renders are
    # unchanged; OUT/deblur/frame.json records the move.
    keep_frame: bool = False
    keep_frame_scale_error: float = setting(0.001, NON_NEGATIVE)
    # [ours] after every update of an exposure (training and held-out fits), its mid-exposure offset (d_s + d_e) / 2
    # shrinks by this share towards stage 2's pose, its span unchanged: 0 leaves it free (the method), 1 pins every
    # mid-exposure pose at stage 2's (the exposures learn their spans only)
    mid_exposure_decay: float = setting(0.0, FRACTION)
    # [ours] a rolling shutter: the colour camera reads its rows top to bottom over readout_ms milliseconds
    # (0: a global shutter, the method). Each virtual view's rows are then warped from the anchors at the poses
    # where they were read, along each frame's velocity from its neighbours in the trajectory
    # (``rolling_shutter``); needs warp_views. The sharp renders and "error" densification stay global-shutter.
    # camera_readout: with readout_ms 0 and warp_views, the readout of a camera the sequence's reading names
    # where it is known (``io.readout.KNOWN_READOUT_MS``: TUM fr1, 7-Scenes), else 0
    readout_ms: float = setting(0.0, NON_NEGATIVE)
    camera_readout: bool = False
    # [ours] with a readout, the depth frames are de-skewed to their frames' poses (rolling_shutter.DeskewedSequence,
    # each frame's motion from stage 2's poses), so that the depth loss and fill_uncovered, which use
    # global-shutter renders at the mid-exposure pose, meet depth as a global shutter would read it.
    # false: depth as read
    deskew_depth: bool = True



# paper: the method (every addition of ours off). fast: CPU-sized, ours on; each value's measured reason is a row
# of docs/presets.md.
PRESETS = {
    "paper": DeblurConfig(),
    "fast": DeblurConfig(k=9, max_step_px=2.0, iterations=840, sh_degree=0, lr_colors=0.02, densify_from=70,
                         densify_until=315, densify_every=70, max_gaussians=100_000, reset_opacity_every=0,
                         lr_exposure=2e-3, exposure_from=84, checkpoint_every=100, colour_affine=True,
                         fill_uncovered=True, epoch_sampling=True, adaptive_k=True, iterations_per_view=80,
                         test_pose_iterations=20, test_fit="rprop", test_fit_refresh_px=1.0,
                         test_fit_from_neighbours=True, spatial_order=True, early_views_fraction=0.3,
                         warp_views=True, odd_views=True, densify_headroom=1.3, keep_frame=True,
                         initial_exposure_fraction=0.7, camera_readout=True, test_fit_lambda_depth=1.0),
}


def with_headroom(config: DeblurConfig, handed_over: int) -> DeblurConfig:
    """``config`` with ``max_gaussians`` raised to ``densify_headroom`` x the ``handed_over`` Gaussians when
    that is more."""
    wanted = math.ceil(config.densify_headroom * handed_over)
    return config if wanted <= config.max_gaussians else dataclasses.replace(config, max_gaussians=wanted)


def scaled_schedule(config: DeblurConfig, n_train: int) -> DeblurConfig:
    """``config`` with ``iterations`` raised to ``iterations_per_view`` x ``n_train`` when that is more,
    and the iteration counts of its densification and exposure windows scaled by the same factor."""
    wanted = config.iterations_per_view * n_train
    if wanted <= config.iterations:
        return config
    factor = wanted / config.iterations
    return dataclasses.replace(
        config, iterations=wanted, densify_from=round(config.densify_from * factor),
        densify_until=round(config.densify_until * factor), densify_every=max(1, round(config.densify_every * factor)),
        exposure_from=round(config.exposure_from * factor), iterations_per_view=0)
