"""Trajectory and image metrics, with evo's command-line tools as the oracle where installed."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from taichi_gs import geometry as g
from taichi_gs.evaluate import (ate, inverse_depth_rmse, match_by_time, psnr, rotation_drift_deg, rotation_scale, rpe,
                                ssim, trajectory_errors)
from taichi_gs.io.trajectory import write_tum


def drifting_pair(n=25, seed=0):
    rng = np.random.default_rng(seed)
    gt = [np.eye(4)]
    for _ in range(n - 1):
        gt.append(gt[-1] @ g.se3_exp(np.r_[rng.normal(size=3) * 0.1, rng.normal(size=3) * 0.05]))
    gt = np.stack(gt)
    est = np.stack([g.se3_exp(np.r_[rng.normal(size=3) * 0.02, rng.normal(size=3) * 0.01]) @ T for T in gt])
    return g.se3_exp([1, 2, 3, 0.3, 0.2, 0.1]) @ est, gt


def test_ate_is_invariant_to_a_rigid_transform_of_the_estimate():
    est, gt = drifting_pair()
    assert ate(gt, gt) < 1e-12
    moved = g.se3_exp([5, -1, 2, 1.0, 0.3, -0.7]) @ est
    assert abs(ate(moved, gt) - ate(est, gt)) < 1e-9 and ate(est, gt) > 0.01


def test_rpe_of_known_constant_error():
    _, gt = drifting_pair()
    offset = g.pose_from_rt(g.so3_exp([0, 0, np.radians(0.5)]), [0.01, 0, 0])
    est = [gt[0]]
    for i in range(len(gt) - 1):
        est.append(est[-1] @ (g.invert(gt[i]) @ gt[i + 1]) @ offset)
    trans, rot = rpe(np.stack(est), gt)
    assert trans == pytest.approx(0.01, abs=1e-9) and rot == pytest.approx(0.5, abs=1e-7)


def chained_with(gt, offsets):
    """The reference's relative poses chained with offsets[i] applied after pair i."""
    est = [gt[0]]
    for i in range(len(gt) - 1):
        est.append(est[-1] @ (g.invert(gt[i]) @ gt[i + 1]) @ offsets[i])
    return np.stack(est)


def test_rotation_drift_is_the_systematic_part_of_the_rpe_rotation():
    _, gt = drifting_pair(n=25)
    turn = g.pose_from_rt(g.so3_exp([0, np.radians(0.03), 0]), [0, 0, 0])
    back = g.pose_from_rt(g.so3_exp([0, -np.radians(0.03), 0]), [0, 0, 0])
    steady = chained_with(gt, [turn] * 24)  # turns 0.03 deg too far at every pair: drifts
    alternating = chained_with(gt, [turn, back] * 12)  # the same error per pair, cancelling: no drift
    assert rotation_drift_deg(steady, gt) == pytest.approx(0.03, abs=1e-9)
    assert rotation_drift_deg(alternating, gt) < 1e-9
    assert rpe(alternating, gt)[1] == pytest.approx(0.03, abs=1e-9)
    assert trajectory_errors(steady, gt).as_dict()["rpe_rot_drift_deg"] == pytest.approx(0.03, abs=1e-9)
    assert np.isnan(rotation_drift_deg(steady[:1], gt[:1]))


def turning_steps(n=40, seed=1):
    """se(3) steps of a camera that pans about 1.5 deg per frame (its axis wobbling) while it moves."""
    rng = np.random.default_rng(seed)
    return [np.r_[rng.normal(size=3) * 0.01, np.radians(1.5) * (np.array([0.1, 1.0, 0.2]) + rng.normal(size=3) * 0.2)]
            for _ in range(n - 1)]


def chained_steps(steps, rotation_factor=1.0):
    """Poses from identity through ``steps``, each step's rotation times ``rotation_factor``."""
    poses = [np.eye(4)]
    for step in steps:
        poses.append(poses[-1] @ g.se3_exp(np.r_[step[:3], rotation_factor * step[3:]]))
    return np.stack(poses)


