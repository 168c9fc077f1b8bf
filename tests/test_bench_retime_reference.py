"""bench/retime_reference.py: stamps scattered about a regular clock (with a dropped frame) come back on the clock,
and the written reference holds the capture's pose at each frame's regular time plus the shift, at its own stamp."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np

BENCH = Path(__file__).resolve().parents[1] / "bench"
sys.path.insert(0, str(BENCH))

from retime_reference import regular_times  # noqa: E402

from taichi_gs.io.trajectory import read_tum, write_tum  # noqa: E402

PERIOD = 1 / 30
RATE = np.radians(60.0)  # the capture turns about z at 60 deg/s


def _clock_and_stamps(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    clock = 100.0 + PERIOD * np.delete(np.arange(120), 57)  # frame 57 dropped
    return clock, clock + 0.001 * rng.standard_normal(len(clock))


def test_scattered_stamps_come_back_on_the_regular_clock():
    clock, stamps = _clock_and_stamps(np.random.default_rng(0))
    error = regular_times(stamps) - clock
    assert np.std(stamps - clock) > 0.0008
    assert np.sqrt(np.mean(error**2)) < 0.0003 and np.abs(error).max() < 0.001  # worst at the ends: a one-sided line


def test_the_reference_is_written_at_the_stamps_with_the_pose_at_the_regular_time_plus_the_shift(tmp_path):
    clock, stamps = _clock_and_stamps(np.random.default_rng(1))
    capture = np.arange(99.0, 105.0, 0.01)
    poses = np.tile(np.eye(4), (len(capture), 1, 1))
    for k, t in enumerate(capture):
        poses[k, :3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, RATE * (t - 99.0)]))[0]
    write_tum(tmp_path / "groundtruth.txt", capture, poses)
    (tmp_path / "rgb.txt").write_text("# timestamp filename\n" + "".join(f"{s:.6f} rgb/{s:.6f}.png\n" for s in stamps))
    subprocess.run([sys.executable, str(BENCH / "retime_reference.py"), str(tmp_path / "groundtruth.txt"),
                    str(tmp_path / "rgb.txt"), "--shift-ms", "-10", "--out", str(tmp_path / "R.txt")], check=True)
    times, poses = read_tum(tmp_path / "R.txt")
    np.testing.assert_allclose(times, stamps, atol=1e-6)
    angles = np.arctan2(poses[:, 1, 0], poses[:, 0, 0])
    expected = RATE * (clock - 0.010 - 99.0)
    wrapped = np.angle(np.exp(1j * (angles - expected)))
    assert np.degrees(np.sqrt(np.mean(wrapped**2))) < 0.02  # 0.33 ms at 60 deg/s; the stamps are 1 ms off (0.06 deg)


def test_stamps_in_a_repeating_pattern_are_read_at_the_clocks_period_not_the_patterns_median_step():
    clock = 100.0 + PERIOD * np.arange(120)
    stamps = clock + 0.001 * np.array([0.0, -4 / 3, -8 / 3])[np.arange(120) % 3]  # steps of 32, 32, 36 ms
    assert abs(np.median(np.diff(stamps)) - 0.032) < 1e-6
    offset = regular_times(stamps) - clock
    assert np.std(offset) < 0.0002 and abs(np.mean(offset) + 0.004 / 3) < 0.0002  # one line, the pattern's mean
