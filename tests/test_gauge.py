"""[ours] Stage 3's output back in stage 2's frame (stages/gauge.py): the scale + translation fit, the move of the
scene and exposures (colour renders unchanged, depth scaled), and stage 3 ending in stage 2's frame."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from taichi_gs.geometry import fit_scale_translation, se3_exp, virtual_pose
from taichi_gs.io.ply import read_splats
from taichi_gs.io.trajectory import read_tum
from taichi_gs.splats import Splats
from taichi_gs.stages.deblur import PRESETS, run_deblur, shrink_mid
from taichi_gs.stages.deblur.gauge import back_to_stage_2s_frame
from taichi_gs.stages.deblur.model import BlurScene

WIDTH, HEIGHT = 40, 32
K = np.array([[38.0, 0.0, 19.3], [0.0, 37.0, 15.6], [0.0, 0.0, 1.0]])


def test_the_fit_recovers_a_scale_and_translation_and_leaves_the_scale_out_when_told():
    rng = np.random.default_rng(0)
    source = rng.normal(size=(12, 3))
    target = 1.013 * source + np.array([0.004, -0.002, 0.006])
    scale, translation = fit_scale_translation(source, target)
    assert scale == pytest.approx(1.013, abs=1e-12) and np.allclose(translation, [0.004, -0.002, 0.006], atol=1e-12)
    scale, translation = fit_scale_translation(source, target, with_scale=False)
    assert scale == 1.0 and np.allclose(translation, target.mean(axis=0) - source.mean(axis=0))


def _drifted(scale: float, shift: np.ndarray, noise_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Stage 2's poses of three frames 0.3 m apart, and exposure offsets (start, end) whose mid-exposure centres
    are stage 2's centres put through the inverse of ``x -> scale x + shift`` (then moved by up to ``noise_m``
    each), plus a spread about them."""
    poses = np.stack([se3_exp(np.array([0.3 * i, 0.05 * i, 0.02, 0.01, -0.02 * i, 0.03])) for i in range(3)])
    offsets = np.zeros((3, 2, 6))
    noise = np.random.default_rng(7).uniform(-noise_m, noise_m, (3, 3))
    for i, pose in enumerate(poses):
        drifted = (pose[:3, 3] - shift) / scale + noise[i]
        rho = pose[:3, :3].T @ (drifted - pose[:3, 3])  # exp([rho, 0]) moves the centre by R rho
        offsets[i, 0, :3], offsets[i, 1, :3] = rho - 0.01, rho + 0.01
        offsets[i, 0, 3:], offsets[i, 1, 3:] = [0.01, -0.004, 0.0], [-0.01, 0.004, 0.0]
    return poses, offsets


def _scene(poses: np.ndarray) -> Splats:
    rng = np.random.default_rng(3)
    n = 40
    local = np.stack([rng.uniform(-1.0, 1.0, n), rng.uniform(-0.8, 0.8, n), rng.uniform(2.5, 4.0, n)], axis=1)
    means = local @ poses[1, :3, :3].T + poses[1, :3, 3]
    return Splats(means, rng.normal(size=(n, 4)), np.log(rng.uniform(0.08, 0.3, (n, 3))), rng.normal(0.5, 1.0, n),
                  rng.normal(size=(n, 4, 3)) * 0.5)


def test_the_move_puts_drifted_centres_back_and_leaves_every_colour_render_as_it_was():
    """Mid-exposure centres drifted by a known similarity come back onto stage 2's exactly; the sharp and the
    k-view renders (view-dependent colour included) are the same before and after, and depth scales with it."""
    scale, shift = 0.99, np.array([0.006, -0.003, 0.005])
    poses, offsets = _drifted(scale, shift)
    splats = _scene(poses)
    moved, moved_poses, moved_offsets, frame = back_to_stage_2s_frame(splats, poses, offsets, [0, 1, 2], 0.001)
    assert frame.scale == pytest.approx(scale, abs=1e-9) and np.allclose(frame.translation, shift, atol=1e-9)
    assert frame.scale_error < 1e-9
    for i in range(3):
        assert np.allclose(virtual_pose(moved_poses[i], *moved_offsets[i], 0.5)[:3, 3], poses[i, :3, 3], atol=1e-9)
    before, after = BlurScene(splats, K, WIDTH, HEIGHT), BlurScene(moved, K, WIDTH, HEIGHT)
    colour, depth = before.render(virtual_pose(poses[1], *offsets[1], 0.5))
    colour_moved, depth_moved = after.render(virtual_pose(moved_poses[1], *moved_offsets[1], 0.5))
    assert colour.std() > 0.05 and (depth > 0).mean() > 0.3
    assert np.abs(colour_moved - colour).max() < 1e-4
    assert np.allclose(depth_moved, scale * depth, rtol=1e-4, atol=1e-5)
    blurred = before.render_blurred(poses[2], offsets[2, 0], offsets[2, 1], 5)
    blurred_moved = after.render_blurred(moved_poses[2], moved_offsets[2, 0], moved_offsets[2, 1], 5)
    assert np.abs(blurred_moved - blurred).max() < 1e-4


