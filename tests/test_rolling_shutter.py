"""[ours] Rolling shutters (``rolling_shutter``, ``[deblur] readout_ms``): each frame's motion over the readout
from the trajectory, the rows' poses, and stage 3's wiring. The warp of rows at their own poses and the step's
gradients are checked against NumPy and finite differences in ``test_warp_views``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from taichi_gs.errors import InputError
from taichi_gs.geometry import se3_exp
from taichi_gs.io.readout import camera_readout_ms
from taichi_gs.rolling_shutter import readout_motions, readout_px, shutter_rows
from taichi_gs.stages.deblur import PRESETS, run_deblur
from taichi_gs.validation import validate_sections

synth = pytest.importorskip("taichi_gs.synth")

TWIST = np.array([0.3, -0.1, 0.2, 0.5, -0.8, 0.4])  # per second, camera frame


def test_a_steady_motion_gives_every_frame_its_twist_times_the_readout():
    """On a path of constant body velocity P(t) = P0 exp(t xi), every frame (the ends too) moves xi x readout
    while its rows are read, whatever the frame times."""
    times = np.array([0.0, 0.03, 0.07, 0.1, 0.16])
    start = se3_exp(np.array([1.0, 2.0, 0.5, 0.3, -0.2, 1.0]))
    poses = np.stack([start @ se3_exp(t * TWIST) for t in times])
    np.testing.assert_allclose(readout_motions(poses, times, 0.025), np.tile(0.025 * TWIST, (5, 1)), atol=1e-12)


def test_a_global_shutter_or_no_time_between_neighbours_moves_nothing():
    poses = np.stack([se3_exp(t * TWIST) for t in (0.0, 0.1, 0.2)])
    assert not readout_motions(poses, np.array([0.0, 0.1, 0.2]), 0.0).any()
    still = readout_motions(poses, np.array([0.0, 0.0, 0.0]), 0.02)
    assert not still.any()
    assert not readout_motions(poses[:1], np.zeros(1), 0.02).any()


def test_rows_are_read_top_to_bottom_about_the_frames_pose():
    """Row v's pose is the frame's moved by ((v + 1/2) / H - 1/2) of the readout's motion: the first and last rows
    half a motion (less half a row) either side, mirror rows inverse to each other."""
    motion = 0.02 * TWIST
    rows = shutter_rows(motion, 6)
    np.testing.assert_allclose(rows[0], se3_exp(-5 / 12 * motion), atol=1e-14)
    np.testing.assert_allclose(rows[5], se3_exp(5 / 12 * motion), atol=1e-14)
    for v in range(6):
        np.testing.assert_allclose(rows[v] @ rows[5 - v], np.eye(4), atol=1e-14)
    assert readout_px(motion, 500.0, 2.0) == pytest.approx(
        0.5 * 500.0 * (np.linalg.norm(motion[:3]) / 2.0 + np.linalg.norm(motion[3:])))


@pytest.mark.parametrize("overrides, message", [({"readout_ms": -1.0}, "readout_ms = -1.0 must be at least 0"),
                                                ({"readout_ms": 20.0, "warp_views": False}, "needs warp_views")])
def test_bad_readout_settings_are_input_errors(overrides, message):
    with pytest.raises(InputError, match=message):
        validate_sections({"deblur": dataclasses.replace(PRESETS["fast"], **overrides)})


def test_the_re_blurred_renders_read_their_rows_along_the_readout(tmp_path):
    """Untrained (no step): the sharp renders are the same with and without a readout, and the re-blurred ones
    differ, the most in the first and last rows (the farthest from the frame's pose) and least in the middle."""
    from taichi_gs.io.sequence import read_color
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=64, height=48, frames=4, trajectory="turn", blur="extreme", seed=2)
    renders = {}
    for readout in (0.0, 30.0):
        sequence, out = synthetic_refine_outputs(tmp_path / f"r{readout:g}", clip, voxel=0.08)
        config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, iterations=0, k=5, adaptive_k=False,
                                     test_pose_iterations=0, holdout_every=0, readout_ms=readout, keep_frame=False)
        run_deblur(sequence, out, config)
        renders[readout] = {kind: np.stack([read_color(out / "deblur" / "renders" / kind / f"{n}.png")
                                            for n in sequence.names]) for kind in ("sharp", "reblurred")}
    np.testing.assert_array_equal(renders[0.0]["sharp"], renders[30.0]["sharp"])
    change = np.abs(renders[30.0]["reblurred"] - renders[0.0]["reblurred"]).mean(axis=(0, 2, 3))  # per row
    edges, middle = np.r_[change[:6], change[-6:]].mean(), change[21:27].mean()
    assert edges > 3 * middle and edges > 0.01


