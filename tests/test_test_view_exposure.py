"""Stage 3's test-time exposure refinement of a held-out view: with the scene frozen, fitting the
frame's exposure offsets to its blurred input moves a deliberately wrong exposure to the true one
(the blur of the re-rendered scene over a known exposure) and leaves the scene untouched."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from taichi_gs.geometry import invert, se3_exp, se3_log, virtual_pose
from taichi_gs.splats import Splats
from taichi_gs.stages.deblur.exposures import DepthMoments, neighbours_mid_shift, velocity_twists
from taichi_gs.stages.deblur.model import BlurScene
from taichi_gs.stages.deblur.run import PRESETS, DeblurConfig, _Frames, _refine_test_exposure, load_stage2, run_deblur

WIDTH, HEIGHT = 48, 40
K = np.array([[40.0, 0.0, 23.5], [0.0, 40.0, 19.5], [0.0, 0.0, 1.0]])
BASE = se3_exp(np.array([0.1, 0.05, -0.02, 0.02, -0.04, 0.01]))
VELOCITY = np.array([0.08, -0.04, 0.02, 0.02, 0.03, -0.01])  # ~3 px of image travel over the exposure
TRUE = np.stack([-0.5 * VELOCITY, 0.5 * VELOCITY])
K_VIEWS = 5


def _textured_scene(seed: int, n: int = 400) -> Splats:
    """Small, opaque, randomly coloured Gaussians filling the view at 2-3 m: plenty of edges."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(2.0, 3.0, n)
    u, v = rng.uniform(-4, WIDTH + 4, n), rng.uniform(-4, HEIGHT + 4, n)
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    means = cam @ BASE[:3, :3].T + BASE[:3, 3]
    sh = rng.uniform(-1.5, 1.5, (n, 1, 3))
    return Splats(means.astype(np.float32), rng.normal(size=(n, 4)).astype(np.float32),
                  np.log(rng.uniform(0.03, 0.08, (n, 3))).astype(np.float32),
                  np.full(n, 2.0, np.float32), sh.astype(np.float32))


def _error(d: np.ndarray) -> float:
    """Distance to the true exposure in se(3); start and end may swap (the k-view mean cannot tell)."""
    return min(np.linalg.norm(d - TRUE), np.linalg.norm(d[::-1] - TRUE))


def _held_out_frame(seed: int) -> tuple[BlurScene, np.ndarray, _Frames, np.ndarray]:
    """(scene, its blur over the true exposure, that blur as the held-out frame, a wrong start: a third
    of the true motion with its middle off by a few pixels)."""
    model = BlurScene(_textured_scene(seed), K, WIDTH, HEIGHT)
    blurred = model.render_blurred(BASE, TRUE[0], TRUE[1], K_VIEWS)
    _, depth = model.render(BASE)
    frames = _Frames([blurred], [depth], np.array([float(np.median(depth[depth > 0]))]), K)
    shift = np.array([0.02, -0.015, 0.0, 0.0, 0.01, 0.0])
    return model, blurred, frames, np.stack([0.33 * TRUE[0] + shift, 0.33 * TRUE[1] + shift])


@pytest.mark.parametrize("seed", [0, 1])
def test_refinement_recovers_the_exposure_with_the_scene_frozen(seed):
    model, blurred, frames, start = _held_out_frame(seed)
    config = DeblurConfig(k=K_VIEWS, test_pose_iterations=120, lr_test_pose=2e-3, lambda_dssim=0.2)

    params, t = model.arrays(), model.store.adam.t
    stats = model.density.grad_sum.copy(), model.density.grad_count.copy()
    refined, colour, _ = _refine_test_exposure(model, frames, BASE, start.copy(), start, 0, config)

    assert _error(refined) < 0.1 * _error(start), (_error(start), _error(refined))
    mid = virtual_pose(BASE, *refined, 0.5)
    true_mid = virtual_pose(BASE, *TRUE, 0.5)
    start_mid = virtual_pose(BASE, *start, 0.5)
    assert np.linalg.norm(mid[:3, 3] - true_mid[:3, 3]) < 0.25 * np.linalg.norm(start_mid[:3, 3] - true_mid[:3, 3])
    residual = np.abs(model.render_blurred(BASE, *refined, K_VIEWS) - blurred).mean()
    assert residual < 0.3 * np.abs(model.render_blurred(BASE, *start, K_VIEWS) - blurred).mean()

    # scene frozen: parameters, optimiser step and densification statistics unchanged
    for name, value in model.arrays().items():
        np.testing.assert_array_equal(value, params[name], err_msg=name)
    assert model.store.adam.t == t
    np.testing.assert_array_equal(model.density.grad_sum, stats[0])
    np.testing.assert_array_equal(model.density.grad_count, stats[1])
    np.testing.assert_array_equal(colour, np.eye(3, 4))  # colour_affine off: identity


