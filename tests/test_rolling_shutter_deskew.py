"""[ours] Frames de-skewed for a rolling shutter (``rolling_shutter.DeskewedSequence``) and stages 1 and 2 on them:
a rolling-shutter frame moved to its pose is the global-shutter frame, stage 1 de-skews with the motions of its
pairs as read and resumes from both caches, and the settings reach the stages from presets, config and CLI."""

from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np
import pytest
from typer.testing import CliRunner

import taichi_gs.stages.pose.run as pose_stage
from taichi_gs import synth
from taichi_gs.cli import app
from taichi_gs.evaluate import ate
from taichi_gs.geometry import se3_exp
from taichi_gs.io.load import load_sequence
from taichi_gs.rolling_shutter import (MAX_DESKEW_WIDTH_FRACTION, DeskewedSequence, deskew_maps, deskewing_motions,
                                       readout_motions, readout_px, stage_readout_ms)
from taichi_gs.stages import refine as refine_stage
from taichi_gs.stages.pose import pose_readout_ms, run_pose
from taichi_gs.stages.pose.config import PRESETS, PoseConfig

KINECT_V1 = {"format": "tum", "camera": "fr1"}


class _Frames:
    """The least of a sequence that DeskewedSequence reads: colour, depth and K per frame."""

    def __init__(self, colors: list[np.ndarray], depths: list[np.ndarray], K: np.ndarray):
        self.colors, self.depths, self.intrinsics_K = colors, depths, K

    def __len__(self) -> int:
        return len(self.colors)

    def color(self, i: int) -> np.ndarray:
        return self.colors[i]

    def depth(self, i: int) -> np.ndarray:
        return self.depths[i]

    def K(self) -> np.ndarray:
        return self.intrinsics_K


def test_a_rolling_shutter_frame_moved_to_its_pose_is_the_global_shutter_frame():
    """A turn read out over 30 ms (no blur, exact depth; rows up to 10 px from the frame's pose): de-skewed by the
    motion its neighbours' poses give, colour is the global-shutter render at the frame's pose to within
    resampling (measured 0.018 against 0.077 as read; a half-pixel shift there and back alone leaves 0.016) and
    depth to a tenth of the error as read."""
    config = synth.SynthConfig(width=160, height=120, frames=40, trajectory="turn", blur="none", seed=4,
                               depth_noise=False, holes=False, readout_ms=30.0)
    path, K = synth._camera_path(config), synth.camera_matrix(config)
    times = np.arange(9, 12) / config.fps
    poses = np.stack([path(t) for t in times])
    images, _ = synth.render_frame(config, 10, poses[1], np.stack([poses[1], poses[1]]))
    read_depth = images.depth_raw.astype(np.float32) / config.depth_scale
    global_rgb, global_depth = synth.render_view(poses[1], K, 160, 120, 4, "room")
    frames = _Frames([images.blurred] * 3, [read_depth] * 3, K)
    deskewed = DeskewedSequence(frames, readout_motions(poses, times, 0.030))

    inner = (slice(6, -6), slice(6, -6))  # rows that the readout brought in from outside the frame
    color_before = np.abs(images.blurred - global_rgb)[inner].mean()
    color_after = np.abs(deskewed.color(1) - global_rgb)[inner].mean()
    assert color_before > 0.05 and color_after < 0.35 * color_before
    depth = deskewed.depth(1)[inner]
    seen = depth > 0
    assert seen.mean() > 0.98
    depth_before = np.median(np.abs(read_depth[inner] - global_depth[inner]))
    depth_after = np.median(np.abs(depth[seen] - global_depth[inner][seen]))
    assert depth_after < 0.25 * depth_before


