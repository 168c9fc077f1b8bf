"""The end-to-end command under interruption and bad input: killed runs resume to the same result,
the input folder is never written to, divergence and missing depth end with clear messages."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from taichi_gs.evaluate import ate
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import read_tum
from taichi_gs.synth import SynthConfig, generate

# Small enough for a few seconds per stage on 2 cores, long enough to be caught mid-stage (each stage checkpoints
# at least twice); iterations_per_view = 0 keeps stage 3 at its 80 iterations (the fast preset would raise them).
TINY_CONFIG = """
[pose]
icp_from_prior = false
pose_graph = false

[refine]
iterations_per_frame = 20
prune_every_per_frame = 10
reset_every_per_frame = 15
checkpoint_every = 20

[deblur]
iterations = 80
iterations_per_view = 0
k = 3
checkpoint_every = 20
test_pose_iterations = 3
densify_from = 20
densify_until = 60
densify_every = 20
"""
# What shows that a stage is under way (and has something to resume from).
IN_PROGRESS = {"pose": "pose/pairs/000001.json", "refine": "refine/checkpoint.npz", "deblur": "deblur/checkpoint.npz"}


def taichi_gs(*args: str, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "taichi_gs.cli", "--arch", "cpu", *args], capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """A 6-frame 80x60 extreme-blur sequence, the tiny config, and one uninterrupted run."""
    root = tmp_path_factory.mktemp("robust")
    seq = generate(SynthConfig(width=80, height=60, frames=6, trajectory="handheld", blur="extreme", seed=5), root / "seq")
    config = root / "tiny.toml"
    config.write_text(TINY_CONFIG)
    reference = root / "reference"
    result = taichi_gs("reconstruct", str(seq), "--out", str(reference), "--config", str(config))
    assert result.returncode == 0, result.stderr
    return {"seq": seq, "config": config, "reference": reference}


def _final_ate(run: Path, seq: Path) -> float:
    sequence = load_sequence(seq)
    _, poses = read_tum(run / "deblur" / "trajectory.txt")
    return ate(poses, sequence.gt_poses)


def _kill_during(stage: str, sig: int, seq: Path, out: Path, config: Path) -> tuple[int, str]:
    """Start a run, send ``sig`` once ``stage`` is under way; return (exit code, stderr)."""
    log = out.parent / "stderr.txt"
    with open(log, "w") as stderr:
        process = subprocess.Popen(
            [sys.executable, "-m", "taichi_gs.cli", "--arch", "cpu", "reconstruct", str(seq), "--out", str(out),
             "--config", str(config)], stdout=subprocess.DEVNULL, stderr=stderr,
            # a shell's background job ignores SIGINT, and a child would inherit that: restore the default
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        deadline = time.monotonic() + 240
        while not (out / IN_PROGRESS[stage]).exists():
            if process.poll() is not None or time.monotonic() > deadline:
                process.kill()
                pytest.fail(f"the run ended before stage {stage} was under way: {log.read_text()[-500:]}")
            time.sleep(0.01)
        process.send_signal(sig)
        process.wait(timeout=60)
    return process.returncode, log.read_text()


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGKILL], ids=["SIGINT", "SIGKILL"])
@pytest.mark.parametrize("stage", ["pose", "refine", "deblur"])
def test_a_run_killed_in_any_stage_resumes_to_the_uninterrupted_result(tiny, tmp_path, stage, sig):
    out = tmp_path / "run"
    returncode, stderr = _kill_during(stage, sig, tiny["seq"], out, tiny["config"])
    if sig == signal.SIGINT:
        assert returncode == 130
        assert "interrupted" in stderr and "rerun the same command to resume" in stderr
    else:
        assert returncode == -signal.SIGKILL
    assert not (out / stage / "done.json").exists()

    result = taichi_gs("reconstruct", str(tiny["seq"]), "--out", str(out), "--config", str(tiny["config"]))
    assert result.returncode == 0, result.stderr
    skipped = [s for s in ("pose", "refine") if f"{s}: already done, skipped" in result.stderr]
    assert skipped == ["pose", "refine"][: ["pose", "refine", "deblur"].index(stage)]
    for name in ("splats.ply", "trajectory.txt", "exposure.txt", "split.json"):
        assert (out / "deblur" / name).is_file()
    assert abs(_final_ate(out, tiny["seq"]) - _final_ate(tiny["reference"], tiny["seq"])) < 0.003


def _snapshot(folder: Path) -> dict[str, tuple[str, float]]:
    return {str(p.relative_to(folder)): (hashlib.sha1(p.read_bytes()).hexdigest(), p.stat().st_mtime)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_input_folder_is_never_written_to(tiny, tmp_path):
    before = _snapshot(tiny["seq"])
    os.chmod(tiny["seq"], 0o555)
    try:
        out = tmp_path / "run"
        assert taichi_gs("reconstruct", str(tiny["seq"]), "--out", str(out), "--config", str(tiny["config"])).returncode == 0
        assert taichi_gs("eval", str(out)).returncode == 0
        assert taichi_gs("export", str(out), "--format", "nerfstudio").returncode == 0
    finally:
        os.chmod(tiny["seq"], 0o755)
    assert _snapshot(tiny["seq"]) == before


def test_output_inside_the_input_is_refused(tiny):
    result = taichi_gs("reconstruct", str(tiny["seq"]), "--out", str(tiny["seq"] / "out"))
    assert result.returncode == 2 and "inside the input folder" in result.stderr
    assert not (tiny["seq"] / "out").exists()


def test_eval_reports_images_stages_and_versions(tiny):
    assert taichi_gs("eval", str(tiny["reference"])).returncode == 0
    metrics = json.loads((tiny["reference"] / "metrics.json").read_text())
    assert set(metrics["trajectory"]) == {"pose", "refine", "deblur"}
    assert set(metrics["stages"]) == {"pose", "refine", "deblur"}
    assert all(s["seconds"] > 0 and s["peak_rss_mb"] > 50 for s in metrics["stages"].values())
    test = metrics["images"]["test"]
    assert test["views"] == 2 and 5 < test["psnr_db"] < 60 and 0 < test["ssim"] <= 1
    assert test["inverse_depth_rmse"] < 0.2
    assert metrics["images"]["lpips"].startswith("unavailable")
    no_reference = metrics["no_reference"]
    assert no_reference["test"]["views"] == 2 and no_reference["test"]["reblur_psnr_db"] > 15
    assert no_reference["protocol"].startswith("held-out views: frames 1, 1 + 3")
    assert metrics["arch"] == "cpu" and "taichi" in metrics["versions"]
    for name in ("trajectory_top.png", "position_error.png", "test_views.png"):
        assert (tiny["reference"] / "report" / name).is_file()


def test_frames_without_depth_still_finish_with_weak_pairs_reported(tiny, tmp_path):
    import shutil

    import cv2

    seq = tmp_path / "seq"
    shutil.copytree(tiny["seq"], seq)
    depth_path = sorted((seq / "depth").glob("*.png"))[3]
    cv2.imwrite(str(depth_path), np.zeros(cv2.imread(str(depth_path), cv2.IMREAD_UNCHANGED).shape, np.uint16))
    out = tmp_path / "run"
    result = taichi_gs("reconstruct", str(seq), "--out", str(out), "--config", str(tiny["config"]))
    assert result.returncode == 0, result.stderr
    assert "2 weak" in result.stderr
    assert f"{depth_path}: 0 pixels of usable depth" in result.stderr  # the file is named, once
    assert result.stderr.count("pixels of usable depth") == 1
    pairs = json.loads((out / "pose" / "pairs.json").read_text())["pairs"]
    assert [p["index"] for p in pairs if p["weak"]] == [2, 3]


def test_a_diverging_optimiser_stops_naming_stage_and_iteration(tiny, tmp_path, monkeypatch):
    import shutil

    from typer.testing import CliRunner

    from taichi_gs.cli import app
    from taichi_gs.stages.refine.model import DepthRefiner

    run = tmp_path / "run"
    shutil.copytree(tiny["reference"], run, ignore=shutil.ignore_patterns("refine", "deblur"))

    def diverged(self, *args, **kwargs):
        return {"depth": float("nan"), "opacity": 0.0}, np.full(6, np.nan)

    monkeypatch.setattr(DepthRefiner, "step", diverged)
    result = CliRunner().invoke(app, ["--arch", "cpu", "refine", str(run), "--config", str(tiny["config"])])
    assert result.exit_code == 4
    assert "stage 2 (refine) diverged at iteration 0" in result.output
    assert not (run / "refine" / "trajectory.txt").exists()


@pytest.mark.parametrize("stage", ["refine", "deblur"])
def test_divergence_mid_stage_exits_4_keeping_the_last_good_checkpoint(tiny, tmp_path, monkeypatch, stage):
    import shutil

    from typer.testing import CliRunner

    from taichi_gs.cli import app
    from taichi_gs.stages.deblur.model import BlurScene
    from taichi_gs.stages.refine.model import DepthRefiner

    run = tmp_path / "run"
    kept = ("pose",) if stage == "refine" else ("pose", "refine")
    shutil.copytree(tiny["reference"], run, ignore=lambda folder, names: [
        n for n in names if Path(folder) == tiny["reference"] and n not in (*kept, "run.json", "config.toml")])
    model = DepthRefiner if stage == "refine" else BlurScene
    original = model.step
    calls = []

    def fly_away_after_30_steps(self, *args, **kwargs):  # a runaway learning rate, as Gaussians see it
        calls.append(1)
        result = original(self, *args, **kwargs)
        if len(calls) > 30:
            arrays = self.gaussians.params["means"]
            arrays.from_numpy(arrays.to_numpy() + 1e9)
        return result

    monkeypatch.setattr(model, "step", fly_away_after_30_steps)
    result = CliRunner().invoke(app, ["--arch", "cpu", stage, str(run), "--config", str(tiny["config"])])
    assert result.exit_code == 4, result.output
    assert "diverged at iteration" in result.output and "flew" in result.output
    assert not (run / stage / "done.json").exists()
    checkpoint = np.load(run / stage / "checkpoint.npz")
    assert int(checkpoint["iteration"]) == 20  # the last one saved before the parameters went bad
