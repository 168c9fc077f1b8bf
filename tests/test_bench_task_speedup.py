"""bench/task_speedup.py: its arithmetic (per-kind speed-ups of two profiled runs, the split of a run's wall time
into the time inside its tasks and outside them), the whole script on a tiny run folder, and a refused one."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "task_speedup.py"
sys.path.insert(0, str(SCRIPT.parent))

from task_speedup import inside_outside, report, speedups  # noqa: E402

ONE = {"threads": 1, "wall_s": 30.0, "cpu_s": 30.0,
       "tasks": {"blend:1 range_for": [10, 20000.0], "adam_step:1 range_for": [10, 4000.0],
                 "only_here:1 range_for": [1, 1000.0]}}
MANY = {"threads": 4, "wall_s": 16.0, "cpu_s": 29.0,
        "tasks": {"blend:1 range_for": [10, 10000.0], "adam_step:1 range_for": [10, 2500.0]}}


def test_speedups_pair_the_kinds_both_runs_have_longest_first():
    assert speedups(ONE, MANY) == [("blend:1 range_for", 10, 20.0, 10.0), ("adam_step:1 range_for", 10, 4.0, 2.5)]


def test_inside_outside_splits_the_wall_time():
    assert inside_outside(ONE) == pytest.approx((25.0, 5.0))
    assert inside_outside(MANY) == pytest.approx((12.5, 3.5))


def test_report_prints_each_kind_and_the_stage(capsys):
    report(ONE, MANY)
    out = capsys.readouterr().out
    assert "| blend:1 range_for | 10 | 20.00 | 10.00 | 2.00 |" in out
    assert "| adam_step:1 range_for | 10 | 4.00 | 2.50 | 1.60 |" in out
    assert "speed-up 2.00" in out  # 25 s of tasks on one thread, 12.5 s on four
    assert "3.5 s outside them (22%)" in out
    assert "stage speed-up 1.88" in out  # 30 / 16


def test_task_speedup_profiles_a_run_folder_on_one_thread_and_the_default(tmp_path):
    """The whole script on a tiny stage-2 output: both profiled runs finish and the render's loops are listed."""
    from taichi_gs.standins import synthetic_refine_outputs
    from taichi_gs.synth import SynthConfig

    _, out = synthetic_refine_outputs(tmp_path, SynthConfig(width=48, height=32, frames=3, seed=1), voxel=0.08)
    result = subprocess.run([sys.executable, str(SCRIPT), "--run", str(out)], capture_output=True, text=True,
                            timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "| blend:1 range_for |" in result.stdout
    assert "1 thread: " in result.stdout and "stage speed-up" in result.stdout
    assert (out / "deblur" / "splats.ply").exists()


def test_task_speedup_names_a_failed_stage(tmp_path):
    """A run folder that the stage refuses stops the script with the stage's own error."""
    result = subprocess.run([sys.executable, str(SCRIPT), "--run", str(tmp_path / "missing")], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode != 0
    assert "run folder not found" in result.stderr
