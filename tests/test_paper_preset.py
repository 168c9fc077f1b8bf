"""``--preset paper`` is the paper's method: every addition of ours is off in it, and each one listed here is a
real field that the default (fast) preset turns on, so that a renamed or new addition cannot hide."""

from __future__ import annotations

import dataclasses

import pytest

from taichi_gs.stages import deblur, refine
from taichi_gs.stages.pose import config as pose_config

# Per stage: each addition of ours and the value that switches it off (the method's).
ADDITIONS = {
    "pose": (pose_config.PRESETS, {
        "verify": False, "joint_solve": False, "rgbd_refine": False, "icp_from_prior": False, "seeded_retry": False,
        "pose_graph": False, "flow_finest_width_px": 0, "camera_readout": False, "readout_ms": 0.0}),
    "refine": (refine.PRESETS, {"accept_neighbours": 0, "lambda_coverage": 0.0, "edge_ratio": 0.0,
                                "pose_prior_weight": 0.0, "converge_window_per_frame": 0, "spatial_order": False,
                                "camera_readout": False, "readout_ms": 0.0}),
    "deblur": (deblur.PRESETS, {
        "colour_affine": False, "iterations_per_view": 0, "epoch_sampling": False, "fill_uncovered": False,
        "init_max_px": 0.0, "split_px": 0.0, "coarse_scale": 1, "adaptive_k": False, "early_views_fraction": 0.0,
        "spatial_order": False, "sourced_pixels_only": False, "densify_by": "gradient", "prune_weight_share": 0.0,
        "warp_views": False, "odd_views": False, "keep_frame": False, "mid_exposure_decay": 0.0, "readout_ms": 0.0,
        "camera_readout": False, "test_fit": "adam", "test_fit_from_neighbours": False, "test_fit_refresh_px": 0.0,
        "densify_headroom": 0.0, "initial_exposure_fraction": 0.5, "test_fit_lambda_depth": 0.0,
        "test_fit_bend": 0.0}),
}


@pytest.mark.parametrize("stage", sorted(ADDITIONS))
def test_the_paper_preset_turns_every_addition_off(stage):
    presets, off = ADDITIONS[stage]
    paper = dataclasses.asdict(presets["paper"])
    assert set(off) <= set(paper), f"stale names: {set(off) - set(paper)}"
    assert {name: paper[name] for name in off} == off


@pytest.mark.parametrize("stage", sorted(ADDITIONS))
def test_the_default_preset_is_ours(stage):
    presets, off = ADDITIONS[stage]
    fast = dataclasses.asdict(presets["fast"])
    on = {name for name in off if fast[name] != off[name]}
    assert on, f"the fast preset turns none of stage {stage}'s additions on"


def test_the_pose_stage_of_paper_runs_the_flow_solve_and_icp_alone(tmp_path):
    """Run on a tiny synthetic sequence: every pair's estimate is the flow solve or ICP, and no graph ran."""
    from taichi_gs.io.load import load_sequence
    from taichi_gs.stages.pose import run_pose
    from taichi_gs.synth import SynthConfig, generate

    generate(SynthConfig(width=96, height=72, frames=4, blur="moderate", seed=2), tmp_path / "seq")
    config = dataclasses.replace(pose_config.PRESETS["paper"], icp_max_points=20000)
    result = run_pose(load_sequence(tmp_path / "seq"), tmp_path / "out", config)
    assert {p["estimate"] for p in result.pairs} <= {"flow", "icp"}
    assert all(p.get("candidates") in (None, [], {}) for p in result.pairs)
