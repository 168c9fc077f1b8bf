"""Config values checked before any work starts: types come from the dataclasses (``config.py``),
ranges, choices and relations between fields from the rules here.

Every float must be finite; every learning rate (``lr_*``) must lie in [0, 1] (all are per-step
rates in metres, radians, logits or colour units, or fractions of the scene extent); the rest is
per field. A broken rule is an :class:`~taichi_gs.errors.InputError` naming the section and key.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from .errors import InputError
from .flow import DIS_PRESETS
from .stages.pose_pair import CANDIDATE_NAMES

Check = Callable[[Any], bool]


def _at_least(low: float) -> tuple[Check, str]:
    return (lambda v: v >= low), f"at least {low:g}"


def _above(low: float) -> tuple[Check, str]:
    return (lambda v: v > low), f"above {low:g}"


def _within(low: float, high: float) -> tuple[Check, str]:
    return (lambda v: low <= v <= high), f"in [{low:g}, {high:g}]"


def _one_of(*choices: Any) -> tuple[Check, str]:
    return (lambda v: v in choices), "one of " + ", ".join(map(str, choices))


def _each(rule: tuple[Check, str]) -> tuple[Check, str]:
    check, text = rule
    return (lambda v: len(v) > 0 and all(check(x) for x in v)), f"a non-empty list, each {text}"


POSITIVE, NON_NEGATIVE, FRACTION = _above(0), _at_least(0), _within(0, 1)
COUNT, OPTIONAL_COUNT = _at_least(1), _at_least(0)
FRAME_GAPS = ((lambda v: all(isinstance(k, int) and k >= 2 for k in v)), "a list of frame gaps of at least 2")

FIELD_RULES: dict[str, dict[str, tuple[Check, str]]] = {
    "pose": {
        "flow_preset": _one_of(*DIS_PRESETS), "flow_finest_width_px": OPTIONAL_COUNT,
        "fb_alpha": NON_NEGATIVE, "fb_beta": NON_NEGATIVE,
        "max_points": COUNT, "min_points": _at_least(6),
        "min_depth_m": POSITIVE, "max_depth_m": POSITIVE, "depth_edge_ratio": NON_NEGATIVE,
        "photometric_weight": NON_NEGATIVE, "depth_consistency_weight": NON_NEGATIVE,
        "flow_floor_px": POSITIVE, "photometric_floor": POSITIVE, "depth_floor_m": POSITIVE,
        "min_baseline_m": NON_NEGATIVE, "max_iterations": COUNT, "step_tolerance": POSITIVE,
        "cost_tolerance": POSITIVE, "initial_damping": POSITIVE, "max_flow_residual_px": POSITIVE,
        "icp_voxel_m": POSITIVE, "icp_scales": _each(POSITIVE), "icp_iterations": _each(COUNT),
        "icp_distance_factor": POSITIVE, "icp_normal_radius_factor": POSITIVE, "icp_normal_max_nn": COUNT,
        "icp_max_points": OPTIONAL_COUNT, "icp_min_fitness": FRACTION, "icp_max_jump_m": POSITIVE,
        "icp_max_jump_deg": POSITIVE, "rgbd_iterations": _each(COUNT), "rgbd_depth_diff_max_m": POSITIVE,
        "voxel_size_m": POSITIVE,
        "verify_max_score": POSITIVE, "verify_margin": NON_NEGATIVE, "verify_min_overlap": FRACTION,
        "joint_plane_weight": POSITIVE, "joint_iterations": COUNT, "joint_normal_smooth_px": NON_NEGATIVE,
        "verify_preference": ((lambda v: len(v) > 0 and set(v) <= set(CANDIDATE_NAMES)),
                              "a non-empty list of " + ", ".join(CANDIDATE_NAMES)),
        "verify_grid_points": _at_least(10), "verify_depth_sigma_m": POSITIVE,
        "verify_depth_sigma_quadratic": NON_NEGATIVE, "verify_photo_sigma": POSITIVE,
        "verify_photo_weight": NON_NEGATIVE, "graph_skips": FRAME_GAPS,
        "graph_long_spans": FRAME_GAPS, "graph_long_every": COUNT,
        "graph_weak_weight": NON_NEGATIVE, "graph_info_voxel_m": POSITIVE, "graph_info_max_points": OPTIONAL_COUNT,
        "graph_info_distance_m": POSITIVE, "graph_near_tie_mm": NON_NEGATIVE,
        "loop_min_gap": _at_least(2), "loop_every": COUNT, "loop_max_distance_m": POSITIVE,
        "loop_max_angle_deg": _within(0, 180), "threads": OPTIONAL_COUNT, "readout_ms": NON_NEGATIVE,
    },
    "refine": {
        "voxel_size": NON_NEGATIVE, "initial_opacity": _within(0.01, 0.99), "iterations_per_frame": OPTIONAL_COUNT,
        "prune_every_per_frame": COUNT, "reset_every_per_frame": COUNT, "prune_opacity": FRACTION,
        "lambda_depth": NON_NEGATIVE, "lambda_coverage": NON_NEGATIVE, "lambda_opacity": NON_NEGATIVE,
        "min_alpha": _within(0.01, 1), "views_per_step": COUNT, "pose_rotation_per_m": NON_NEGATIVE,
        "pose_warmup_fraction": FRACTION, "resolution_scale": COUNT, "checkpoint_every": COUNT,
        "max_depth": NON_NEGATIVE, "edge_ratio": NON_NEGATIVE, "edge_radius": OPTIONAL_COUNT,
        "pose_prior_weight": NON_NEGATIVE, "pose_prior_sigma_m": POSITIVE, "pose_prior_sigma_deg": POSITIVE,
        "converge_window_per_frame": OPTIONAL_COUNT, "converge_rel_tol": NON_NEGATIVE,
        "converge_pose_m": NON_NEGATIVE, "converge_pose_deg": NON_NEGATIVE,
        "accept_neighbours": OPTIONAL_COUNT, "readout_ms": NON_NEGATIVE,
    },
    "deblur": {
        "k": COUNT, "holdout_every": ((lambda v: v == 0 or v >= 2), "0 (no test views) or at least 2"),
        "iterations": COUNT, "lambda_dssim": FRACTION, "lambda_depth": NON_NEGATIVE, "sh_degree": _one_of(0, 1, 2, 3),
        "exposure_from": OPTIONAL_COUNT, "initial_exposure_fraction": FRACTION, "min_open_px": NON_NEGATIVE,
        "max_step_px": POSITIVE, "densify_from": OPTIONAL_COUNT, "densify_until": OPTIONAL_COUNT,
        "densify_every": COUNT, "densify_grad": POSITIVE, "split_scale": POSITIVE, "prune_opacity": FRACTION,
        "prune_scale": POSITIVE, "max_gaussians": COUNT, "densify_headroom": NON_NEGATIVE,
        "reset_opacity_every": OPTIONAL_COUNT,
        "test_pose_iterations": OPTIONAL_COUNT, "resolution_scale": COUNT, "checkpoint_every": COUNT,
        "grid_frames": OPTIONAL_COUNT, "holdout": _one_of("every", "sharpest"), "lambda_colour_affine": NON_NEGATIVE,
        "test_fit": _one_of("adam", "rprop"), "lr_test_pose": POSITIVE,
        "iterations_per_view": OPTIONAL_COUNT, "fill_frames": COUNT, "fill_stride": COUNT,
        "coarse_scale": COUNT, "coarse_fraction": FRACTION, "k_min": COUNT,
        "early_views_fraction": FRACTION, "early_step_scale": _at_least(1.0),
        "densify_by": _one_of("gradient", "error", "both"), "error_densify_share": FRACTION,
        "prune_weight_share": FRACTION,
        "error_densify_frames": COUNT, "warp_px": _within(0.5, 64), "test_fit_refresh_px": NON_NEGATIVE,
        "keep_frame_scale_error": NON_NEGATIVE, "mid_exposure_decay": FRACTION, "readout_ms": NON_NEGATIVE,
    },
}

# (section, description, check over the section's values): relations between fields of a section.
RELATION_RULES: list[tuple[str, str, Callable[[Any], bool]]] = [
    ("pose", "min_depth_m must be below max_depth_m", lambda c: c.min_depth_m < c.max_depth_m),
    ("pose", "min_points must not exceed max_points", lambda c: c.min_points <= c.max_points),
    ("pose", "icp_scales and icp_iterations need one entry per ICP level",
     lambda c: len(c.icp_scales) == len(c.icp_iterations)),
    ("deblur", "densify_from must not exceed densify_until", lambda c: c.densify_from <= c.densify_until),
    ("deblur", "readout_ms (a rolling shutter) needs warp_views = true", lambda c: c.readout_ms == 0 or c.warp_views),
]


def validate_sections(sections: dict[str, Any], source: Path | None = None) -> None:
    """Raise an InputError for the first value of any section that breaks a rule (see module doc)."""
    for name, section in sections.items():
        rules = FIELD_RULES.get(name, {})
        for field in dataclasses.fields(section):
            value = getattr(section, field.name)
            key = f"[{name}] {field.name}"
            if isinstance(value, float) and not math.isfinite(value):
                raise InputError(source, f"{key} = {value} is not a finite number", "give a finite value")
            if field.name.startswith("lr_") and not 0.0 <= value <= 1.0:
                raise InputError(source, f"{key} = {value:g} is not a learning rate in [0, 1]",
                                 "use the preset's value (see OUT/config.toml) or one near it")
            if field.name in rules:
                check, text = rules[field.name]
                if not check(value):
                    raise InputError(source, f"{key} = {value!r} must be {text}", "fix the value in the config file")
    for name, text, check in RELATION_RULES:
        if name in sections and not check(sections[name]):
            raise InputError(source, f"[{name}] {text}", "fix the values in the config file")
