"""Stage-3 settings against the default on a grid of synthetic and real sequences, before any of them
becomes a default (the brief: a claim must hold on longer sequences, several seeds, scenes the generator
did not make, and real data).

    python bench/stage3_grid.py --out /tmp/grid --arm decay=d05.toml [--arm NAME=FILE.toml ...]
        [--grid synth sample 7scenes tum] [--7scenes ../shared/data/7scenes_redkitchen_000-249]
        [--tum /tmp/fr1_rpy/data] [--run NAME=STAGE1_RUN ...] [--jobs 2]

Each sequence goes through `taichi-gs pose` once (OUT/base/NAME). Every arm, the default (no --config)
included, then runs `taichi-gs refine`, `taichi-gs deblur [--config FILE]` and `taichi-gs eval --json` on its
own copy of that stage-1 folder (OUT/runs/NAME/ARM), in a fresh process. Sequences without sharp ground truth
(real captures) hold out their sharpest frames (`--holdout sharpest`). Finished cells are read back, so a
killed grid resumes.

The grid (60 frames at 320x240 for synth; real slices at --scale 0.5):
- synth: room hand-held seed 5, office turn seed 11, corridor translation seed 3;
- sample: the bundled samples/room (16 frames);
- 7scenes (needs --7scenes): frames 0-39, and every 3rd frame of 0-117;
- tum (needs --tum, a TUM folder such as fr1_rpy's): frames 400-439 with --camera fr1.
--run NAME=DIR adds a stage-1 run folder made elsewhere.

Prints one Markdown table: per sequence and arm, held-out PSNR / SSIM (synthetic: against sharp ground truth;
real: against the held-out sharpest frames), re-blur PSNR of test / training views, the render against the
warped-neighbour floor on the floor's pixels, ATE after stages 1 and 3, RPE rotation after stage 3, stage 3's
wall and CPU seconds (user + sys of its process), and the held-out difference to the default. Image and pose
figures do not depend on --jobs; seconds are comparable only with --jobs 1 on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_ARM = "default"


@dataclass(frozen=True)
class GridSequence:
    """A grid sequence: how its stage-1 folder is made (``synth`` options or ``pose`` options on ``source``)."""

    name: str
    real: bool
    source: str = ""  # folder to pose; empty: made by synth from synth_args
    synth_args: tuple[str, ...] = ()
    pose_args: tuple[str, ...] = ()
    stage1: str = ""  # an existing stage-1 run folder (--run)


def grid(kinds: list[str], seven_scenes: Path | None, tum: Path | None, runs: list[str]) -> list[GridSequence]:
    """The sequences of the chosen grid parts, in table order."""
    sequences = []
    if "synth" in kinds:
        sequences += [
            GridSequence("room hand-held s5", False, synth_args=("--seed", "5")),
            GridSequence("office turn s11", False,
                         synth_args=("--seed", "11", "--scene", "office", "--trajectory", "turn")),
            GridSequence("corridor translation s3", False,
                         synth_args=("--seed", "3", "--scene", "corridor", "--trajectory", "translation")),
        ]
    if "sample" in kinds:
        sequences.append(GridSequence("sample", False, source=str(ROOT / "samples" / "room")))
    if "7scenes" in kinds:
        if seven_scenes is None:
            raise SystemExit("--grid 7scenes needs --7scenes FOLDER (the 7-Scenes slice)")
        sequences += [
            GridSequence("7-Scenes 0-39", True, str(seven_scenes), pose_args=("--count", "40", "--scale", "0.5")),
            GridSequence("7-Scenes every 3rd", True, str(seven_scenes),
                         pose_args=("--every", "3", "--count", "40", "--scale", "0.5")),
        ]
    if "tum" in kinds:
        if tum is None:
            raise SystemExit("--grid tum needs --tum FOLDER (a TUM RGB-D folder, e.g. fr1_rpy)")
        tum_args = ("--camera", "fr1", "--first", "400", "--count", "40", "--scale", "0.5")
        sequences.append(GridSequence("TUM 400-439", True, str(tum), pose_args=tum_args))
    for item in runs:
        name, _, folder = item.partition("=")
        if not folder or not (Path(folder) / "pose").is_dir():
            raise SystemExit(f"--run {item}: expected NAME=DIR with a stage-1 run folder (DIR/pose)")
        folder = str(Path(folder).resolve())
        sequences.append(GridSequence(name, not _has_sharp_ground_truth(Path(folder)), stage1=folder))
    return sequences


def _has_sharp_ground_truth(run: Path) -> bool:
    from taichi_gs.pipeline import open_run_sequence

    return open_run_sequence(run).sharp_paths is not None


def taichi_gs(*args: str, log: Path) -> tuple[float, float]:
    """Run this tree's CLI in a fresh process, output appended to ``log``; its wall and CPU (user + sys)
    seconds."""
    start = time.perf_counter()
    with open(log, "a") as out:
        process = subprocess.Popen([sys.executable, "-m", "taichi_gs.cli", *args], stdout=out, stderr=out,
                                   cwd=log.parent, env={**os.environ, "PYTHONPATH": str(ROOT)})
        _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    if process.returncode != 0:
        raise SystemExit(f"taichi-gs {' '.join(args)} failed ({process.returncode}); see {log}")
    return time.perf_counter() - start, usage.ru_utime + usage.ru_stime


def stage1(seq: GridSequence, out: Path) -> Path:
    """The sequence's stage-1 folder, made once."""
    if seq.stage1:
        return Path(seq.stage1)
    base = out / "base" / _slug(seq.name)
    if (base / "pose" / "done.json").is_file():
        return base
    base.parent.mkdir(parents=True, exist_ok=True)
    source = seq.source
    if not source:
        source = str(out / "sequences" / _slug(seq.name))
        if not Path(source, "groundtruth.txt").is_file():
            taichi_gs("synth", source, "--overwrite", *seq.synth_args, log=base.parent / f"{_slug(seq.name)}.log")
    taichi_gs("pose", source, *seq.pose_args, "--out", str(base), log=base.parent / f"{_slug(seq.name)}.log")
    return base


