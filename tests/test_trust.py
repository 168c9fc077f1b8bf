"""Runs you can trust: loud failures with one-line errors, one writer per output folder, nothing
overwritten that the user did not ask for, results reproducible from what is recorded."""

from __future__ import annotations

import errno
import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from taichi_gs.cli import app
from taichi_gs.errors import DivergenceError, InputError
from taichi_gs.io.atomic import write_text
from taichi_gs.io.load import load_sequence
from taichi_gs.io.lock import output_lock
from taichi_gs.io.sequence import IntrinsicsOverride
from taichi_gs.stages import pose as pose_stage
from taichi_gs.stages.divergence import DivergenceGuard
from taichi_gs.stages.pose import PoseConfig, run_pose
from taichi_gs.synth import SynthConfig, generate


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "taichi_gs.cli", "--arch", "cpu", *args], capture_output=True,
                          text=True, timeout=300)


def one_line_error(result) -> str:
    """The error line of a failed command; fails the test on a traceback."""
    stderr = result.stderr if hasattr(result, "stderr") and result.stderr is not None else result.output
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1, stderr
    return lines[0]


@pytest.fixture(scope="module")
def small_seq(tmp_path_factory) -> Path:
    return generate(SynthConfig(width=64, height=48, frames=3, trajectory="handheld", blur="moderate", seed=1),
                    tmp_path_factory.mktemp("trust") / "seq")


def test_a_programming_error_in_a_pair_ends_the_run(tmp_path, small_seq, monkeypatch):
    def broken(*args, **kwargs):
        raise TypeError("a bug")

    monkeypatch.setattr(pose_stage, "estimate_relative_pose", broken)
    with pytest.raises(TypeError, match="a bug"):
        run_pose(load_sequence(small_seq), tmp_path, PoseConfig())


def test_bad_config_enum_exits_2_before_any_work(tmp_path, small_seq):
    config = tmp_path / "bad.toml"
    config.write_text('[pose]\nflow_preset = "nonsense"\n')
    out = tmp_path / "run"
    result = cli("reconstruct", str(small_seq), "--out", str(out), "--config", str(config))
    assert result.returncode == 2
    assert "flow_preset" in one_line_error(result)
    assert not (out / "pose").exists()


def test_huge_or_nan_learning_rates_exit_2(tmp_path, small_seq):
    for value in ("1e12", "nan"):
        config = tmp_path / f"lr_{value}.toml"
        config.write_text(f"[refine]\nlr_means = {value}\n")
        result = cli("reconstruct", str(small_seq), "--out", str(tmp_path / value), "--config", str(config))
        assert result.returncode == 2 and "lr_means" in one_line_error(result)


def test_export_into_the_input_folder_is_refused_and_the_input_unchanged(tmp_path, small_seq):
    out = tmp_path / "run"
    assert cli("pose", str(small_seq), "--out", str(out)).returncode == 0
    before = {p: p.read_bytes() for p in small_seq.rglob("*") if p.is_file()}
    for dest in (small_seq, small_seq / "rgb"):
        result = cli("export", str(out), "--format", "ply", "--dest", str(dest))
        assert result.returncode == 2 and "inside the input folder" in one_line_error(result)
    after = {p: p.read_bytes() for p in small_seq.rglob("*") if p.is_file()}
    assert after == before


def test_a_second_run_on_a_held_output_folder_is_refused(tmp_path, small_seq):
    out = tmp_path / "run"
    with output_lock(out):
        result = cli("pose", str(small_seq), "--out", str(out))
    assert result.returncode == 2
    assert f"in use by pid {os.getpid()}" in one_line_error(result)
    assert not (out / "pose").exists()


def test_a_lock_left_by_a_killed_run_is_taken_over(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / ".lock").write_text(json.dumps({"pid": 999999, "host": "gone", "command": "x", "started": 0}))
    with output_lock(out):
        assert json.loads((out / ".lock").read_text())["pid"] == os.getpid()


def test_a_depth_scale_five_times_off_is_caught_with_the_likely_scale(own_layout):
    with pytest.raises(InputError, match=r"--depth-scale 5000"):  # 2 m stored at 5000/m, read at 1000/m
        load_sequence(own_layout, IntrinsicsOverride(depth_scale=1000.0))
    with pytest.raises(InputError, match=r"--depth-scale 5000"):  # 10x too short: 0.2 m
        load_sequence(own_layout, IntrinsicsOverride(depth_scale=50000.0))
    trusted = load_sequence(own_layout, IntrinsicsOverride(depth_scale=1000.0), trust_depth_scale=True)
    assert float(np.median(trusted.depth(0))) == pytest.approx(10.0)