@pytest.mark.parametrize("seed", [0, 1])
def test_a_fit_on_frozen_anchors_recovers_the_exposure_as_the_rendered_fit(seed, monkeypatch):
    """[ours] ``test_fit_refresh_px``: warped views from anchor renders kept across the fit's steps recover
    the exposure about as well as the fit that renders its anchor at every step (within 1.3x of its error
    and re-blur residual after the same 60 Rprop steps), rendering the anchor at most every 4th step."""
    from taichi_gs.stages.deblur import run as deblur

    made = []

    class Recorded(deblur.FrozenAnchors):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(deblur, "FrozenAnchors", Recorded)
    _, blurred, frames, start = _held_out_frame(seed)
    start_residual = np.abs(BlurScene(_textured_scene(seed), K, WIDTH, HEIGHT).render_blurred(BASE, *start, K_VIEWS)
                            - blurred).mean()
    error, residual = {}, {}
    for refresh_px in (0.0, 1.0):
        config = DeblurConfig(k=K_VIEWS, test_pose_iterations=60, test_fit="rprop", lr_test_pose=2e-3,
                              lambda_dssim=0.2, warp_views=True, test_fit_refresh_px=refresh_px)
        model = BlurScene(_textured_scene(seed), K, WIDTH, HEIGHT, warp_margin=deblur.warp_margin(config))
        refined, _, _ = _refine_test_exposure(model, frames, BASE, start.copy(), start, 0, config)
        error[refresh_px] = _error(refined)
        residual[refresh_px] = np.abs(model.render_blurred(BASE, *refined, K_VIEWS) - blurred).mean()
    assert len(made) == 1 and 1 <= made[0].renders <= 60 // 4, made[0].renders  # none made when refresh_px is 0
    assert error[1.0] < 0.4 * _error(start) and residual[1.0] < 0.05 * start_residual, (error, residual)
    assert error[1.0] < 1.3 * error[0.0] and residual[1.0] < 1.3 * residual[0.0], (error, residual)


@pytest.mark.parametrize("seed", [0, 1])
def test_rprop_fits_the_blur_in_fewer_steps_than_adam(seed):
    """[ours] test_fit = "rprop": with the same 20 steps its re-blurred render matches the blurred
    input at least twice as closely as Adam's, and the mid-exposure pose improves as much."""
    model, blurred, frames, start = _held_out_frame(seed)
    true_mid, start_mid = virtual_pose(BASE, *TRUE, 0.5), virtual_pose(BASE, *start, 0.5)
    residual, mid_error = {}, {}
    for fit in ("adam", "rprop"):
        config = DeblurConfig(k=K_VIEWS, test_pose_iterations=20, lr_test_pose=2e-3, lambda_dssim=0.2, test_fit=fit)
        refined, _, _ = _refine_test_exposure(model, frames, BASE, start.copy(), start, 0, config)
        residual[fit] = np.abs(model.render_blurred(BASE, *refined, K_VIEWS) - blurred).mean()
        mid_error[fit] = np.linalg.norm(virtual_pose(BASE, *refined, 0.5)[:3, 3] - true_mid[:3, 3])
    assert residual["rprop"] < 0.5 * residual["adam"], residual
    assert mid_error["rprop"] < 0.6 * np.linalg.norm(start_mid[:3, 3] - true_mid[:3, 3]), mid_error


def test_rprop_fit_with_a_zero_colour_rate_keeps_the_colour():
    """A zero ``lr_colour_affine`` (a valid rate: frozen) leaves the colour transform at identity under
    Rprop, as under Adam, instead of failing after training."""
    model, _, frames, start = _held_out_frame(0)
    config = DeblurConfig(k=K_VIEWS, test_pose_iterations=3, lr_test_pose=2e-3, test_fit="rprop",
                          colour_affine=True, lr_colour_affine=0.0)
    refined, colour, _ = _refine_test_exposure(model, frames, BASE, start.copy(), start, 0, config)
    np.testing.assert_array_equal(colour, np.eye(3, 4))
    assert not np.array_equal(refined, start)


