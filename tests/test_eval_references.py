"""`taichi-gs eval` scores what a run's sequence has a reference for (ground-truth poses and sharp frames, each on its
own) and names the rest, on a real tiny run made on a sequence without either."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import imageio.v3 as imageio
import numpy as np
import pytest
from typer.testing import CliRunner

from taichi_gs.cli import app
from taichi_gs.synth import SynthConfig, generate

# Each stage in a few seconds on 2 cores: stage 2 hands stage 1's output over untrained, stage 3 takes 20 steps.
TINY_CONFIG = """
[pose]
icp_from_prior = false
pose_graph = false

[refine]
iterations_per_frame = 0

[deblur]
iterations = 20
iterations_per_view = 0
k = 3
test_pose_iterations = 2
densify_from = 100
densify_until = 100
"""


def _copy_without(seq: Path, folder: Path, *names: str) -> Path:
    """A copy of ``seq`` at ``folder`` less the named files and folders."""
    shutil.copytree(seq, folder)
    for name in names:
        path = folder / name
        shutil.rmtree(path) if path.is_dir() else path.unlink()
    return folder


@pytest.fixture(scope="module")
def bare(tmp_path_factory) -> dict[str, Path]:
    """A 6-frame synthetic sequence (``full``), its copies without ground-truth poses (``sharp_only``) and without
    those, sharp/ and exposure.txt (``bare``, as a real capture), and a finished run (``run``) made on ``bare``."""
    root = tmp_path_factory.mktemp("references")
    full = generate(SynthConfig(width=64, height=48, frames=6, trajectory="handheld", blur="extreme", seed=5),
                    root / "full")
    sharp_only = _copy_without(full, root / "sharp_only", "groundtruth.txt")
    bare = _copy_without(full, root / "bare", "groundtruth.txt", "sharp", "exposure.txt")
    (root / "tiny.toml").write_text(TINY_CONFIG)
    result = subprocess.run([sys.executable, "-m", "taichi_gs.cli", "--arch", "cpu", "reconstruct", str(bare), "--out",
                             str(root / "run"), "--config", str(root / "tiny.toml")], capture_output=True, text=True,
                            timeout=300)
    assert result.returncode == 0, result.stderr
    return {"full": full, "sharp_only": sharp_only, "bare": bare, "run": root / "run"}


def _eval(run: Path, tmp_path: Path, *args: str) -> tuple[str, dict, Path]:
    """``taichi-gs eval`` on a copy of ``run``: (printed text, metrics.json, the copy)."""
    local = tmp_path / "run"
    shutil.copytree(run, local)
    result = CliRunner().invoke(app, ["eval", str(local), *args])
    assert result.exit_code == 0, result.output
    return result.stdout, json.loads((local / "metrics.json").read_text()), local


def test_eval_without_ground_truth_or_sharp_frames_reports_what_needs_neither(bare, tmp_path):
    printed, metrics, run = _eval(bare["run"], tmp_path)
    assert metrics["trajectory"] == {} and "trajectory (after rigid alignment)" not in printed
    reasons = {item["what"].split(":")[0].split(" (")[0]: item["reason"] for item in metrics["not_scored"]}
    assert set(reasons) == {"trajectory errors", "images"}
    assert "no ground-truth poses" in reasons["trajectory errors"] and "no sharp/ folder" in reasons["images"]
    assert "not scored" in printed and "no ground-truth poses" in printed and "no sharp/ folder" in printed
    no_reference = metrics["no_reference"]
    for split, views in (("test", 2), ("train", 4)):
        figures = no_reference[split]
        assert figures["views"] == views and figures["reblur_psnr_db"] > 10 and figures["exposure_px"] > 0
        assert figures["gradient_energy_ratio"] > 0 and "true_exposure_px" not in figures
    assert "no-reference figures" in printed and f"{no_reference['test']['reblur_psnr_db']:.2f}" in printed
    assert metrics["images"]["test"]["inverse_depth_rmse"] < 0.2 and "psnr_db" not in metrics["images"]["test"]
    assert set(metrics["stages"]) == {"pose", "refine", "deblur"} and "peak MB" in printed
    assert all(s["seconds"] >= 0 and s["peak_rss_mb"] > 0 for s in metrics["stages"].values())
    report = {p.name for p in (run / "report").iterdir()}
    assert report == {"trajectory_top.png", "test_views.png", "no_reference_views.png", "blur_streaks.png"}


def test_eval_scores_sharp_frames_without_ground_truth_poses(bare, tmp_path):
    printed, metrics, _ = _eval(bare["run"], tmp_path, "--gt", str(bare["sharp_only"]))
    assert metrics["trajectory"] == {} and metrics["images"]["ground_truth"] == "sharp images"
    assert 5 < metrics["images"]["test"]["psnr_db"] < 60 and "PSNR dB" in printed
    (trajectory, true_exposure) = metrics["not_scored"]  # exposure.txt's blur is seen from the missing poses
    assert trajectory["what"].startswith("trajectory errors") and "true_exposure_px" in true_exposure["what"]


def test_eval_with_ground_truth_scores_everything(bare, tmp_path):
    printed, metrics, run = _eval(bare["run"], tmp_path, "--gt", str(bare["full"]))
    assert set(metrics["trajectory"]) == {"pose", "refine", "deblur"}
    assert all(t["frames"] == 6 and t["ate_m"] < 0.05 for t in metrics["trajectory"].values())
    assert printed.startswith("trajectory (after rigid alignment)") and "not scored" not in printed
    assert metrics["not_scored"] == [] and metrics["no_reference"]["test"]["true_exposure_px"] > 0
    assert "as_read_psnr_db" not in metrics["images"]["test"]  # a global shutter: no renders/as_read/
    assert (run / "report" / "position_error.png").is_file() and (run / "report" / "trajectory_top.png").is_file()


def test_eval_scores_the_renders_as_a_rolling_shutter_reads_them_where_stage_3_wrote_them(bare, tmp_path):
    """A run whose stage 3 modelled a rolling shutter has renders/as_read/: eval scores them beside the sharp renders
    (here they are the sharp renders, except one held-out view halfway to its truth, so they score higher)."""
    local = tmp_path / "source"
    shutil.copytree(bare["run"], local)
    renders = local / "deblur" / "renders"
    shutil.copytree(renders / "sharp", renders / "as_read")
    names = [line.split()[1].split("/", 1)[1].rsplit(".", 1)[0]
             for line in (bare["full"] / "frames.txt").read_text().splitlines() if line and line[0] != "#"]
    name = names[json.loads((local / "deblur" / "split.json").read_text())["test"][0]]
    render = imageio.imread(renders / "sharp" / f"{name}.png").astype(np.float64)
    truth = imageio.imread(bare["full"] / "sharp" / f"{name}.png").astype(np.float64)
    imageio.imwrite(renders / "as_read" / f"{name}.png", np.rint(0.5 * (render + truth)).astype(np.uint8))
    printed, metrics, _ = _eval(local, tmp_path, "--gt", str(bare["full"]))
    assert "as read PSNR" in printed and f"{metrics['images']['test']['as_read_psnr_db']:.2f}" in printed
    test, train = metrics["images"]["test"], metrics["images"]["train"]
    assert test["as_read_psnr_db"] > test["psnr_db"] and test["as_read_ssim"] > test["ssim"]
    assert train["as_read_psnr_db"] == train["psnr_db"] and train["as_read_ssim"] == train["ssim"]