def test_non_utf8_frame_list_is_a_one_line_error(tmp_path, own_layout):
    (own_layout / "frames.txt").write_bytes(b"0.0 rgb/\xff\xfe.png depth/x.png\n")
    result = cli("pose", str(own_layout), "--out", str(tmp_path / "run"))
    assert result.returncode == 2 and "not UTF-8" in one_line_error(result)


def test_out_that_is_a_file_is_a_one_line_error(tmp_path, own_layout):
    target = tmp_path / "file"
    target.write_text("x")
    for args in (("pose", str(own_layout), "--out", str(target)), ("synth", str(target), "--frames", "2")):
        result = cli(*args)
        assert result.returncode == 2 and "is a file" in one_line_error(result)
    assert target.read_text() == "x"


@pytest.mark.parametrize("code, hint", [(errno.ENOSPC, "free disk space"), (errno.EROFS, "writable file system")])
def test_disk_full_or_read_only_output_is_a_one_line_error(tmp_path, own_layout, monkeypatch, code, hint):
    import taichi_gs.io.atomic as atomic

    def failing(*args, dir=None, **kwargs):
        raise OSError(code, os.strerror(code), str(dir))

    # every atomic write starts with a temporary file: failing there reaches each writer however it imported
    # write_text (a module first imported during the run would keep a patched name after the test)
    monkeypatch.setattr(atomic.tempfile, "mkstemp", failing)
    result = CliRunner().invoke(app, ["--arch", "cpu", "pose", str(own_layout), "--out", str(tmp_path / "run")])
    assert result.exit_code == 2
    assert hint in one_line_error(result)


def test_eval_of_garbage_trajectory_or_run_record_is_a_one_line_error(tmp_path, own_layout):
    garbage = tmp_path / "garbage.txt"
    garbage.write_bytes(b"\x00\x01 not a trajectory\n")
    result = cli("eval", "--traj", str(garbage), "--gt-traj", str(own_layout / "groundtruth.txt"))
    assert result.returncode == 2 and "garbage.txt" in one_line_error(result)
    run = tmp_path / "run"
    run.mkdir()
    (run / "run.json").write_text("{broken")
    for command in ("eval", "refine", "deblur", "render", "export"):
        result = cli(command, str(run))
        assert result.returncode == 2 and "corrupt run record" in one_line_error(result), command


def test_synth_refuses_huge_requests_and_never_mixes_old_frames(tmp_path):
    assert cli("synth", str(tmp_path / "huge"), "--frames", "1000000000").returncode == 2
    out = tmp_path / "seq"
    assert cli("synth", str(out), "--frames", "4", "--width", "32", "--height", "24").returncode == 0
    result = cli("synth", str(out), "--frames", "2", "--width", "32", "--height", "24")
    assert result.returncode == 2 and "not empty" in one_line_error(result)
    assert cli("synth", str(out), "--frames", "2", "--width", "32", "--height", "24", "--overwrite").returncode == 0
    assert len(list((out / "rgb").iterdir())) == 2


def test_cuda_without_a_gpu_is_refused_by_every_stage_command(tmp_path, own_layout):
    from taichi_gs.kernels import runtime

    if runtime.cuda_available():
        pytest.skip("this machine has a CUDA GPU")
    result = subprocess.run([sys.executable, "-m", "taichi_gs.cli", "--arch", "cuda", "pose", str(own_layout),
                             "--out", str(tmp_path / "run")], capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "cuda" in one_line_error(result).lower()
    assert not (tmp_path / "run" / "pose").exists()


def test_outputs_honour_the_umask(tmp_path):
    previous = os.umask(0o022)
    try:
        write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(previous)
    assert stat.S_IMODE((tmp_path / "a.txt").stat().st_mode) == 0o644


def test_divergence_guard_catches_non_finite_runaway_and_flying_parameters():
    guard = DivergenceGuard("stage 2 (refine)", np.zeros(3), extent=2.0, patience=3)
    guard.check_step(0, 1.0, [np.zeros(6)])
    with pytest.raises(DivergenceError, match="iteration 1: loss is nan"):
        guard.check_step(1, float("nan"))
    with pytest.raises(DivergenceError, match="non-finite gradient"):
        guard.check_step(2, 1.0, [np.array([0.0, np.inf])])
    for it in range(2):
        guard.check_step(3 + it, 500.0)  # a spike or two is not a runaway
    guard.check_step(5, 1.0)
    with pytest.raises(DivergenceError, match="ran away"):
        for it in range(3):
            guard.check_step(6 + it, 500.0)
    guard.check_parameters(9, np.ones((4, 3)))
    with pytest.raises(DivergenceError, match="flew"):
        guard.check_parameters(10, np.array([[0.0, 0.0, 3e12]]))
    with pytest.raises(DivergenceError, match="non-finite parameters"):
        guard.check_parameters(11, np.ones((4, 3)), np.array([np.nan]))
