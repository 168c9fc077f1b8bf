"""Stage 3's initial exposures (issue 84): the fast preset opens each exposure to a share of the motion to its
neighbours that lies closer to the truth than the old +-1/4 rule, on synthetic extreme blur (the shutter open for
the whole frame interval) and on averaged sharp frames (W consecutive frames: (W - 1) / W of the interval)."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from taichi_gs.cli import app
from taichi_gs.geometry import backproject, invert, project, transform, virtual_pose
from taichi_gs.io.load import load_sequence
from taichi_gs.io.sequence import Sequence
from taichi_gs.stages.deblur.config import PRESETS
from taichi_gs.stages.deblur.exposures import initial_offsets
from taichi_gs.synth import SynthConfig, generate

OLD_FRACTION = 0.5  # offsets at +-1/4 of the motion to the neighbours


def exposure_error_px(sequence: Sequence, fraction: float) -> float:
    """Mean image distance (pixels) between the sensor's points seen through the initial start/end poses (at the
    true mid poses) and through the true ones."""
    poses = sequence.gt_poses
    offsets = initial_offsets(poses, fraction)
    K, errors = sequence.K(), []
    for i in range(len(sequence)):
        depth = sequence.depth(i)
        points = transform(poses[i], backproject(depth, K)[depth > 0])
        for j, tau in enumerate((0.0, 1.0)):
            guess = project(transform(invert(virtual_pose(poses[i], *offsets[i], tau)), points), K)
            truth = project(transform(invert(sequence.exposure_poses[i, j]), points), K)
            errors.append(np.linalg.norm(guess - truth, axis=1).mean())
    return float(np.mean(errors))


@pytest.fixture(scope="module")
def extreme(tmp_path_factory) -> Sequence:
    return load_sequence(generate(SynthConfig(width=64, height=48, frames=6, trajectory="handheld", blur="extreme",
                                              seed=2), tmp_path_factory.mktemp("extreme") / "seq"))


def averaged(tmp_path_factory, window: int) -> Sequence:
    """Sharp synthetic frames averaged W at a time by ``taichi-gs import --average``."""
    root = tmp_path_factory.mktemp(f"average{window}")
    sharp = generate(SynthConfig(width=64, height=48, frames=4 * window, trajectory="handheld", blur="none", seed=4),
                     root / "sharp")
    result = CliRunner().invoke(app, ["import", str(sharp), "--out", str(root / "avg"), "--average", str(window)])
    assert result.exit_code == 0, result.output
    return load_sequence(root / "avg")


def test_fast_opens_synthetic_extreme_blur_closer_to_the_truth(extreme):
    fast = PRESETS["fast"].initial_exposure_fraction
    assert exposure_error_px(extreme, fast) < 0.7 * exposure_error_px(extreme, OLD_FRACTION)


@pytest.mark.parametrize("window", [3, 5, 7])
def test_fast_opens_averaged_frames_closer_to_the_truth(tmp_path_factory, window):
    sequence = averaged(tmp_path_factory, window)
    fast = PRESETS["fast"].initial_exposure_fraction
    assert exposure_error_px(sequence, fast) < exposure_error_px(sequence, OLD_FRACTION)


def test_paper_keeps_the_methods_rule():
    assert PRESETS["paper"].initial_exposure_fraction == OLD_FRACTION
