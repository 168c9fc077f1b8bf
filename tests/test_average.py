"""``taichi-gs import --average W``: consecutive frames averaged in linear light into one long exposure, the
centre frame its sharp reference, checked on a synthetic sequence whose sharp frames and poses are known."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from taichi_gs.cli import app
from taichi_gs.io.average import AveragedSequence, average_in_linear_light, linear_to_srgb, srgb_to_linear
from taichi_gs.io.load import load_sequence
from taichi_gs.io.sequence import read_color
from taichi_gs.io.trajectory import read_tum
from taichi_gs.synth import SynthConfig, generate

runner = CliRunner()
WINDOW = 3


@pytest.fixture(scope="module")
def sharp_sequence(tmp_path_factory):
    """A 10-frame synthetic sequence without blur: each colour frame is the sharp view at its pose."""
    return generate(SynthConfig(width=96, height=72, frames=10, trajectory="handheld", blur="none", seed=3),
                    tmp_path_factory.mktemp("synth") / "seq")


@pytest.fixture(scope="module")
def averaged(sharp_sequence, tmp_path_factory):
    out = tmp_path_factory.mktemp("avg") / "avg"
    result = runner.invoke(app, ["import", str(sharp_sequence), "--out", str(out), "--average", str(WINDOW),
                                 "--scale", "0.5"])
    assert result.exit_code == 0, result.output
    return out


def test_srgb_round_trip_and_the_mean_of_black_and_white_is_half_the_light():
    values = np.linspace(0.0, 1.0, 101)
    assert np.allclose(linear_to_srgb(srgb_to_linear(values)), values, atol=1e-12)
    mean = average_in_linear_light([np.zeros((1, 1, 3)), np.ones((1, 1, 3))])
    assert np.allclose(srgb_to_linear(mean.astype(np.float64)), 0.5, atol=1e-6)
    assert mean[0, 0, 0] == pytest.approx(0.7354, abs=1e-3)  # not 0.5: the mean is of light, not of code values


def test_each_frame_is_its_windows_linear_light_mean_and_the_centre_its_reference(sharp_sequence, averaged):
    source = load_sequence(sharp_sequence, scale=0.5)
    result = load_sequence(averaged)
    assert len(result) == len(source) // WINDOW == 3  # the tenth frame fills no window
    assert (result.intrinsics.width, result.intrinsics.height) == (48, 36)
    assert result.intrinsics.fx == pytest.approx(source.intrinsics.fx)
    t_gt, gt = read_tum(averaged / "groundtruth.txt")
    for j in range(len(result)):
        window = [source.color(i) for i in range(j * WINDOW, (j + 1) * WINDOW)]
        linear = np.mean([np.where(f <= 0.04045, f / 12.92, ((f + 0.055) / 1.055) ** 2.4) for f in window], axis=0)
        expected = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
        assert np.abs(result.color(j) - expected).max() <= 0.5 / 255 + 1e-6
        assert np.abs(result.color(j) - window[1]).max() > 0.1  # the camera moved: the mean is blurred
        centre = j * WINDOW + 1
        assert np.abs(result.sharp(j) - source.sharp(centre)).max() <= 0.5 / 255 + 1e-6
        assert np.abs(result.depth(j) - source.depth(centre)).max() < 1e-3
        assert result.timestamps[j] == pytest.approx(source.timestamps[centre], abs=1e-6)
        assert np.allclose(gt[j], source.gt_poses[centre], atol=1e-6)
        assert np.allclose(result.exposure_poses[j, 0], source.gt_poses[centre - 1], atol=1e-6)
        assert np.allclose(result.exposure_poses[j, 1], source.gt_poses[centre + 1], atol=1e-6)
    assert len(t_gt) == len(result)


def test_blur_json_measures_each_streak_and_the_flow_agrees_with_the_poses(sharp_sequence, averaged):
    blur = json.loads((averaged / "blur.json").read_text())
    assert blur["window"] == WINDOW
    assert blur["exposure_s"] == pytest.approx((WINDOW - 1) / 30.0, rel=1e-3)
    assert [f["sources"] for f in blur["frames"]][1] == ["000003", "000004", "000005"]
    from_poses = np.array([f["median_px"] for f in blur["frames"]])
    assert all(f["from"] == "poses" for f in blur["frames"]) and np.all(from_poses > 0.3)
    without_poses = AveragedSequence(load_sequence(sharp_sequence, scale=0.5), WINDOW)
    without_poses.base.gt_poses = None
    from_flow = np.array([without_poses.streak(j)["median_px"] for j in range(len(without_poses))])
    assert without_poses.streak(0)["from"] == "flow"
    assert np.allclose(from_flow, from_poses, rtol=0.35, atol=0.3)


def test_the_input_is_never_written_and_the_sharp_folder_comes_from_the_centre_frames(sharp_sequence, averaged):
    assert sorted(p.name for p in (averaged / "sharp").iterdir()) == ["000001.png", "000004.png", "000007.png"]
    assert not (sharp_sequence / "blur.json").exists()
    assert read_color(averaged / "rgb" / "000004.png").shape == (36, 48, 3)


@pytest.mark.parametrize("args, message", [
    (["--average", "4"], "not an odd window"),
    (["--average", "7"], "window(s) of 7"),
])
def test_windows_that_cannot_be_made_are_refused(sharp_sequence, tmp_path, args, message):
    result = runner.invoke(app, ["import", str(sharp_sequence), "--out", str(tmp_path / "out"), *args])
    assert result.exit_code == 2, result.output
    assert message in " ".join(result.output.split())


def test_each_window_keeps_its_centre_frames_depth_timestamp(sharp_sequence):
    source = load_sequence(sharp_sequence)
    source.depth_timestamps = source.timestamps + np.linspace(-0.01, 0.01, len(source))
    averaged = AveragedSequence(source, WINDOW)
    np.testing.assert_array_equal(averaged.depth_timestamps, source.depth_timestamps[averaged.centres])
    np.testing.assert_allclose(averaged.depth_offsets(), source.depth_offsets()[averaged.centres])
