"""The CLI behaves like its neighbours: help text, choices, command order, options after the
subcommand, clean stdout, progress without a terminal, quiet/verbose, a run log, eval's table."""

from __future__ import annotations

import io
import json
import logging
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from rich.console import Console
from rich.progress import Progress
from typer.testing import CliRunner

from taichi_gs.cli import app
from taichi_gs.cli_options import COMMAND_ORDER, hoist_global_options
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import write_tum
from taichi_gs.pipeline import write_run_info
from taichi_gs.synth import SynthConfig, generate
from taichi_gs.terminal import PlainProgress, configure_logging, progress_columns

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def _cli(*args: str, timeout: int = 300) -> subprocess.CompletedProcess:
    """The CLI in a fresh process (Taichi's banner is printed at import, so only a new process shows it)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "80"}
    env.pop("ENABLE_TAICHI_HEADER_PRINT", None)
    return subprocess.run([sys.executable, "-m", "taichi_gs.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=ROOT)


def _plain(text: str) -> str:
    return re.sub(r"\x1b\[[0-9;?]*[a-zA-Z]", "", text)


@pytest.mark.parametrize("command", ["pose", "reconstruct", "refine", "deblur"])
def test_config_help_shows_the_table_names(command):
    result = runner.invoke(app, [command, "--help"], terminal_width=100)
    assert result.exit_code == 0
    text = " ".join(_plain(result.output).replace("│", " ").split())  # undo rich's wrapping
    assert "TOML file with [pose], [refine], [deblur] tables" in text


def test_every_synth_option_has_help():
    group = typer.main.get_command(app)
    synth = group.get_command(None, "synth")
    missing = [p.name for p in synth.params if p.name != "help" and not getattr(p, "help", None)]
    assert not missing


@pytest.mark.parametrize("args, word", [
    (["synth", "OUT", "--trajectory", "circle"], "circle"),
    (["synth", "OUT", "--blur", "heavy"], "heavy"),
    (["synth", "OUT", "--scene", "cave"], "cave"),
    (["reconstruct", "IN", "--out", "OUT", "--force", "everything"], "everything"),
    (["deblur", "OUT", "--holdout", "1"], "--holdout"),
    (["deblur", "OUT", "--holdout", "some"], "some"),
])
def test_closed_options_are_choices_checked_before_any_work(args, word, tmp_path):
    result = runner.invoke(app, [a.replace("OUT", str(tmp_path / "o")).replace("IN", str(tmp_path)) for a in args])
    assert result.exit_code == 2
    assert word in _plain(result.output)
    assert not (tmp_path / "o").exists()


def test_holdout_accepts_none_and_integers():
    from taichi_gs.cli_options import parse_holdout

    assert (parse_holdout("none"), parse_holdout("NONE"), parse_holdout("3")) == (0, 0, 3)


def test_commands_are_listed_with_reconstruct_first():
    group = typer.main.get_command(app)
    names = group.list_commands(None)
    assert names[0] == "reconstruct" and set(names) >= {"pose", "refine", "deblur", "eval", "synth", "info"}
    assert [n for n in names if n in COMMAND_ORDER] == [n for n in COMMAND_ORDER if n in names]
    help_text = _plain(runner.invoke(app, ["--help"], terminal_width=100).output)
    assert help_text.index("reconstruct") < help_text.index(" synth ") < help_text.index(" info ")


def test_group_options_after_the_subcommand_are_moved_in_front():
    commands = {"pose", "info"}
    assert hoist_global_options(["pose", "IN", "--arch", "cpu", "--out", "O", "-q"], commands) == \
        ["--arch", "cpu", "-q", "pose", "IN", "--out", "O"]
    assert hoist_global_options(["--arch", "cpu", "info"], commands) == ["--arch", "cpu", "info"]
    assert hoist_global_options(["info", "--arch=cuda"], commands) == ["--arch=cuda", "info"]
    assert hoist_global_options(["pose", "--", "-q"], commands) == ["pose", "--", "-q"]


def test_info_stdout_has_no_taichi_banner_and_arch_works_after_the_command():
    result = _cli("info", "--arch", "cpu")
    assert result.returncode == 0, result.stderr
    assert "[Taichi]" not in result.stdout
    assert re.search(r"^arch requested\s+cpu$", result.stdout, re.M)
    assert re.search(r"^arch obtained\s+cpu$", result.stdout, re.M)


def test_plain_progress_prints_every_tenth_and_every_30_seconds():
    now = [0.0]
    lines: list[str] = []
    progress = PlainProgress("refine", 1000, lines.append, clock=lambda: now[0])
    for done in range(1, 1001):
        now[0] += 0.01
        progress.update(done, loss=0.5)
    assert len(lines) == 10 and lines[0].startswith("refine: 100/1000 (10%)") and lines[-1].startswith("refine: 1000/1000 (100%)")
    assert "eta 0:00:09" in lines[0] and "loss=0.5" in lines[0]
    lines.clear()
    slow = PlainProgress("deblur", 1000, lines.append, clock=lambda: now[0])
    for done in range(1, 50):
        now[0] += 1.0  # 1 s per step: 30 s pass long before 10%
        slow.update(done)
    assert [line.split()[1] for line in lines] == ["30/1000"]


def test_progress_bar_keeps_count_and_eta_whole_at_80_columns():
    clock = [0.0]
    out = io.StringIO()
    narrow = Console(file=out, width=80, force_terminal=True, color_system=None)
    with Progress(*progress_columns("stage 3: deblur", 1), console=narrow, get_time=lambda: clock[0],
                  auto_refresh=False) as progress:
        task = progress.add_task("stage 3: deblur", total=1, info="")
        for k in range(1, 7):
            clock[0] = 10.0 * k
            progress.update(task, completed=100 * k, total=6000,
                            info="loss=0.01234  psnr=27.5  gaussians=123456  exposure=0.5")
        progress.refresh()
    last = _plain(out.getvalue()).replace("\r", "\n").strip().splitlines()[-1]
    assert len(last) <= 80
    assert "stage 3: deblur" in last and " 600/6000 " in last and " 0:01:00 " in last and " 0:09:00 " in last


def test_warnings_print_on_their_own_line(capsys):
    configure_logging(1)
    logging.getLogger("taichi_gs").warning("deblur: k = 7 is likely too small")
    err = _plain(capsys.readouterr().err)
    assert "warning: deblur: k = 7 is likely too small\n" in err


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory) -> Path:
    return generate(SynthConfig(width=48, height=32, frames=12, blur="moderate", seed=4),
                    tmp_path_factory.mktemp("cli") / "seq")


def test_without_a_terminal_pose_prints_progress_lines_and_logs_to_the_run_folder(tiny_sequence, tmp_path):
    out = tmp_path / "run"
    result = _cli("pose", str(tiny_sequence), "--out", str(out), "--arch", "cpu")
    assert result.returncode == 0, result.stderr
    assert result.stdout == ""
    # 11 pairs, the graph's 11 frames, 12 fused frames
    progress = re.findall(r"^stage 1: pose: (\d+)/34 \(\d+%\) elapsed \d:\d\d:\d\d eta \d:\d\d:\d\d  step=(.+)$",
                          result.stderr, re.M)
    assert progress and progress[-1] == ("34", "fused cloud")
    kinds = [kind for _, kind in progress]
    assert kinds == sorted(kinds, key=["pairs", "graph", "fused cloud"].index)
    assert "stage 1 done" in result.stderr
    log = (out / "log.txt").read_text()
    assert "$ taichi-gs pose" in log.splitlines()[0]
    assert "stage 1: pose: 34/34 (100%)" in log and "stage 1 done" in log

    quiet = _cli("-q", "pose", str(tiny_sequence), "--out", str(out))
    assert quiet.returncode == 0, quiet.stderr
    assert "stage 1" not in quiet.stderr  # neither progress nor the summary
    assert (out / "log.txt").read_text().count("stage 1 done") == 2  # the log still gets it


def test_eval_prints_the_table_and_warnings(tiny_sequence, tmp_path):
    sequence = load_sequence(tiny_sequence)
    run = tmp_path / "run"
    write_run_info(run, sequence)
    rng = np.random.default_rng(0)
    noisy = sequence.gt_poses.copy()
    noisy[:, :3, 3] += rng.normal(0, 0.01, (len(sequence), 3))
    write_tum(run / "pose" / "trajectory.txt", sequence.timestamps, noisy)
    (run / "pose" / "done.json").write_text(json.dumps({"seconds": 12.5, "peak_rss_mb": 321.0, "arch": "cpu",
                                                        "summary": "", "warnings": ["a test warning"]}))
    result = runner.invoke(app, ["eval", str(run)])
    assert result.exit_code == 0, result.output
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["warnings"] == ["pose: a test warning"]
    row = next(line for line in result.stdout.splitlines() if line.strip().startswith("pose "))
    ate_mm = f"{metrics['trajectory']['pose']['ate_m'] * 1000:.2f}"
    rpe_mm = f"{metrics['trajectory']['pose']['rpe_trans_m'] * 1000:.2f}"
    assert row.split()[1:3] == [ate_mm, rpe_mm] and float(ate_mm) > 1  # the numbers themselves, in mm
    assert "12.5" in result.stdout and "321" in result.stdout
    assert "warning: pose: a test warning" in result.stdout

    as_json = _cli("eval", str(run), "--json")  # a fresh process: nothing but the JSON object on stdout
    assert as_json.returncode == 0, as_json.stderr
    assert json.loads(as_json.stdout)["trajectory"]["pose"]["frames"] == len(sequence)


def test_pose_and_refine_profiles_name_where_each_stage_spends_its_time(tiny_sequence, tmp_path):
    out = tmp_path / "run"
    config = tmp_path / "short.toml"
    config.write_text("[refine]\niterations_per_frame = 2\n")
    assert _cli("pose", str(tiny_sequence), "--out", str(out), "--profile").returncode == 0
    pose = json.loads((out / "profile.json").read_text())["pose"]["sections"]
    for name in ("optical flow (DIS)", "flow solve (se(3))", "ICP", "verification", "pose graph: optimisation",
                 "fused point cloud", "input frames (I/O)"):
        assert pose[name]["calls"] > 0 and pose[name]["wall_s"] > 0, name
    assert pose["other host work"]["wall_s"] < 0.5 * sum(s["wall_s"] for s in pose.values())
    result = _cli("refine", str(out), "--config", str(config), "--profile")
    assert result.returncode == 0, result.stderr
    assert "profile: " in result.stderr
    refine = json.loads((out / "profile.json").read_text())
    assert set(refine) == {"refine"} and refine["refine"]["sections"]["render backward"]["calls"] == 2 * 12
    assert "## refine: " in (out / "profile.md").read_text()