def test_a_frames_colour_and_depth_share_one_computation_of_its_maps(monkeypatch):
    import taichi_gs.rolling_shutter as rolling_shutter

    rng = np.random.default_rng(1)
    frames = _Frames([rng.random((12, 16, 3), dtype=np.float32)] * 2, [1.0 + rng.random((12, 16), dtype=np.float32)] * 2,
                     np.array([[20.0, 0, 7.5], [0, 20.0, 5.5], [0, 0, 1]]))
    motions = np.tile([0.01, 0.0, 0.0, 0.0, 0.05, 0.0], (2, 1))
    expected = DeskewedSequence(frames, motions)
    expected = (expected.color(1), expected.depth(1))
    calls = []
    monkeypatch.setattr(rolling_shutter, "deskew_maps", lambda *a: calls.append(1) or deskew_maps(*a))
    deskewed = DeskewedSequence(frames, motions)
    color, depth = deskewed.color(1), deskewed.depth(1)
    assert len(calls) == 1 and not depth.flags.writeable
    np.testing.assert_array_equal(color, expected[0])
    np.testing.assert_array_equal(depth, expected[1])


def test_frames_without_readout_motion_are_the_sequences_own():
    color, depth = np.random.default_rng(0).random((8, 10, 3), dtype=np.float32), np.ones((8, 10), np.float32)
    frames = _Frames([color, color], [depth, depth], np.diag([20.0, 20.0, 1.0]))
    deskewed = DeskewedSequence(frames, np.zeros((2, 6)))
    assert deskewed.color(1) is color and deskewed.depth(0) is depth and len(deskewed) == 2
    assert deskewed.K() is frames.K()  # everything else is the wrapped sequence's
    assert copy.copy(deskewed).color(1) is color  # a copy reads through to the same sequence
    with pytest.raises(ValueError, match="3 readout motions for 2 frames"):
        DeskewedSequence(frames, np.zeros((3, 6)))


@pytest.fixture(scope="module")
def rolling_shutter_walk(tmp_path_factory):
    """A hand-held walk, 160x120, read out over 25 ms (no blur)."""
    folder = tmp_path_factory.mktemp("rs_walk")
    synth.generate(synth.SynthConfig(width=160, height=120, frames=10, trajectory="handheld", blur="none", seed=0,
                                     readout_ms=25.0), folder)
    return load_sequence(folder)


def test_stage_1_on_de_skewed_frames_holds_where_the_frames_as_read_slip(tmp_path, rolling_shutter_walk, monkeypatch):
    """With the clip's readout, stage 1 estimates the pairs as read, de-skews and estimates them again: ATE under
    half that of the same stage on the frames as read (measured 1.5 against 6.3 mm). It records the readout, and
    a rerun takes every pair from the two caches."""
    sequence = rolling_shutter_walk
    as_read = run_pose(sequence, tmp_path / "as_read", PoseConfig()).poses
    progress: list[str] = []
    result = run_pose(sequence, tmp_path / "rs", PoseConfig(readout_ms=25.0),
                      progress=lambda done, total, kind: progress.append(kind))
    error, error_as_read = ate(result.poses, sequence.gt_poses), ate(as_read, sequence.gt_poses)
    assert error < 0.5 * error_as_read and error < 0.003, (error, error_as_read)

    record = json.loads((tmp_path / "rs" / "pose" / "pairs.json").read_text())
    assert record["rolling_shutter"]["readout_ms"] == 25.0 and 0.5 < record["rolling_shutter"]["skew_px"] < 20
    assert "frames de-skewed for a rolling shutter of 25 ms" in record["summary"]
    assert len(list((tmp_path / "rs" / "pose" / "pairs_as_read").glob("*.json"))) == 9
    assert progress[:9] == ["pairs as read"] * 9 and progress[9:18] == ["pairs"] * 9
    assert len(progress) == pose_stage.progress_steps(10, PoseConfig(), 25.0)
    assert "rolling_shutter" not in json.loads((tmp_path / "as_read" / "pose" / "pairs.json").read_text())

    def no_estimates(*args, **kwargs):
        raise AssertionError("a cached pair was estimated again")

    monkeypatch.setattr(pose_stage, "_estimate_pair", no_estimates)
    again = run_pose(sequence, tmp_path / "rs", PoseConfig(readout_ms=25.0))
    np.testing.assert_allclose(again.poses, result.poses, atol=1e-12)


