"""No-reference measures of the real-data protocol: known answers on synthetic images, the sharpest
hold-out split, and the protocol's figures on a run folder whose renders are the ground truth."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from taichi_gs.errors import InputError
from taichi_gs.evaluate import psnr
from taichi_gs.io.images import to_uint8, write_png
from taichi_gs.io.trajectory import write_tum
from taichi_gs.noreference import (
    dark_hole_fraction, gradient_energy, laplacian_variance, masked_psnr, masked_ssim, sharpest_holdout, warp_to_view,
)
from taichi_gs.report import format_metrics
from taichi_gs.stages.deblur import choose_split


def texture(h=64, w=80, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return cv2.GaussianBlur(rng.uniform(0, 1, (h, w, 3)), (0, 0), 1.5).clip(0, 1)


def test_gradient_energy_of_a_ramp_is_its_slope_squared():
    slope = 0.004
    ramp = np.repeat((slope * np.arange(100.0))[None, :, None], 3, axis=2).repeat(60, axis=0)
    assert gradient_energy(ramp) == pytest.approx(slope**2, rel=1e-9)
    diagonal = np.repeat((slope * (np.arange(60.0)[:, None] + np.arange(100.0)[None, :]))[..., None], 3, axis=2)
    assert gradient_energy(diagonal) == pytest.approx(2 * slope**2, rel=1e-9)
    assert gradient_energy(np.full((40, 40, 3), 0.3)) == pytest.approx(0.0, abs=1e-20)


def test_gradient_energy_scales_with_contrast_and_falls_with_blur():
    image = texture()
    assert gradient_energy(0.5 * image) == pytest.approx(0.25 * gradient_energy(image), rel=1e-9)
    assert laplacian_variance(0.5 * image) == pytest.approx(0.25 * laplacian_variance(image), rel=1e-9)
    assert laplacian_variance(np.full((10, 10, 3), 0.7)) == pytest.approx(0.0, abs=1e-20)
    blurred = [cv2.GaussianBlur(image, (0, 0), s) for s in (1.0, 2.0, 3.0)]
    energies = [gradient_energy(image)] + [gradient_energy(b) for b in blurred]
    assert all(a > b for a, b in zip(energies, energies[1:]))
    # the sigma-1 pre-filter damps pixel noise far more than structure at the scale of the texture
    noise = np.random.default_rng(1).normal(0, 0.05, image.shape)
    noise_kept = gradient_energy(noise) / gradient_energy(noise, sigma=0)
    structure_kept = gradient_energy(image) / gradient_energy(image, sigma=0)
    assert noise_kept < 0.15 and structure_kept > 3 * noise_kept


def test_sharpest_holdout_takes_the_sharpest_of_each_window():
    train, test = sharpest_holdout([1, 5, 2, 3, 1, 3, 4, 2, 0, 9], every=3)
    # windows [0, 3), [3, 6) (tie: earlier frame), [6, 10): the short last one joined; the last frame,
    # sharpest of its window, has no training frame after it
    assert test == [1, 3, 6]
    assert train == [0, 2, 4, 5, 7, 8, 9]
    assert sharpest_holdout([1, 5, 2, 3, 3, 1, 0.5], every=3)[1] == [1, 3]  # a blurred lone last frame trains
    assert sharpest_holdout([1, 5, 2, 3, 3, 1], every=3)[1] == [1, 3]
    assert sharpest_holdout([1, 5, 1], every=3)[1] == [1]  # one window, shorter than every: still one test view
    assert sharpest_holdout([1, 2, 3], every=0) == ([0, 1, 2], [])
    with pytest.raises(ValueError):
        sharpest_holdout([1.0, 2.0, 3.0], every=1)


def test_sharpest_holdout_keeps_training_frames_on_both_sides_of_each_test_view():
    # the sharpest of windows [0, 3) and [3, 6) are frames 2 and 3, side by side: the second window takes
    # its sharpest frame that is not next to frame 2
    assert sharpest_holdout([1, 2, 9, 9, 1, 5, 1, 1, 1], every=3)[1] == [2, 5, 7]
    # the first and last frames are never test views (no training frame beyond them)
    assert sharpest_holdout([9, 1, 2, 1, 1, 9], every=3)[1] == [2, 4]
    assert sharpest_holdout([9, 1], every=3)[1] == []  # no frame lies between two others
    # a window whose only candidate is next to the previous test view holds nothing out
    assert sharpest_holdout([1, 9, 5, 1, 1, 1], every=2)[1] == [1, 3]
    train, test = sharpest_holdout([1, 9, 1, 9, 1, 1], every=2)
    assert test == [1, 3] and train == [0, 2, 4, 5]
    for n, every in [(40, 3), (41, 3), (60, 4), (7, 2), (5, 5)]:
        sharpness = np.random.default_rng(n + every).random(n)
        train, test = sharpest_holdout(sharpness, every)
        assert all(0 < i < n - 1 for i in test) and all(b - a >= 2 for a, b in zip(test, test[1:]))
        assert sorted(train + test) == list(range(n))


def test_choose_split_holds_out_the_least_blurred_frames():
    base = texture(seed=3)
    sigmas = [2.0, 0.5, 3.0, 2.5, 1.5, 0.3, 1.0, 2.0, 4.0]
    colors = [cv2.GaussianBlur(base, (0, 0), s) for s in sigmas]
    train, test, sharpness = choose_split(colors, "sharpest", 3)
    assert test == [1, 5, 7] and train == [0, 2, 3, 4, 6, 8]  # 6, sharper than 7, is next to 5
    assert np.argsort(sharpness).tolist() == np.argsort(-np.array(sigmas), kind="stable").tolist()
    assert choose_split(colors, "every", 3)[1] == [1, 4, 7]
    with pytest.raises(InputError):
        choose_split(colors, "blurriest", 3)


def test_warp_through_a_plane_is_a_known_shift():
    h, w, focal, z, shift = 40, 60, 50.0, 2.0, 3
    K = np.array([[focal, 0, 30.0], [0, focal, 20.0], [0, 0, 1]])
    source = texture(h, w, seed=4)
    source_pose = np.eye(4)
    source_pose[:3, 3] = [0.1, -0.2, 0.3]
    pose = source_pose.copy()
    pose[0, 3] += shift * z / focal  # camera moved along its x axis by 3 px at depth z
    warped, valid = warp_to_view(source, source_pose, np.full((h, w), z), pose, K)
    assert valid[:, : w - shift].all() and not valid[:, w - shift + 1:].any()
    assert np.allclose(warped[:, : w - shift], source[:, shift:], atol=1e-5)
    same, valid_same = warp_to_view(source, source_pose, np.full((h, w), z), source_pose, K)
    assert valid_same.all() and np.allclose(same, source, atol=1e-6)
    holes = np.full((h, w), z)
    holes[:10] = 0.0
    assert not warp_to_view(source, source_pose, holes, source_pose, K)[1][:10].any()


def test_masked_scores_and_dark_holes():
    image = np.full((50, 50, 3), 0.5)
    mask = np.zeros((50, 50), bool)
    mask[10:30, 10:30] = True
    shifted = image + 0.1 * mask[..., None]
    assert masked_psnr(shifted, image, mask) == pytest.approx(20.0)
    assert masked_psnr(shifted, image, ~mask) == np.inf
    assert masked_ssim(image, image, mask) == pytest.approx(1.0)
    # what lies outside the mask (a warp's empty pixels) does not enter: only windows inside it count
    texture_image = texture(50, 50, seed=5)
    holed = np.where(mask[..., None], texture_image, 0.0)
    assert masked_ssim(holed, texture_image, mask) == pytest.approx(1.0)
    assert masked_ssim(holed, texture_image, np.ones_like(mask)) < 0.9
    render = np.full((100, 100, 3), 0.6)
    render[30:70, 30:70] = 0.0
    assert dark_hole_fraction(render, np.full((100, 100, 3), 0.6)) == pytest.approx(0.16, abs=0.01)
    away = np.ones((100, 100), bool)
    away[20:80, 20:80] = False  # a mask that leaves the hole out: no dark pixels among its own
    assert dark_hole_fraction(render, np.full((100, 100, 3), 0.6), mask=away) == 0.0
    assert dark_hole_fraction(np.zeros((20, 20, 3)), np.full((20, 20, 3), 0.05)) == 0.0  # input itself dark


def _run_on_synthetic(tmp_path, renders):
    """A 6-frame synthetic sequence (TMP/seq) and a run (TMP/run) whose stage-3 trajectory is the ground truth and
    whose sharp and re-blurred renders of frame i are ``renders(sequence, i)``; (sequence, the run's deblur folder)."""
    synth = pytest.importorskip("taichi_gs.synth")
    from taichi_gs.io.load import load_sequence

    synth.generate(synth.SynthConfig(width=64, height=48, frames=6, trajectory="handheld", blur="extreme", seed=2),
                   tmp_path / "seq")
    sequence = load_sequence(tmp_path / "seq")
    stage = tmp_path / "run" / "deblur"
    for i, name in enumerate(sequence.names):
        for kind, image in zip(("sharp", "reblurred"), renders(sequence, i)):
            write_png(stage / "renders" / kind / f"{name}.png", to_uint8(image))
    write_tum(stage / "trajectory.txt", sequence.timestamps, sequence.gt_poses)
    return sequence, stage


def test_protocol_on_a_run_whose_renders_are_the_truth(tmp_path):
    """Sharp renders = sharp ground truth and re-blurred renders = the input: re-blur PSNR is that
    of 8-bit rounding, the gradient-energy ratio equals ground truth's, and the held-out score is
    the ground truth's against the blurred frame."""
    from taichi_gs.noreference_report import no_reference_metrics

    sequence, stage = _run_on_synthetic(tmp_path, lambda sequence, i: (sequence.sharp(i), sequence.color(i)))
    train, test, sharpness = choose_split([sequence.color(i) for i in range(6)], "sharpest", 3)
    (stage / "split.json").write_text(json.dumps({"train": train, "test": test, "holdout": "sharpest",
                                                  "holdout_every": 3, "laplacian_variance": sharpness}))
    metrics = no_reference_metrics(tmp_path / "run", sequence)
    assert "sharpest frame" in metrics["protocol"]
    held = metrics["test"]
    assert held["views"] == 2 and held["reblur_psnr_db"] > 45
    assert held["gradient_energy_ratio"] == pytest.approx(held["ground_truth_gradient_energy_ratio"], rel=0.02)
    expected = np.mean([psnr(sequence.sharp(i), sequence.color(i)) for i in test])
    assert held["held_out_psnr_db"] == pytest.approx(expected, abs=0.05)
    assert 0.3 < held["warp_coverage"] <= 1.0 and np.isfinite(held["warped_neighbour_psnr_db"])
    # the re-blurred renders are the inputs themselves: on the floor's pixels too they match to 8-bit rounding
    assert held["reblur_on_warp_mask_psnr_db"] > 45 > held["render_on_warp_mask_psnr_db"]
    views = metrics["per_view"]
    assert [v["index"] for v in views] == list(range(6)) and [v["frame"] for v in views] == sequence.names
    assert sorted(v["index"] for v in views if v["split"] == "test") == sorted(test)
    assert np.mean([v["held_out_psnr_db"] for v in views if v["split"] == "test"]) == pytest.approx(
        held["held_out_psnr_db"], rel=1e-12)
    printed = format_metrics({"trajectory": {}, "no_reference": metrics})
    assert f"{held['reblur_psnr_db']:.2f}" in printed and f"{held['warped_neighbour_psnr_db']:.2f}" in printed
    assert f"re-blurred render {held['reblur_on_warp_mask_psnr_db']:.2f}" in printed
    synthetic = {"trajectory": {}, "no_reference": metrics, "images": {"ground_truth": "sharp images"}}
    assert "no-reference" not in format_metrics(synthetic)  # sharp ground truth scores the renders instead
    ceiling = []
    for i in test:  # the held-out frame over the mean of its nearest training frames, before and after
        near = [j for j in (max((t for t in train if t < i), default=None), min((t for t in train if t > i), default=None))
                if j is not None]
        ceiling.append(gradient_energy(sequence.color(i)) / np.mean([gradient_energy(sequence.color(j)) for j in near]))
    assert held["sharpest_over_neighbours_gradient_energy_ratio"] == pytest.approx(np.mean(ceiling), rel=1e-9)
    assert metrics["train"]["views"] == 4 and metrics["sourced_fraction"] == 1.0
    assert cv2.imread(str(tmp_path / "run" / "report" / "no_reference_views.png")) is not None


def test_protocol_leaves_pixels_without_a_camera_source_out(tmp_path):
    """A reader transform whose top rows have no source (as an undistorted frame's border): renders
    that are wrong only there score as if they were right everywhere, and the protocol says so."""
    synth = pytest.importorskip("taichi_gs.synth")
    from taichi_gs.io.load import load_sequence
    from taichi_gs.io.transforms import FrameTransform
    from taichi_gs.noreference_report import no_reference_metrics

    class UnsourcedTop(FrameTransform):
        def color(self, path, image):
            return np.concatenate([np.repeat(image[6:7], 6, axis=0), image[6:]])

        def sourced(self, share):
            return np.concatenate([np.zeros_like(share[:6]), share[6:]])

    synth.generate(synth.SynthConfig(width=64, height=48, frames=6, trajectory="handheld", blur="extreme", seed=2),
                   tmp_path / "seq")
    sequence = load_sequence(tmp_path / "seq")
    sequence.transform = UnsourcedTop()
    stage = tmp_path / "run" / "deblur"
    for i, name in enumerate(sequence.names):
        for kind, image in (("sharp", sequence.sharp(i)), ("reblurred", sequence.color(i))):
            wrong_on_top = image.copy()
            wrong_on_top[:6] = 1.0 - wrong_on_top[:6]
            write_png(stage / "renders" / kind / f"{name}.png", to_uint8(wrong_on_top))
    write_tum(stage / "trajectory.txt", sequence.timestamps, sequence.gt_poses)
    train, test, sharpness = choose_split([sequence.color(i) for i in range(6)], "sharpest", 3)
    (stage / "split.json").write_text(json.dumps({"train": train, "test": test, "holdout": "sharpest",
                                                  "holdout_every": 3, "laplacian_variance": sharpness}))
    metrics = no_reference_metrics(tmp_path / "run", sequence)
    assert metrics["sourced_fraction"] == pytest.approx(42 / 48) and "camera saw" in metrics["protocol"]
    held = metrics["test"]
    assert held["reblur_psnr_db"] > 45 and held["reblur_ssim"] > 0.99
    assert held["gradient_energy_ratio"] == pytest.approx(held["ground_truth_gradient_energy_ratio"], rel=0.02)
    seen = np.ones((48, 64), bool)
    seen[:6] = False
    expected = np.mean([masked_psnr(sequence.sharp(i), sequence.color(i), seen) for i in test])
    assert held["held_out_psnr_db"] == pytest.approx(expected, abs=0.05)
    assert metrics["train"]["reblur_psnr_db"] > 45


def test_protocol_reports_the_streaks_of_learned_and_true_exposures(tmp_path):
    """``exposure_px`` is the mean streak over the exposure in the run's exposure.txt: a sideways slide of s metres
    moves a point at depth z by f s / z pixels. ``true_exposure_px`` follows the sequence's own exposures and
    agrees with the smear the generator recorded (from noise-free depth); a run whose exposure.txt does not
    match the frames is an input error naming the file."""
    from taichi_gs.noreference_report import no_reference_metrics
    from taichi_gs.stages.deblur.outputs import _format_exposure

    sequence, stage = _run_on_synthetic(tmp_path, lambda sequence, i: (sequence.color(i), sequence.color(i)))
    (stage / "split.json").write_text(json.dumps({"train": [0, 2, 3, 5], "test": [1, 4], "holdout": "every",
                                                  "holdout_every": 3}))
    slide = 0.01 * np.arange(1, 7)  # metres along the camera's x axis, one length per frame
    starts = sequence.gt_poses.copy()
    starts[:, :3, 3] -= starts[:, :3, 0] * slide[:, None] / 2
    ends = sequence.gt_poses.copy()
    ends[:, :3, 3] += ends[:, :3, 0] * slide[:, None] / 2
    exposure = np.stack([starts, ends], 1)
    (stage / "exposure.txt").write_text(_format_exposure(sequence.timestamps, exposure))
    metrics = no_reference_metrics(tmp_path / "run", sequence)
    expected = []
    for i in range(6):  # the points of every 4th pixel with depth
        depth = sequence.depth(i)[::4, ::4]
        expected.append(np.mean(sequence.K()[0, 0] * slide[i] / depth[depth > 0]))
    views = metrics["per_view"]
    np.testing.assert_allclose([v["exposure_px"] for v in views], expected, rtol=1e-4)
    assert metrics["test"]["exposure_px"] == pytest.approx(np.mean([expected[1], expected[4]]), rel=1e-4)
    assert "blur px" in format_metrics({"trajectory": {}, "no_reference": metrics})
    recorded = json.loads((tmp_path / "seq" / "synth.json").read_text())["smear_px"]["per_frame_mean"]
    np.testing.assert_allclose([v["true_exposure_px"] for v in views], recorded, rtol=0.03)
    assert cv2.imread(str(tmp_path / "run" / "report" / "blur_streaks.png")) is not None
    (stage / "exposure.txt").write_text(_format_exposure(sequence.timestamps[:5], exposure[:5]))
    with pytest.raises(InputError, match="exposure.txt"):
        no_reference_metrics(tmp_path / "run", sequence)