def run_cell(seq: GridSequence, base: Path, arm: str, config: Path | None, out: Path) -> dict:
    """Stages 2 and 3 and eval of one arm on a copy of the sequence's stage-1 folder; its figures."""
    cell = out / "runs" / _slug(seq.name) / arm
    result_path = cell.parent / f"{arm}.json"
    if result_path.is_file():
        return json.loads(result_path.read_text())
    shutil.rmtree(cell, ignore_errors=True)
    cell.mkdir(parents=True)
    shutil.copytree(base / "pose", cell / "pose")
    shutil.copy2(base / "run.json", cell / "run.json")
    log = cell.parent / f"{arm}.log"
    taichi_gs("refine", str(cell), log=log)
    options = (["--config", str(config.resolve())] if config else []) + (["--holdout", "sharpest"] if seq.real else [])
    wall, cpu = taichi_gs("deblur", str(cell), *options, log=log)
    taichi_gs("eval", str(cell), log=log)
    metrics = json.loads((cell / "metrics.json").read_text())
    result = {"sequence": seq.name, "arm": arm, "real": seq.real, "deblur_wall_s": wall, "deblur_cpu_s": cpu,
              **figures(metrics)}
    result_path.write_text(json.dumps(result, indent=1))
    return result


def figures(metrics: dict) -> dict:
    """The table's figures from a run's metrics.json."""
    trajectory = metrics["trajectory"]
    reference = metrics["no_reference"]
    test = reference["test"]
    sharp = (metrics.get("images") or {}).get("test") or {}
    held_out = (sharp.get("psnr_db"), sharp.get("ssim")) if "psnr_db" in sharp else \
        (test.get("held_out_psnr_db"), test.get("held_out_ssim"))
    return {
        "held_out_psnr_db": held_out[0], "held_out_ssim": held_out[1],
        "reblur_test_db": test["reblur_psnr_db"], "reblur_train_db": reference["train"]["reblur_psnr_db"],
        "render_on_floor_pixels_db": test.get("render_on_warp_mask_psnr_db"),
        "floor_db": test.get("warped_neighbour_psnr_db"),
        "blur_test_px": test.get("exposure_px"), "blur_train_px": reference["train"].get("exposure_px"),
        "ate_pose_mm": 1000 * trajectory["pose"]["ate_m"] if trajectory.get("pose") else None,
        "ate_deblur_mm": 1000 * trajectory["deblur"]["ate_m"] if trajectory.get("deblur") else None,
        "rpe_rot_deblur_deg": trajectory["deblur"]["rpe_rot_deg"] if trajectory.get("deblur") else None,
    }