def test_known_cameras_readout_reaches_stages_1_and_2_in_the_fast_preset(rolling_shutter_walk):
    """A known camera's readout (a Kinect v1 reading, or the own layout's intrinsics.json ``readout_ms``) is the
    fast preset's; the stage's own readout stands over it, and the paper preset keeps a global shutter."""
    assert stage_readout_ms(0.0, True, KINECT_V1) == 25.0
    assert stage_readout_ms(10.0, True, KINECT_V1) == 10.0
    assert stage_readout_ms(0.0, False, KINECT_V1) == 0.0
    assert stage_readout_ms(0.0, True, {"format": "taichi-gs"}) == 0.0
    sequence = rolling_shutter_walk
    assert sequence.source["readout_ms"] == 25.0  # synth wrote its readout into intrinsics.json
    assert pose_readout_ms(sequence, PRESETS["fast"]) == 25.0
    assert pose_readout_ms(sequence, PRESETS["paper"]) == 0.0
    assert stage_readout_ms(0.0, True, {"format": "taichi-gs", "readout_ms": 0.0}) == 0.0  # a global shutter, said

    poses = sequence.gt_poses
    refine_fast = dataclasses.replace(refine_stage.PRESETS["fast"], readout_ms=25.0)
    assert refine_fast.iterations_per_frame == 0
    assert refine_stage.deskewed_for_training(sequence, poses, refine_fast) == (sequence, 0.0)  # no training
    training = dataclasses.replace(refine_fast, iterations_per_frame=1)
    deskewed, readout_ms = refine_stage.deskewed_for_training(sequence, poses, training)
    assert readout_ms == 25.0 and isinstance(deskewed, DeskewedSequence)
    np.testing.assert_allclose(deskewed.readout_motions, readout_motions(poses, sequence.timestamps, 0.025))


def test_a_pose_jump_between_neighbours_de_skews_by_a_bounded_amount(rolling_shutter_walk):
    """A readout motion that would move rows by more than MAX_DESKEW_WIDTH_FRACTION of the width (a slipped pair
    gives it) is scaled down to that; the others are kept as they are."""
    sequence = rolling_shutter_walk
    poses = sequence.gt_poses.copy()
    kept, kept_skew = deskewing_motions(sequence, readout_motions(poses, sequence.timestamps, 0.025))
    assert 0.5 < kept_skew < MAX_DESKEW_WIDTH_FRACTION * 160
    np.testing.assert_allclose(kept, readout_motions(poses, sequence.timestamps, 0.025))
    poses[5] = poses[5] @ se3_exp(np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0]))  # a 57-degree jump
    motions, skew = deskewing_motions(sequence, readout_motions(poses, sequence.timestamps, 0.025))
    assert skew == pytest.approx(MAX_DESKEW_WIDTH_FRACTION * 160)
    for i in (4, 6):  # their neighbours' poses straddle the jump
        depth = sequence.depth(i)
        assert readout_px(motions[i], sequence.K()[0, 0], np.median(depth[depth > 0])) == pytest.approx(skew)
    np.testing.assert_allclose(motions[[0, 1, 2, 3, 7, 8, 9]], kept[[0, 1, 2, 3, 7, 8, 9]])


def test_precomputed_flows_keep_the_frames_as_read(tmp_path):
    """Flows from a folder belong to the frames as read: a known camera's readout is not applied with them, and a
    readout asked for with them is an input error naming the folder."""
    from taichi_gs.errors import InputError

    tum = type("Reading", (), {"source": KINECT_V1})()
    flows = dataclasses.replace(PRESETS["fast"], flow_dir=str(tmp_path))
    assert pose_readout_ms(tum, PRESETS["fast"]) == 25.0 and pose_readout_ms(tum, flows) == 0.0
    with pytest.raises(InputError, match="precomputed flows are of the frames as read"):
        pose_readout_ms(tum, dataclasses.replace(flows, readout_ms=25.0))