def test_rotation_scale_reads_how_much_of_the_reference_turn_the_estimate_turns():
    steps = turning_steps()
    gt = chained_steps(steps)
    assert rotation_scale(gt, gt) == pytest.approx(1.0, abs=1e-12)
    # every relative rotation 10% short, in another world frame: 0.9 at every span
    short = g.se3_exp([1, 2, 3, 0.3, 0.2, 0.1]) @ chained_steps(steps, 0.9)
    assert rotation_scale(short, gt) == pytest.approx(0.9, abs=0.005)
    assert rotation_scale(short, gt, span=1) == pytest.approx(0.9, abs=0.005)
    # zero-mean noise on every pose does not move it; a turn the wrong way reads negative
    rng = np.random.default_rng(3)
    noisy = np.stack([T @ g.se3_exp(np.r_[0, 0, 0, rng.normal(size=3) * np.radians(0.3)]) for T in gt])
    assert rotation_scale(noisy, gt) == pytest.approx(1.0, abs=0.02)
    backwards = chained_steps([np.r_[s[:3], -s[3:]] for s in steps])
    assert rotation_scale(backwards, gt) == pytest.approx(-1.0, abs=0.01)
    # spans without turning carry no axis; frames without a reference are skipped
    still = np.stack([g.se3_exp([0.01 * i, 0, 0, 0, 0, 0]) for i in range(20)])
    assert np.isnan(rotation_scale(still, still))
    gt_nan = gt.copy()
    gt_nan[5] = np.nan
    assert rotation_scale(short, gt_nan) == pytest.approx(0.9, abs=0.005)
    assert trajectory_errors(short, gt).as_dict()["rotation_scale"] == pytest.approx(rotation_scale(short, gt))


def test_nan_reference_frames_are_skipped():
    est, gt = drifting_pair()
    gt_nan = gt.copy()
    gt_nan[3] = np.nan
    errors = trajectory_errors(est, gt_nan)
    assert errors.frames == len(gt) - 1 and np.isfinite(errors.ate_m) and np.isfinite(errors.rpe_rot_deg)


def test_match_by_time():
    i, j = match_by_time(np.array([0.0, 1.0, 2.0]), np.array([0.005, 2.0, 5.0]))
    assert list(i) == [0, 2] and list(j) == [0, 1]


def evo_tool(name):
    """evo's command, on PATH or beside this interpreter (an unactivated virtual environment)."""
    beside = Path(sys.executable).parent / name
    return str(beside) if beside.is_file() else shutil.which(name)


def evo_stat(tool, args, tmp_path):
    out = tmp_path / f"{tool}_{'_'.join(args)}.zip"
    subprocess.run([evo_tool(tool), "tum", str(tmp_path / "gt.txt"), str(tmp_path / "est.txt"), "-a", "--no_warnings",
                    "--save_results", str(out), *args], check=True, capture_output=True)
    with zipfile.ZipFile(out) as z:
        return json.loads(z.read("stats.json"))["rmse"]


@pytest.mark.skipif(evo_tool("evo_ape") is None, reason="evo (test oracle) not installed")
@pytest.mark.parametrize("seed", [0, 1])
def test_matches_evo_to_1e6(tmp_path, seed):
    est, gt = drifting_pair(seed=seed)
    t = np.arange(len(gt)) / 30.0
    write_tum(tmp_path / "gt.txt", t, gt)
    write_tum(tmp_path / "est.txt", t, est)
    ours = trajectory_errors(est, gt)
    assert ours.ate_m == pytest.approx(evo_stat("evo_ape", [], tmp_path), abs=1e-6)
    assert ours.rpe_trans_m == pytest.approx(evo_stat("evo_rpe", ["-r", "trans_part", "--delta", "1"], tmp_path), abs=1e-6)
    assert ours.rpe_rot_deg == pytest.approx(evo_stat("evo_rpe", ["-r", "angle_deg", "--delta", "1"], tmp_path), abs=1e-6)


def test_psnr_and_ssim():
    rng = np.random.default_rng(0)
    ref = rng.uniform(size=(40, 50, 3))
    noisy = np.clip(ref + rng.normal(scale=0.1, size=ref.shape), 0, 1)
    mse = np.mean((noisy - ref) ** 2)
    assert psnr(noisy, ref) == pytest.approx(-10 * np.log10(mse))
    noisier = np.clip(ref + rng.normal(scale=0.3, size=ref.shape), 0, 1)
    assert ssim(ref, ref) == pytest.approx(1.0) and 0 < ssim(noisier, ref) < ssim(noisy, ref) < 0.99


def test_inverse_depth_rmse_ignores_invalid_pixels():
    ref = np.full((4, 4), 2.0)
    est = np.full((4, 4), 4.0)
    est[0, 0] = 0.0
    assert inverse_depth_rmse(est, ref) == pytest.approx(0.25)