def test_held_out_frames_are_scored_against_the_sharp_render_as_the_shutter_reads_it(tmp_path):
    """With a readout, stage 3 writes renders/as_read/ (the sharp render with each row at its own pose: the
    middle rows are the sharp render's, the top and bottom rows moved) and eval scores the held-out frames and
    the dark holes against it, the sharpness on the global-shutter render; a rerun without a readout removes it,
    and eval goes back to the sharp render."""
    from taichi_gs.io.sequence import read_color
    from taichi_gs.noreference import dark_hole_fraction, gradient_energy
    from taichi_gs.noreference_report import _psnr, no_reference_metrics
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=64, height=48, frames=5, trajectory="turn", blur="extreme", seed=2)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.08)
    renders = out / "deblur" / "renders"
    for readout in (30.0, 0.0):
        config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, iterations=0, k=5, adaptive_k=False,
                                     test_pose_iterations=0, holdout_every=2, readout_ms=readout, keep_frame=False)
        run_deblur(sequence, out, config)
        test = no_reference_metrics(out, sequence)["per_view"]
        held_out = [view for view in test if view["split"] == "test"]
        assert (renders / "as_read").is_dir() == (readout > 0) and held_out
        for view in held_out:
            name, frame = view["frame"], sequence.color(view["index"])
            sharp = read_color(renders / "sharp" / f"{name}.png")
            scored = read_color(renders / ("as_read" if readout else "sharp") / f"{name}.png")
            assert view["held_out_psnr_db"] == pytest.approx(_psnr(scored, frame, None), abs=1e-9)
            assert view["dark_hole_fraction"] == pytest.approx(dark_hole_fraction(scored, frame), abs=1e-12)
            assert view["gradient_energy_ratio"] == pytest.approx(
                gradient_energy(sharp) / gradient_energy(frame), rel=1e-9)
            if readout:
                rows = np.abs(scored - sharp).mean(axis=(1, 2))
                assert rows[23:25].mean() < 0.03 and rows[:4].mean() > 5 * rows[23:25].mean()
                assert view["held_out_psnr_db"] != pytest.approx(_psnr(sharp, frame, None), abs=1e-3)


def _measured_readout_ms(tmp_path, readout_ms: float) -> float:
    """``bench/rolling_shutter_readout.py`` (pairs one frame apart) on a synthetic hand-held clip read out in
    ``readout_ms``."""
    import subprocess
    import sys
    from pathlib import Path

    clip = synth.SynthConfig(width=160, height=120, frames=24, trajectory="handheld", blur="moderate", seed=0,
                             readout_ms=readout_ms)
    folder = synth.generate(clip, tmp_path / f"clip{readout_ms:g}")
    bench = Path(__file__).resolve().parents[1] / "bench" / "rolling_shutter_readout.py"
    result = subprocess.run([sys.executable, str(bench), "--recording", str(folder), "--count", "24", "--gap", "1"],
                            capture_output=True, text=True, timeout=600, cwd=bench.parents[1])
    assert result.returncode == 0, result.stderr[-2000:]
    return float(result.stdout.split(" frames = ")[1].split(" ms")[0])