def test_a_scale_the_centres_do_not_determine_stays_one():
    """Centres that drifted 5 mm each besides the similarity: the scale's standard error (about 1%) is above the
    limit, so only the translation moves, and it brings their mean onto stage 2's."""
    poses, offsets = _drifted(0.99, np.array([0.006, -0.003, 0.005]), noise_m=0.005)
    splats = _scene(poses)
    moved, moved_poses, moved_offsets, frame = back_to_stage_2s_frame(splats, poses, offsets, [0, 1, 2], 0.001)
    assert frame.scale == 1.0 and 0.001 < frame.scale_error < 0.1
    assert np.allclose(moved.log_scales, splats.log_scales)
    mids = np.stack([virtual_pose(moved_poses[i], *moved_offsets[i], 0.5)[:3, 3] for i in range(3)])
    assert np.allclose(mids.mean(axis=0), poses[:, :3, 3].mean(axis=0), atol=1e-9)


def _short_stage_3(tmp_path, **overrides):
    """A 12-iteration stage 3 on a stand-in stage 2 of a 4-frame clip whose exposures train at a large rate (so that
    they drift from stage 2's cameras); returns (result, stage 2's centres, stage 3's mid-exposure poses)."""
    synth = pytest.importorskip("taichi_gs.synth")
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=64, height=48, frames=4, trajectory="handheld", blur="extreme", seed=3)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.08)
    config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, k=3, iterations=12, densify_from=1000,
                                 exposure_from=0, lr_exposure=0.02, lr_exposure_final=0.02, test_pose_iterations=0,
                                 holdout_every=0, checkpoint_every=100, fill_uncovered=False)
    result = run_deblur(sequence, out, dataclasses.replace(config, **overrides))
    return result, read_tum(out / "refine" / "trajectory.txt")[1], read_tum(out / "deblur" / "trajectory.txt")[1]


@pytest.mark.parametrize("keep_frame", [True, False])
def test_stage_3_ends_in_stage_2s_frame(tmp_path, keep_frame):
    """With ``keep_frame`` the training frames' mid-exposure centres end with stage 2's mean and the move is
    recorded in frame.json (the scene moved with them); without it the drift stays and no frame.json is
    written."""
    result, stage_2, stage_3 = _short_stage_3(tmp_path, keep_frame=keep_frame)
    train = result.train
    gap = np.linalg.norm(stage_3[train, :3, 3].mean(axis=0) - stage_2[train, :3, 3].mean(axis=0))
    record = tmp_path / "out" / "deblur" / "frame.json"
    if keep_frame:
        assert gap < 1e-6
        frame = json.loads(record.read_text())
        unmoved = read_splats(tmp_path / "out" / "refine" / "splats.ply")  # means train at a tiny rate: near these
        moved = read_splats(tmp_path / "out" / "deblur" / "splats.ply")
        assert len(moved) == len(unmoved)
        assert np.allclose(moved.means.mean(axis=0), frame["scale"] * unmoved.means.mean(axis=0)
                           + frame["translation_m"], atol=2e-3)
    else:
        assert gap > 1e-4 and not record.exists()


def test_the_mid_offset_shrinks_by_its_share_and_the_span_stays():
    d = np.array([[0.01, -0.02, 0.004, 0.002, 0.0, -0.001], [0.03, 0.01, -0.002, 0.004, 0.002, 0.003]])
    shrunk = shrink_mid(d, 0.25)
    assert np.allclose(shrunk.mean(axis=0), 0.75 * d.mean(axis=0)) and np.allclose(shrunk[1] - shrunk[0], d[1] - d[0])
    assert shrink_mid(d, 0.0) is d and np.allclose(shrink_mid(d, 1.0).mean(axis=0), 0.0)


@pytest.mark.parametrize("pin", [True, False])
def test_pinned_exposures_keep_every_mid_exposure_pose_at_stage_2s(tmp_path, pin):
    """``mid_exposure_decay = 1``: training frames and held-out fits alike end at stage 2's cameras (the exposures
    still learn their spans); at 0, the same run moves them by more than 0.1 mm."""
    result, stage_2, stage_3 = _short_stage_3(tmp_path, mid_exposure_decay=1.0 if pin else 0.0, keep_frame=False,
                                              holdout_every=2, test_pose_iterations=3)
    assert result.test
    moved = np.abs(stage_3 - stage_2).max(axis=(1, 2))
    exposure = np.loadtxt(tmp_path / "out" / "deblur" / "exposure.txt")
    spans = np.linalg.norm(exposure[:, 1:4] - exposure[:, 8:11], axis=1)
    assert spans.min() > 0
    if pin:
        assert moved.max() < 1e-6
    else:
        assert moved[result.train].max() > 1e-4 and moved[result.test].max() > 1e-4
