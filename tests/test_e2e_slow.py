"""End to end on the bundled sample, as the README's first command runs it (about 10 minutes on
two CPU cores): ``python -m pytest -m slow``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "room"


def _cli(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "taichi_gs.cli", *args], capture_output=True, text=True,
                          timeout=3600, env=env, cwd=ROOT)


@pytest.mark.slow
def test_reconstruct_the_sample_then_evaluate_and_export(tmp_path):
    run = tmp_path / "run"
    result = _cli("reconstruct", str(SAMPLE), "--out", str(run), "--arch", "cpu")
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout == ""
    assert "warning" not in result.stderr.lower()  # the default preset does not warn about itself here

    evaluated = _cli("eval", str(run), "--json")
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    metrics = json.loads(evaluated.stdout, parse_constant=lambda c: pytest.fail(f"{c} in JSON"))
    assert metrics["warnings"] == []
    deblur = metrics["trajectory"]["deblur"]
    assert deblur["frames"] == 16 and deblur["ate_m"] < 0.01  # bench/results.py sample: under 1 mm
    test = metrics["images"]["test"]
    assert test["psnr_db"] > test["blurred_input_psnr_db"] + 3.0  # bench/results.py sample: +7 dB
    assert (run / "log.txt").is_file() and "stage 3" in (run / "log.txt").read_text()

    for fmt in ("nerfstudio", "colmap", "ply", "3dgs"):
        exported = _cli("export", str(run), "--format", fmt)
        assert exported.returncode == 0, exported.stderr[-3000:]
    assert (run / "export" / "3dgs" / "cfg_args").is_file()