def test_the_readout_bench_finds_a_rolling_shutter_and_none_in_a_global_one(tmp_path):
    """The bench's estimate: near 0 for a global shutter, and for a 20 ms readout between 15 and 30 ms (it reads
    about 1.3x long on synthetic hand-held clips: docs/notebook/benchmarks-2026-11.md, "A rolling shutter in TUM's
    Kinect frames")."""
    assert abs(_measured_readout_ms(tmp_path, 0.0)) < 3.0
    assert 15.0 < _measured_readout_ms(tmp_path, 20.0) < 30.0


def test_kinect_v1_readings_know_their_readout_and_others_do_not():
    assert camera_readout_ms({"format": "tum", "camera": "fr1"}) == 25.0
    assert camera_readout_ms({"format": "7scenes", "camera": "registered"}) == 25.0
    assert camera_readout_ms({"format": "tum", "camera": "fr3"}) == 0.0  # not measured
    assert camera_readout_ms({"format": "taichi-gs"}) == 0.0


@pytest.mark.parametrize("camera_readout, readout_ms, expected", [(True, 0.0, 25.0), (False, 0.0, 0.0),
                                                                  (True, 10.0, 10.0)])
def test_the_fast_preset_models_a_known_cameras_rolling_shutter(tmp_path, camera_readout, readout_ms, expected):
    """A sequence read as TUM fr1 gets Kinect v1's readout from ``camera_readout`` (the fast preset's), unless
    ``readout_ms`` names one or the switch is off; the summary says which was modelled."""
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=48, height=32, frames=4, trajectory="turn", blur="extreme", seed=2)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.1)
    sequence.source = {**sequence.source, "format": "tum", "camera": "fr1"}
    assert PRESETS["fast"].camera_readout and not PRESETS["paper"].camera_readout
    config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, iterations=0, k=3, adaptive_k=False,
                                 test_pose_iterations=0, holdout_every=0, keep_frame=False,
                                 camera_readout=camera_readout, readout_ms=readout_ms)
    result = run_deblur(sequence, out, config)
    assert result.readout_ms == expected
    assert (f"rolling shutter {expected:g} ms" in result.summary()) == (expected > 0)
    assert (out / "deblur" / "renders" / "as_read").is_dir() == (expected > 0)


def test_a_pose_jump_between_neighbours_widens_the_anchors_margin_by_a_bounded_amount(tmp_path, monkeypatch):
    """A frame whose neighbours lie 20 m apart (a tracking failure) would skew its rows by hundreds of pixels:
    the anchors' margin grows by at most ``MAX_SKEW_MARGIN_SCALE`` x ``warp_px``."""
    from taichi_gs.stages.deblur import run as deblur
    from taichi_gs.standins import synthetic_refine_outputs

    clip = synth.SynthConfig(width=48, height=32, frames=4, trajectory="turn", blur="extreme", seed=2)
    sequence, out = synthetic_refine_outputs(tmp_path, clip, voxel=0.1)
    trajectory = out / "refine" / "trajectory.txt"
    lines = trajectory.read_text().splitlines()
    fields = lines[-1].split()
    fields[1] = f"{float(fields[1]) + 20.0:.6f}"  # the last frame 20 m off
    trajectory.write_text("\n".join(lines[:-1] + [" ".join(fields)]) + "\n")
    margins = []
    original = deblur.BlurScene

    def recording(*args, **kwargs):
        margins.append(kwargs.get("warp_margin", 0))
        return original(*args, **kwargs)

    monkeypatch.setattr(deblur, "BlurScene", recording)
    config = dataclasses.replace(PRESETS["fast"], iterations_per_view=0, iterations=0, k=3, adaptive_k=False,
                                 test_pose_iterations=0, holdout_every=0, keep_frame=False, readout_ms=30.0)
    run_deblur(sequence, out, config)
    assert margins[0] == deblur.warp_margin(config, deblur.MAX_SKEW_MARGIN_SCALE * config.warp_px)