def test_velocity_twists_are_the_motion_to_the_neighbours_per_frame_or_per_second():
    step = np.array([0.01, -0.02, 0.005, 0.01, 0.002, -0.003])
    poses = np.stack([BASE @ se3_exp(i * step) for i in range(5)])
    np.testing.assert_allclose(velocity_twists(poses), np.tile(step, (5, 1)), atol=1e-12)
    np.testing.assert_allclose(velocity_twists(poses, np.arange(5) * 0.05), np.tile(step / 0.05, (5, 1)), atol=1e-9)


def test_the_depth_shift_is_the_velocity_times_the_depths_time_offset():
    moments = DepthMoments(np.stack([VELOCITY, 2 * VELOCITY]), np.array([-0.3, 0.0]))
    np.testing.assert_allclose(moments.shift(0), -0.3 * VELOCITY)
    np.testing.assert_array_equal(moments.shift(1), np.zeros(6))


@pytest.mark.parametrize("seed", [0, 1])
def test_the_depth_term_pins_the_exposure_at_the_instant_its_depth_shows(seed):
    """[ours] ``test_fit_lambda_depth``: a held-out frame whose depth shows the start of its exposure (0.5 s before
    its colour's timestamp, the exposure one second of its velocity) is fitted closer to the truth when the fit
    knows that instant than when it takes the depth as mid-exposure's (half the error or less), and still recovers
    the exposure from its wrong start."""
    model, blurred, frames, start = _held_out_frame(seed)
    depth = model.rasterizer.forward(model.gaussians, model.camera(virtual_pose(BASE, *TRUE, 0.0)),
                                     with_colour=False).depth.to_numpy()  # the blended depth the loss compares
    frames = _Frames(frames.colors, [depth], frames.median_depth, K)
    error = {}
    for name, offset in (("mid", 0.0), ("instant", -0.5)):
        config = DeblurConfig(k=K_VIEWS, test_pose_iterations=60, test_fit="rprop", lr_test_pose=2e-3,
                              lambda_dssim=0.2, test_fit_lambda_depth=1.0)
        moments = DepthMoments(VELOCITY[None], np.array([offset]))
        refined, _, _ = _refine_test_exposure(model, frames, BASE, start.copy(), start, 0, config, None, moments)
        error[name] = _error(refined)
    assert error["instant"] < 0.5 * error["mid"] and error["instant"] < 0.5 * _error(start), error


def test_neighbours_mid_shift_is_the_mean_correction_of_the_nearest_training_frames():
    """[ours] The shift is the mean of (d_s + d_e) / 2 over the nearest training frame on each side that
    exists (skipping held-out neighbours), and zero when no frame trains."""
    rng = np.random.default_rng(3)
    offsets = rng.normal(scale=0.01, size=(7, 2, 6))
    mid = 0.5 * (offsets[:, 0] + offsets[:, 1])
    train = [0, 2, 5]
    np.testing.assert_allclose(neighbours_mid_shift(offsets, train, 1), 0.5 * (mid[0] + mid[2]))
    np.testing.assert_allclose(neighbours_mid_shift(offsets, train, 3), 0.5 * (mid[2] + mid[5]))
    np.testing.assert_allclose(neighbours_mid_shift(offsets, train, 4), 0.5 * (mid[2] + mid[5]))
    np.testing.assert_allclose(neighbours_mid_shift(offsets, train, 6), mid[5])  # none after it
    np.testing.assert_array_equal(neighbours_mid_shift(offsets, [], 3), np.zeros(6))


