"""bench/launch_cores.py's arithmetic: uniform work's cores interpolated by launch length, and the ceiling of a
profiled run's tasks."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from launch_cores import task_ceiling, uniform_cores  # noqa: E402

CURVE = [{"parallel": {"wall_ms": 10.0, "cores": 1.9}}, {"parallel": {"wall_ms": 1.0, "cores": 1.5}}]


def test_uniform_cores_interpolates_in_log_length_and_holds_at_the_ends():
    assert uniform_cores(CURVE, 1.0) == pytest.approx(1.5)
    assert uniform_cores(CURVE, 10.0) == pytest.approx(1.9)
    assert uniform_cores(CURVE, 10 ** 0.5) == pytest.approx(1.7)  # halfway in log(ms)
    assert uniform_cores(CURVE, 0.1) == pytest.approx(1.5)
    assert uniform_cores(CURVE, 100.0) == pytest.approx(1.9)


def test_task_ceiling_weights_parallel_tasks_by_their_time_and_serial_ones_at_one_core():
    tasks = [("blend_c3_0_kernel_1_range_for", 10.0), ("blend_c3_0_kernel_0_serial", 10.0),
             ("adam_step_c9_0_kernel_1_range_for", 1.0)]
    assert task_ceiling(tasks, CURVE) == pytest.approx((10 * 1.9 + 10 * 1.0 + 1 * 1.5) / 21)

