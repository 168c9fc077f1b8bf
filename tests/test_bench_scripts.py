"""Every benchmark script still imports and parses its arguments (bench/refine.py and bench/refine_keep.py
imported a helper that bench/pose.py had dropped, and failed before doing anything); bench/raster.py times a run
folder's scene."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"
SCRIPTS = sorted(p.name for p in BENCH.glob("*.py") if 'if __name__ == "__main__":' in p.read_text())


def test_the_bench_folder_has_scripts():
    assert {"pose.py", "raster.py", "refine.py", "refine_keep.py"} <= set(SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS)
def test_bench_script_help_runs(script):
    result = subprocess.run([sys.executable, str(BENCH / script), "--help"], capture_output=True, text=True,
                            timeout=120, cwd=BENCH.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "usage:" in result.stdout


def test_raster_bench_times_a_run_folder(tmp_path):
    """``bench/raster.py --run OUT`` renders the run's newest splats at its frames' poses, at its resolution."""
    from taichi_gs.io.ply import read_splats
    from taichi_gs.standins import synthetic_refine_outputs
    from taichi_gs.synth import SynthConfig

    _, out = synthetic_refine_outputs(tmp_path, SynthConfig(width=48, height=32, frames=3, seed=1), voxel=0.08)
    result = subprocess.run([sys.executable, str(BENCH / "raster.py"), "--combo", "200:32x24", "--run", str(out)],
                            capture_output=True, text=True, timeout=600, cwd=BENCH.parent)
    assert result.returncode == 0, result.stderr[-2000:]
    rows = [line.split() for line in result.stdout.splitlines() if line.endswith(str(out))]
    assert len(rows) == 1
    assert int(rows[0][0]) == len(read_splats(out / "refine" / "splats.ply"))
    assert rows[0][1] == "48x32"
    assert int(rows[0][2]) > 0  # tile slots: the splats are in view
