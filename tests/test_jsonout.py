"""No NaN or Infinity in any JSON we write; bad poses are errors or reported drops, never silent."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from taichi_gs.cli import app
from taichi_gs.errors import InputError
from taichi_gs.io.jsonout import dumps, write_json
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import read_tum, write_tum
from taichi_gs.pipeline import write_run_info
from taichi_gs.report import evaluate_run
from taichi_gs.synth import SynthConfig, generate


def strict_loads(text: str):
    """json.loads that fails on NaN / Infinity, as jq, JavaScript and Go do."""
    def refuse(constant: str):
        raise ValueError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


def test_dumps_turns_non_finite_numbers_into_null_with_a_reason():
    data = {"ate_m": float("nan"), "psnr": np.float32("inf"), "ok": np.float64(1.5), "n": np.int64(3),
            "nested": {"values": [1.0, float("-inf")], "flag": np.bool_(True)}}
    parsed = strict_loads(dumps(data, reasons={"ate_m": "only 2 frames"}))
    assert parsed["ate_m"] is None and parsed["ate_m_null_reason"] == "only 2 frames"
    assert parsed["psnr"] is None and "inf" in parsed["psnr_null_reason"]
    assert parsed["ok"] == 1.5 and parsed["n"] == 3 and parsed["nested"] == {"values": [1.0, None], "flag": True}
    assert "NaN" not in dumps(data) and "Infinity" not in dumps(data)


def test_write_json_output_is_strict(tmp_path):
    write_json(tmp_path / "x.json", {"loss": [0.5, float("nan")]})
    assert strict_loads((tmp_path / "x.json").read_text()) == {"loss": [0.5, None]}


def test_a_zero_quaternion_in_a_trajectory_is_an_error_naming_the_line(tmp_path):
    path = tmp_path / "traj.txt"
    path.write_text("# t tx ty tz qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0 0\n0.2 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"zero quaternion \(line 3\)"):
        read_tum(path)


def test_a_zero_quaternion_in_ground_truth_is_an_error_not_a_silent_drop(tmp_path):
    seq = generate(SynthConfig(width=32, height=24, frames=3, blur="none", seed=1), tmp_path / "seq")
    lines = (seq / "groundtruth.txt").read_text().splitlines()
    body = [i for i, line in enumerate(lines) if line and not line.startswith("#")]
    parts = lines[body[1]].split()
    lines[body[1]] = " ".join(parts[:4] + ["0", "0", "0", "0"])
    (seq / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match="zero quaternion"):
        load_sequence(seq)


@pytest.fixture(scope="module")
def run_with_partial_ground_truth(tmp_path_factory) -> tuple[Path, Path]:
    """A run whose stage-1 trajectory is exact, on a sequence whose ground truth covers only the
    first two of its five frames (ATE then needs 3 frames: it cannot be computed)."""
    root = tmp_path_factory.mktemp("partial")
    seq = generate(SynthConfig(width=32, height=24, frames=5, blur="none", seed=3), root / "seq")
    sequence = load_sequence(seq)
    run = root / "run"
    write_run_info(run, sequence)
    write_tum(run / "pose" / "trajectory.txt", sequence.timestamps, sequence.gt_poses)
    write_tum(seq / "groundtruth.txt", sequence.timestamps[:2], sequence.gt_poses[:2])
    return run, seq


def test_metrics_json_has_null_with_reason_and_reports_dropped_frames(run_with_partial_ground_truth, tmp_path):
    run, _ = run_with_partial_ground_truth
    local = tmp_path / "run"
    shutil.copytree(run, local)
    evaluate_run(local)
    metrics = strict_loads((local / "metrics.json").read_text())
    pose = metrics["trajectory"]["pose"]
    assert pose["ate_m"] is None and "only 2 frame" in pose["ate_m_null_reason"]
    assert pose["frames"] == 2
    assert math.isclose(pose["rpe_trans_m"], 0.0, abs_tol=1e-6)  # one consecutive pair is enough for RPE
    (drop,) = pose["dropped_frames"]
    assert drop["count"] == 3 and "no ground truth" in drop["reason"] and len(drop["frames"]) == 3


def test_eval_json_output_is_strict_json(run_with_partial_ground_truth, tmp_path):
    run, _ = run_with_partial_ground_truth
    local = tmp_path / "run"
    shutil.copytree(run, local)
    result = CliRunner().invoke(app, ["eval", str(local), "--json"])
    assert result.exit_code == 0, result.output
    parsed = strict_loads(result.stdout)
    assert parsed["trajectory"]["pose"]["ate_m"] is None
