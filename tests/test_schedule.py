"""[ours] Work that follows need: coarse-to-fine resolution, k per exposure, convergence windows,
and stage 3's move of a scene between resolutions."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from taichi_gs.stages.deblur import run as deblur
from taichi_gs.stages.schedule import training_scale, views_for_span, window_converged


def test_coarse_phase_covers_the_given_share_and_the_end_is_full_resolution():
    scales = [training_scale(it, 100, 1, 2, 0.4) for it in range(100)]
    assert scales[:40] == [2] * 40 and scales[40:] == [1] * 60
    assert {training_scale(it, 100, 2, 2, 0.4) for it in range(40)} == {4}
    assert training_scale(99, 100, 2, 2, 1.0) == 4 and training_scale(0, 100, 1, 1, 0.9) == 1
    levels = [training_scale(it, 90, 1, 4, 2 / 3) for it in range(90)]
    assert levels == [4] * 30 + [2] * 30 + [1] * 30


@pytest.mark.parametrize("span, step, k_min, k_max, expected", [
    (12.0, 2.0, 3, 7, 7), (8.0, 2.0, 3, 7, 5), (8.1, 2.0, 3, 7, 6), (1.0, 2.0, 3, 7, 3), (40.0, 1.0, 3, 15, 15),
    (0.0, 1.0, 2, 15, 2), (6.0, 2.0, 5, 3, 3)])
def test_views_keep_neighbours_within_the_step_and_the_bounds(span, step, k_min, k_max, expected):
    k = views_for_span(span, step, k_min, k_max)
    assert k == expected
    if k < k_max:
        assert span / (k - 1) <= step  # neighbours close enough
    if min(k_min, k_max) < k < k_max:
        assert span / (k - 2) > step  # and no view more than needed


def test_early_views_widen_the_step_only_before_their_share_of_training():
    config = deblur.DeblurConfig(k=7, max_step_px=2.0, adaptive_k=True, k_min=3, early_views_fraction=0.5,
                                 early_step_scale=2.0)
    d = np.array([[-0.01, 0, 0, 0, 0, 0], [0.01, 0, 0, 0, 0, 0]])  # 0.02 m sideways at 2 m, f = 500: 5 px
    assert deblur.exposure_px(d[0], d[1], 500.0, 2.0) == pytest.approx(5.0)
    assert deblur._views(d, 500.0, 2.0, config, 0.49) == 3  # 4 px steps: ceil(5 / 4) + 1
    assert deblur._views(d, 500.0, 2.0, config, 0.5) == 4  # 2 px steps: ceil(5 / 2) + 1
    assert deblur._views(d, 500.0, 2.0, config) == 4  # the held-out fits pass no fraction: the full rule
    off = deblur.DeblurConfig(k=7, max_step_px=2.0, adaptive_k=True, k_min=3)
    assert deblur._views(d, 500.0, 2.0, off, 0.0) == 4
    presets = deblur.PRESETS
    assert presets["fast"].early_views_fraction == 0.3 and presets["paper"].early_views_fraction == 0.0


def test_warped_views_leave_out_each_odd_groups_middle_view():
    from taichi_gs.stages.deblur.model import warped_views

    assert [warped_views(k, 1) for k in range(3, 10)] == [2, 4, 4, 6, 6, 8, 8]
    assert [warped_views(k, 3) for k in (4, 5, 8, 9)] == [2, 4, 6, 6]  # groups 1-2-1, 2-1-2, 3-2-3, 3-3-3
    assert warped_views(6, 0) == 6  # no anchors: every view is rendered


@pytest.mark.parametrize("span_px, warp_px, expected", [
    (5.0, 12.0, (5, 1)),  # 4 views at 2 px steps; a fifth at the anchor's pose costs no interpolation
    (9.0, 12.0, (7, 1)),  # 6 -> 7
    (12.0, 12.0, (7, 1)),  # already odd
    (15.0, 12.0, (9, 1)),  # 9 at the cap
    (5.0, 2.0, (4, 3)),  # three anchors: groups 1-2-1 interpolate 2 views, 2-1-2 would interpolate 4
])
def test_odd_views_raise_an_even_count_only_where_no_view_more_is_interpolated(span_px, warp_px, expected):
    from taichi_gs.stages.deblur.run import _exposure_sampling, _Frames

    focal, depth = 200.0, 2.0
    d = np.zeros((2, 6))
    d[1, 0] = span_px * depth / focal  # sideways translation giving span_px on the image
    frames = _Frames([], [], np.array([depth]), np.array([[focal, 0, 0], [0, focal, 0], [0, 0, 1.0]]))
    config = deblur.DeblurConfig(k=9, max_step_px=2.0, adaptive_k=True, k_min=3, warp_views=True, warp_px=warp_px,
                                 odd_views=True)
    assert _exposure_sampling(d, frames, 0, config) == expected
    plain = dataclasses.replace(config, odd_views=False)
    even = _exposure_sampling(d, frames, 0, plain)
    assert even[0] == min(int(np.ceil(span_px / 2.0)) + 1, 9)
    rendered = dataclasses.replace(config, warp_views=False)  # every view rendered: nothing comes free
    assert _exposure_sampling(d, frames, 0, rendered) == (even[0], 0)
    capped = dataclasses.replace(config, k=6)
    assert _exposure_sampling(d, frames, 0, capped)[0] <= 6
    presets = deblur.PRESETS
    assert presets["fast"].odd_views and presets["fast"].k == 9 and not presets["paper"].odd_views


def test_window_convergence_needs_two_windows_and_a_small_relative_change():
    assert not window_converged([1.0] * 5, 3, 0.01)
    assert window_converged([1.0, 1.0, 1.0, 1.005, 0.998, 1.0], 3, 0.01)
    assert not window_converged([2.0, 2.0, 2.0, 1.0, 1.0, 1.0], 3, 0.01)
    assert not window_converged(list(np.linspace(1.0, 0.5, 40)), 10, 0.05)
    assert window_converged(list(np.linspace(1.0, 0.99, 40)), 10, 0.05)


def test_moving_the_scene_between_resolutions_keeps_gaussians_and_optimiser_state(tmp_path):
    from taichi_gs.splats import splats_from_points
    from taichi_gs.stages.deblur.model import BlurScene

    synth = pytest.importorskip("taichi_gs.synth")
    from taichi_gs.io.load import load_sequence

    synth.generate(synth.SynthConfig(width=64, height=48, frames=3, seed=2), tmp_path / "seq")
    sequence = load_sequence(tmp_path / "seq")
    rng = np.random.default_rng(0)
    splats = splats_from_points(rng.uniform(-1, 1, (50, 3)) + [0, 0, 3], rng.uniform(0, 1, (50, 3)), scale=0.05,
                                opacity=0.5)
    cache = {1: deblur._load_frames(sequence, 1, None)}
    model = BlurScene(splats, cache[1].K, 64, 48)
    model.density.grad_sum[:] = rng.uniform(size=model.count)
    before = model.state()
    frames, coarse = deblur._phase(sequence, None, model, cache, 2)
    assert (coarse.width, coarse.height) == (32, 24) and frames.colors[0].shape == (24, 32, 3)
    assert frames.K[0, 0] == pytest.approx(cache[1].K[0, 0] / 2)
    for name, value in coarse.state().items():
        np.testing.assert_array_equal(value, before[name])
    frames, back = deblur._phase(sequence, None, coarse, cache, 1)
    assert (back.width, back.height) == (64, 48) and frames is cache[1]
    assert deblur._phase(sequence, None, back, cache, 1)[1] is back


def _poses(shift_m: float, n: int = 3) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], n, axis=0)
    poses[:, 0, 3] = shift_m
    return poses


def test_convergence_watch_stops_only_on_flat_loss_and_still_cameras_outside_quiet_windows():
    from taichi_gs.stages.schedule import ConvergenceWatch

    watch = ConvergenceWatch(window=4, rel_tol=0.01, pose_m=1e-3, pose_deg=0.1)
    stops = [watch.update(it, 1.0, _poses(0.0)) for it in range(1, 13)]
    assert stops == [False] * 7 + [True] + [False] * 3 + [True]  # first check only records the poses
    moving = ConvergenceWatch(window=4, rel_tol=0.01, pose_m=1e-3, pose_deg=0.1)
    assert not any(moving.update(it, 1.0, _poses(0.002 * it)) for it in range(1, 21))
    assert moving.last_move[0] == pytest.approx(0.008)
    falling = ConvergenceWatch(window=4, rel_tol=0.01, pose_m=1e-3, pose_deg=0.1)
    assert not any(falling.update(it, 1.0 / it, _poses(0.0)) for it in range(1, 21))
    reset = ConvergenceWatch(window=4, rel_tol=0.01, pose_m=1e-3, pose_deg=0.1)
    reset.disturbed(4)
    stops = [reset.update(it, 1.0, _poses(0.0)) for it in range(1, 17)]
    assert stops.index(True) == 11  # iteration 12: two windows after the reset at 4
    off = ConvergenceWatch(window=0, rel_tol=1.0, pose_m=1.0, pose_deg=1.0)
    assert not any(off.update(it, 1.0, _poses(0.0)) for it in range(1, 20))


def test_coarse_to_fine_with_k_per_exposure_deblurs_held_out_views_at_full_size(tmp_path):
    import dataclasses

    import cv2
    from taichi_gs.standins import synthetic_refine_outputs

    from taichi_gs.evaluate import psnr

    synth = pytest.importorskip("taichi_gs.synth")
    clip = synth.SynthConfig(width=96, height=72, frames=9, trajectory="handheld", blur="extreme", seed=1)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.05)
    # early_views_fraction off: the fewer views asserted below must come from the coarse phase alone
    config = dataclasses.replace(deblur.PRESETS["fast"], iterations_per_view=0, k=7, iterations=200, densify_from=100,
                                 densify_until=150, exposure_from=60, test_pose_iterations=10, checkpoint_every=100,
                                 coarse_scale=2, coarse_fraction=0.5, adaptive_k=True, k_min=3,
                                 early_views_fraction=0.0)
    ks: list[int] = []
    original = deblur.BlurScene.step

    def spy(self, *args, **kwargs):
        ks.append((self.width, args[5]))
        return original(self, *args, **kwargs)

    deblur.BlurScene.step = spy
    try:
        result = deblur.run_deblur(sequence, out, config)
    finally:
        deblur.BlurScene.step = original
    assert {w for w, _ in ks[:100]} == {48} and {w for w, _ in ks[100:200]} == {96}
    assert {w for w, _ in ks[200:]} == {96}  # test-time exposure fits at full size
    assert all(3 <= k <= 7 for _, k in ks) and len({k for _, k in ks}) > 1
    assert np.mean([k for _, k in ks[:100]]) < np.mean([k for _, k in ks[100:200]])  # fewer views when coarse
    for i in result.test:
        ours = cv2.cvtColor(cv2.imread(str(out / "deblur" / "renders" / "sharp" / f"{sequence.names[i]}.png")),
                            cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0
        assert ours.shape == (72, 96, 3)
        assert psnr(ours, sequence.sharp(i)) > psnr(sequence.color(i), sequence.sharp(i))


def test_stage2_stops_at_the_first_converged_check_and_still_writes_its_outputs(tmp_path):
    import dataclasses

    from taichi_gs.io.load import load_sequence
    from taichi_gs.io.trajectory import read_tum
    from taichi_gs.stages.pose import PoseConfig, fuse_points
    from taichi_gs.stages.refine import PRESETS, run_refine

    synth = pytest.importorskip("taichi_gs.synth")
    synth.generate(synth.SynthConfig(width=64, height=48, frames=6, seed=3), tmp_path / "seq")
    sequence = load_sequence(tmp_path / "seq")
    poses = np.linalg.inv(sequence.gt_poses[0]) @ sequence.gt_poses
    points, colors = fuse_points(sequence, poses, PoseConfig(voxel_size_m=0.05))
    config = dataclasses.replace(PRESETS["fast"], voxel_size=0.05, iterations_per_frame=40, converge_window_per_frame=5,
                                 converge_rel_tol=1.0, converge_pose_m=1.0, converge_pose_deg=90.0)
    result = run_refine(sequence, poses, points, colors, tmp_path / "run", config)
    # watch starts after the 24-iteration warm-up; checks every 30: 30 records poses, 60 has 36 losses
    # (< 2 windows), 90 stops
    assert result.iterations == 90 < 240
    assert np.allclose(read_tum(tmp_path / "run" / "refine" / "trajectory.txt")[1], result.poses, atol=1e-5)
    capped = run_refine(sequence, poses, points, colors, tmp_path / "cap",
                        dataclasses.replace(config, converge_window_per_frame=0))
    assert capped.iterations == 240
