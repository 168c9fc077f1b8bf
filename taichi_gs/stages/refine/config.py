"""Stage 2's settings: every number of the refine stage and its presets."""

from __future__ import annotations

from dataclasses import dataclass

from ...validation import ANY, COUNT, FRACTION, LEARNING_RATE, NON_NEGATIVE, OPTIONAL_COUNT, POSITIVE, setting, within


@dataclass(frozen=True)
class RefineConfig:
    """Every number stage 2 uses; defaults follow the method (`paper` preset)."""

    voxel_size: float = setting(0.0, NON_NEGATIVE)  # s in metres; 0 = take the voxel size stage 1 used
    initial_opacity: float = setting(0.5, within(0.01, 0.99))
    # iterations = iterations_per_frame x N; [ours] 0 hands stage 1's poses and fused cloud (Gaussians of the
    # initial scale and opacity) to stage 3 untrained
    iterations_per_frame: int = setting(600, OPTIONAL_COUNT)
    prune_every_per_frame: int = setting(100, COUNT)
    reset_every_per_frame: int = setting(200, COUNT)
    prune_opacity: float = setting(0.8, FRACTION)
    lambda_depth: float = setting(1.0, NON_NEGATIVE)
    # mean (1 - alpha) where the input has depth: keeps the surface closed
    lambda_coverage: float = setting(0.3, NON_NEGATIVE)
    lambda_opacity: float = setting(0.1, NON_NEGATIVE)
    min_alpha: float = setting(0.5, within(0.01, 1))  # depth loss on D / alpha where the render's alpha reaches this
    views_per_step: int = setting(1, COUNT)  # training cameras rendered per iteration (gradients averaged)
    lr_means: float = setting(5e-4, LEARNING_RATE)  # times the scene extent, decayed to lr_means_final
    lr_means_final: float = setting(5e-6, LEARNING_RATE)
    lr_opacity: float = setting(0.05, LEARNING_RATE)
    free_scale: bool = False  # ablation: also train anisotropic scales and rotations
    lr_log_scales: float = setting(0.005, LEARNING_RATE)
    lr_quats: float = setting(0.001, LEARNING_RATE)
    # [ours] translation step (m) of the per-frame Adam, decayed to lr_pose_final. Adam moves each component by about
    # lr per step whatever the gradient's size, so lr sets how far a pose wanders on the depth loss's flat directions:
    # it must start below the error of the poses it refines. Stage 1's verified, graph-optimised poses are at the
    # millimetre level, hence 0.1 mm (1e-2, the earlier default, moved exact poses 2-5 mm; raise it for poor starts).
    lr_pose: float = setting(1e-4, LEARNING_RATE)
    lr_pose_final: float = setting(1e-6, LEARNING_RATE)
    # rotation lr (rad) per translation lr (m): ~1 / scene depth
    pose_rotation_per_m: float = setting(0.5, NON_NEGATIVE)
    pose_warmup_fraction: float = setting(0.1, FRACTION)  # poses stay fixed for this first part of the schedule
    # [ours] pose prior: + w/2 (|e_t / sigma_t|^2 + |e_r / sigma_r|^2), e = log(initial^-1 pose) in the camera
    # frame, pulling each pose towards stage 1's; w in metres (0.003: at one sigma the prior pulls about as
    # hard as the depth L1 of a fronto-parallel view). 0 = off (the method).
    pose_prior_weight: float = setting(0.0, NON_NEGATIVE)
    pose_prior_sigma_m: float = setting(0.003, POSITIVE)
    pose_prior_sigma_deg: float = setting(0.1, POSITIVE)
    # [ours] acceptance test (stages/refine/accept.py): the refined trajectory is kept only if stage 1's depth + colour
    # verification score, averaged over every (i, j) with 0 < i - j <= accept_neighbours, is not higher than for the
    # initial poses; otherwise those are returned. 0 = off (the method: the refined poses are always kept).
    accept_neighbours: int = setting(3, OPTIONAL_COUNT)
    resolution_scale: int = setting(1, COUNT)  # render at 1/scale of the input resolution
    seed: int = setting(0, ANY)
    checkpoint_every: int = setting(500, COUNT)
    max_depth: float = setting(0.0, NON_NEGATIVE)  # ignore input depth beyond this (0 = keep all)
    # ignore input depth within edge_radius px of a relative step above this (0 = keep)
    edge_ratio: float = setting(0.05, NON_NEGATIVE)
    edge_radius: int = setting(2, OPTIONAL_COUNT)
    # [ours] stop when converged: every converge_window_per_frame x N iterations (0 = off: the fixed
    # count), stop once the window's mean depth L1 changed by at most converge_rel_tol of the window
    # before and no camera moved more than converge_pose_m / converge_pose_deg since the last check
    # (never within two windows after an opacity reset); iterations_per_frame stays the cap
    converge_window_per_frame: int = setting(0, OPTIONAL_COUNT)
    converge_rel_tol: float = setting(0.02, NON_NEGATIVE)
    converge_pose_m: float = setting(0.0005, NON_NEGATIVE)
    converge_pose_deg: float = setting(0.05, NON_NEGATIVE)
    spatial_order: bool = False  # [ours] Gaussians in Morton order of their centres (memory layout only)
    # [ours] a rolling shutter, as stage 1's readout_ms and camera_readout: when it trains, stage 2 fits the
    # Gaussians to depth (and tests its poses on frames) de-skewed to each frame's pose, each frame's motion over
    # its readout taken from the initial poses (rolling_shutter.DeskewedSequence). 0: a global shutter
    readout_ms: float = setting(0.0, NON_NEGATIVE)
    camera_readout: bool = False


FAST_TRAINING_PER_FRAME = 60  # iterations_per_frame of the fast preset's schedule when stage 2 trains (not by default)

PRESETS = {
    # the method: every pose kept (no acceptance test), no coverage term, depth edges not masked
    "paper": RefineConfig(accept_neighbours=0, lambda_coverage=0.0, edge_ratio=0.0),
    # [ours] CPU-sized: stage 2 hands stage 1's poses and fused cloud to stage 3 untrained. Its 60 N iterations (the
    # schedule below, with iterations_per_frame = FAST_TRAINING_PER_FRAME) took 30% of the sample's run, and the
    # refined poses never passed the acceptance test in the fast preset; stage 3 from the untrained cloud scored
    # -0.05 to +0.21 dB held-out on five synthetic and real sequences, the sample in 0.91x the time
    # (docs/notebook/benchmarks-2026-11.md, "Stage 3 straight from stage 1's cloud")
    "fast": RefineConfig(iterations_per_frame=0, prune_every_per_frame=20, reset_every_per_frame=40,
                         checkpoint_every=200, spatial_order=True, camera_readout=True),
}