def test_the_cli_readout_stands_over_a_known_cameras_and_is_checked(tmp_path, rolling_shutter_walk):
    from taichi_gs.cli import with_readout

    config = with_readout(PRESETS["fast"], 0.0)
    assert config.readout_ms == 0.0 and not config.camera_readout
    assert with_readout(PRESETS["fast"], None) is PRESETS["fast"]
    result = CliRunner().invoke(app, ["pose", str(rolling_shutter_walk.root), "--out", str(tmp_path / "o"),
                                      "--readout-ms", "-5"])
    assert result.exit_code == 2


@pytest.mark.parametrize("deskew_depth", [True, False])
def test_stage_3_trains_on_depth_de_skewed_for_its_readout(tmp_path, monkeypatch, deskew_depth):
    """With a readout, stage 3's depth frames (its depth loss, the fill of uncovered pixels) are de-skewed by the
    motions of stage 2's poses; ``deskew_depth = false`` keeps them as read. Colour stays as read either way."""
    from taichi_gs.stages.deblur import run as deblur_stage
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=48, height=32, frames=4, trajectory="handheld", blur="extreme", seed=2)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.1)
    loaded = []
    load = deblur_stage._load_frames

    def spy(sequence, scale, sourced, depth_source=None):
        loaded.append((depth_source, load(sequence, scale, sourced, depth_source)))
        return loaded[-1][1]

    monkeypatch.setattr(deblur_stage, "_load_frames", spy)
    config = dataclasses.replace(deblur_stage.PRESETS["fast"], iterations_per_view=0, iterations=0, k=3,
                                 adaptive_k=False, test_pose_iterations=0, holdout_every=0, keep_frame=False,
                                 readout_ms=25.0, deskew_depth=deskew_depth)
    deblur_stage.run_deblur(sequence, out, config)
    depth_source, frames = loaded[0]
    assert (depth_source is not None) == deskew_depth
    for i in range(4):
        np.testing.assert_array_equal(frames.colors[i], sequence.color(i))
        expected = depth_source.depth(i) if deskew_depth else sequence.depth(i)
        np.testing.assert_array_equal(frames.depths[i], expected)
    if deskew_depth:
        assert isinstance(depth_source, DeskewedSequence) and depth_source.readout_motions.any()
        assert not np.array_equal(frames.depths[1], sequence.depth(1))


def test_coarse_phases_read_depth_as_the_full_resolution_phase_does(tmp_path, monkeypatch):
    """Coarse-to-fine (``coarse_scale``): every resolution's frames take their depth from the same de-skewed source
    as the training resolution's (before, a coarse phase read the depth as read)."""
    from taichi_gs.stages.deblur import frames as deblur_frames
    from taichi_gs.stages.deblur import run as deblur_stage
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=48, height=32, frames=4, trajectory="handheld", blur="extreme", seed=2)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.1)
    sources = []
    load = deblur_frames._load_frames

    def spy(sequence, scale, sourced, depth_source=None):
        sources.append((scale, depth_source))
        return load(sequence, scale, sourced, depth_source)

    monkeypatch.setattr(deblur_stage, "_load_frames", spy)
    monkeypatch.setattr(deblur_frames, "_load_frames", spy)
    config = dataclasses.replace(deblur_stage.PRESETS["fast"], iterations_per_view=0, iterations=6, k=3,
                                 adaptive_k=False, test_pose_iterations=0, holdout_every=0, keep_frame=False,
                                 readout_ms=25.0, coarse_scale=2, coarse_fraction=0.5, densify_from=100,
                                 densify_until=100, exposure_from=100)
    deblur_stage.run_deblur(sequence, out, config)
    assert {scale for scale, _ in sources} == {1, 2}
    assert all(isinstance(source, DeskewedSequence) and source is sources[0][1] for _, source in sources)
