"""bench/task_speedup.py's arithmetic: per-kind speed-ups of two profiled runs, and the split of a run's wall time
into the time inside its tasks and outside them."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

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