@pytest.mark.parametrize("from_neighbours", [False, True])
def test_held_out_frames_start_where_their_training_neighbours_moved(tmp_path, from_neighbours):
    """[ours] ``test_fit_from_neighbours``: with no fit steps, a held-out frame's mid-exposure pose is its
    stage-2 pose moved by its training neighbours' mean learned correction (off: the stage-2 pose itself)."""
    from taichi_gs.standins import synthetic_refine_outputs

    synth = pytest.importorskip("taichi_gs.synth")
    clip = synth.SynthConfig(width=64, height=48, frames=6, trajectory="handheld", blur="extreme", seed=2)
    sequence, run = synthetic_refine_outputs(tmp_path, clip, voxel=0.06)
    config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, k=3, iterations=30, densify_from=10,
                                 densify_until=20, densify_every=10, exposure_from=0, test_pose_iterations=0,
                                 test_fit_from_neighbours=from_neighbours,
                                 keep_frame=False)  # the poses as trained, not moved into stage 2's frame afterwards
    result = run_deblur(sequence, run, config)
    base, _ = load_stage2(run, sequence.timestamps)
    learned = np.stack([[se3_log(invert(base[j]) @ result.mid_poses[j])] * 2 for j in range(len(sequence))])
    assert result.test == [1, 4]
    for frame in result.test:
        shift = neighbours_mid_shift(learned, result.train, frame)
        assert np.linalg.norm(shift) > 1e-5  # the neighbours did learn a correction
        expected = base[frame] @ se3_exp(shift) if from_neighbours else base[frame]
        np.testing.assert_allclose(result.mid_poses[frame], expected, atol=1e-6)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_bowed_fit_finds_the_middle_of_a_curved_exposure(seed):
    """[ours] ``test_fit_bend``: a held-out frame blurred along a curved path (bowed across its motion by a third of
    its travel) is fitted with its mid-exposure camera at half the distance to the truth's, or less, that a straight exposure
    gets to."""
    model = BlurScene(_textured_scene(seed), K, WIDTH, HEIGHT)
    d_true = 3.0 * TRUE  # ~9 px of travel
    bow = np.array([0.02, 0.04, 0.0, 0.0, 0.0, 0.0])  # across the motion: ~3 px at mid-exposure
    blurred = model.render_blurred(BASE, d_true[0], d_true[1], 9, bend=bow)
    _, depth = model.render(BASE)
    frames = _Frames([blurred], [depth], np.array([float(np.median(depth[depth > 0]))]), K)
    truth = virtual_pose(BASE, *d_true, 0.5, bow)
    start = 0.5 * d_true
    errors = {}
    for share in (0.0, 0.5):
        config = DeblurConfig(k=9, test_pose_iterations=80, test_fit="rprop", lr_test_pose=2e-3, lambda_dssim=0.2,
                              test_fit_bend=share)
        refined, _, bend = _refine_test_exposure(model, frames, BASE, start.copy(), start, 0, config)
        assert share > 0 or not bend.any()
        errors[share] = np.linalg.norm(virtual_pose(BASE, *refined, 0.5, bend)[:3, 3] - truth[:3, 3])
    assert errors[0.5] < 0.5 * errors[0.0], errors


def test_a_bowed_held_out_fit_reaches_the_trajectory_and_the_sharp_render(tmp_path):
    """[ours] ``test_fit_bend`` end to end: a held-out frame's bowed mid-exposure pose is the one stage 3 reports
    and the one its sharp render shows (the render written equals a render at the reported pose)."""
    from taichi_gs.io.sequence import read_color
    from taichi_gs.io.ply import read_splats
    from taichi_gs.standins import synthetic_refine_outputs

    synth = pytest.importorskip("taichi_gs.synth")
    clip = synth.SynthConfig(width=64, height=48, frames=6, trajectory="handheld", blur="extreme", seed=2)
    sequence, run = synthetic_refine_outputs(tmp_path, clip, voxel=0.06)
    config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, k=3, iterations=30, densify_from=10,
                                 densify_until=20, densify_every=10, exposure_from=0, test_pose_iterations=4,
                                 test_fit_bend=0.5, colour_affine=False)
    result = run_deblur(sequence, run, config)
    frame = result.test[0]
    stage = run / "deblur"
    frame_shift = json.loads((stage / "frame.json").read_text()) if (stage / "frame.json").is_file() else None
    base, _ = load_stage2(run, sequence.timestamps)
    if frame_shift is not None:
        base[:, :3, 3] = frame_shift["scale"] * base[:, :3, 3] + np.array(frame_shift["translation_m"])
    ends = result.exposure[frame]
    straight = virtual_pose(base[frame], se3_log(invert(base[frame]) @ ends[0]),
                            se3_log(invert(base[frame]) @ ends[1]), 0.5)
    assert np.linalg.norm(result.mid_poses[frame][:3, 3] - straight[:3, 3]) > 1e-6  # the fit bowed it
    model = BlurScene(read_splats(stage / "splats.ply"), sequence.K(), 64, 48)
    render = np.clip(model.render(result.mid_poses[frame])[0], 0, 1)
    written = read_color(stage / "renders" / "sharp" / f"{sequence.names[frame]}.png")
    assert np.abs(render - written).max() < 1.5 / 255  # the same pose, up to 8-bit rounding