def table(results: list[dict]) -> str:
    """Markdown table, the default's row first per sequence, with the held-out difference to it."""
    lines = ["| sequence | arm | held-out PSNR / SSIM | re-blur test / train dB | render / floor dB "
             "| learned blur test / train px | ATE stage 1 / 3 mm | RPE rot deg | stage 3 s (CPU-s) "
             "| held-out vs default dB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    defaults = {r["sequence"]: r for r in results if r["arm"] == DEFAULT_ARM}
    for r in results:
        base = defaults.get(r["sequence"])
        pair = None if base is None or r is base else (r["held_out_psnr_db"], base["held_out_psnr_db"])
        delta = f"{pair[0] - pair[1]:+.2f}" if pair and None not in pair else ""
        lines.append(f"| {r['sequence']} | {r['arm']} | {_num(r['held_out_psnr_db'])} / "
                     f"{_num(r['held_out_ssim'], 3)} | {_num(r['reblur_test_db'])} / {_num(r['reblur_train_db'])} | "
                     f"{_num(r['render_on_floor_pixels_db'])} / {_num(r['floor_db'])} | "
                     f"{_num(r.get('blur_test_px'), 1)} / {_num(r.get('blur_train_px'), 1)} | {_num(r['ate_pose_mm'])} / "
                     f"{_num(r['ate_deblur_mm'])} | {_num(r['rpe_rot_deblur_deg'], 3)} | "
                     f"{r['deblur_wall_s']:.0f} ({r['deblur_cpu_s']:.0f}) | {delta} |")
    return "\n".join(lines)


def _num(value: float | None, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def _slug(name: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in name).strip("_").lower()


def _arms(items: list[str]) -> dict[str, Path | None]:
    arms: dict[str, Path | None] = {DEFAULT_ARM: None}
    for item in items:
        name, _, path = item.partition("=")
        if not path or not Path(path).is_file() or name == DEFAULT_ARM or not name.isidentifier():
            raise SystemExit(f"--arm {item}: expected NAME=FILE.toml (an existing config file; NAME a word, "
                             f"not '{DEFAULT_ARM}')")
        arms[name] = Path(path)
    return arms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="sequences, stage-1 folders, runs and grid.json")
    parser.add_argument("--arm", action="append", default=[], metavar="NAME=FILE.toml",
                        help="a config to compare with the default (repeatable)")
    parser.add_argument("--grid", nargs="+", default=["synth", "sample"], choices=["synth", "sample", "7scenes", "tum"])
    parser.add_argument("--7scenes", dest="seven_scenes", type=Path, help="the 7-Scenes slice (../shared/data/...)")
    parser.add_argument("--tum", type=Path, help="a TUM RGB-D folder (fr1_rpy)")
    parser.add_argument("--run", action="append", default=[], metavar="NAME=DIR", help="an existing stage-1 run")
    parser.add_argument("--jobs", type=int, default=1, help="cells run at once (seconds comparable only at 1)")
    args = parser.parse_args()
    arms = _arms(args.arm)
    seven_scenes, tum = (path.resolve() if path else None for path in (args.seven_scenes, args.tum))
    sequences = grid(args.grid, seven_scenes, tum, args.run)
    out = args.out.resolve()  # the CLI runs inside each cell's folder
    out.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        bases = dict(zip(sequences, pool.map(lambda s: stage1(s, out), sequences)))
        cells = [(s, arm, config) for s in sequences for arm, config in arms.items()]
        results = list(pool.map(lambda c: run_cell(c[0], bases[c[0]], c[1], c[2], out), cells))
    (out / "grid.json").write_text(json.dumps(results, indent=1))
    print(table(results))


if __name__ == "__main__":
    main()
