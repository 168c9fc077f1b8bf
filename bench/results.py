"""Regenerate BENCHMARKS.md's tables: each table runs fixed bench commands and formats what they print or write.

    python bench/results.py --list                     # the tables: what each runs, what it needs, how long it takes
    python bench/results.py TABLE [--work DIR]         # run one table's commands and print the table
    python bench/results.py TABLE --write [--work DIR] # ... and rewrite its block in BENCHMARKS.md

A table's block in BENCHMARKS.md lies between ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->``. ``--write``
replaces what lies between them with a stamp (date, machine, the command) and the table; the heading, the line saying
what the table measures and any reading around it stay as they are. Tables that need data this repository does not
hold (TUM fr1_rpy, 7-Scenes' second reference, a CUDA GPU) name it in ``--list`` and refuse to start without it.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "BENCHMARKS.md"
SEVEN_SCENES = "/work/shared/data/7scenes_redkitchen_000-249"
PEERS = ("O3D hybrid", "O3D ICP", "O3D dense SLAM", "DIS RANSAC")


@dataclass(frozen=True)
class Run:
    """One command's output: what it printed and how long it took (wall seconds)."""
    stdout: str
    seconds: float


@dataclass(frozen=True)
class Table:
    """A table of BENCHMARKS.md: the commands that measure it and the formatter that turns their output into
    Markdown. Commands are argument lists; ``{python}``, ``{work}``, ``{seven_scenes}`` and every name in ``needs``
    (an environment variable, ``{TAICHI_GS_TUM}``) are filled in before they run."""
    name: str
    summary: str
    cost: str
    commands: tuple[tuple[str, ...], ...]
    format: Callable[[list[Run], Path], str]
    needs: tuple[str, ...] = field(default=())


# --- parsing what the bench scripts print -----------------------------------------------------------------------------

def markdown_tables(text: str) -> list[list[dict[str, str]]]:
    """Every Markdown table in ``text`` (a header row, a ``|---|`` row, then rows), each as a list of dicts keyed by
    the header's cells."""
    tables: list[list[dict[str, str]]] = []
    lines = text.splitlines()
    header = None
    for i, line in enumerate(lines):
        cells = _cells(line)
        if header is not None and cells is not None:
            if not _separator(line):
                tables[-1].append(dict(zip(header, cells)))
        elif cells is not None and i + 1 < len(lines) and _separator(lines[i + 1]):
            header = cells
            tables.append([])
        else:
            header = None
    return tables


def _cells(line: str) -> list[str] | None:
    """A table row's cells, or None for a line that is not a table row."""
    line = line.strip()
    if len(line) < 2 or not (line.startswith("|") and line.endswith("|")):
        return None
    return [c.strip() for c in line[1:-1].split("|")]


def _separator(line: str) -> bool:
    return re.fullmatch(r"\|(\s*:?-+:?\s*\|)+", line.strip()) is not None


def markdown(header: list[str], rows: list[list[str]]) -> str:
    """A Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def pivot(rows: list[dict[str, str]], row_key: str, column_key: str, cell: Callable[[dict[str, str]], str],
          first_column: str) -> str:
    """Rows ``row_key`` by columns ``column_key`` (each in the order first seen), each cell ``cell(row)``; "-" where
    a combination was not measured."""
    row_names = list(dict.fromkeys(r[row_key] for r in rows))
    columns = list(dict.fromkeys(r[column_key] for r in rows))
    found = {(r[row_key], r[column_key]): cell(r) for r in rows}
    return markdown([first_column, *columns], [[name, *(found.get((name, c), "-") for c in columns)] for name in row_names])


# --- formatters -------------------------------------------------------------------------------------------------------

def pose_rows(runs: list[Run]) -> list[dict[str, str]]:
    """The per-method rows of ``bench/pose.py`` runs (its first table each)."""
    return [row for run in runs for row in (markdown_tables(run.stdout) or [[]])[0]]


def pose_ate(runs: list[Run], work: Path) -> str:
    """Stage 1: ATE in mm (rotation scale) per sequence and method."""
    def cell(row: dict[str, str]) -> str:
        scale = row.get("rotation scale", "nan")
        return row["ATE (mm)"] + ("" if scale in ("nan", "-", "") else f" ({scale})")
    return pivot(pose_rows(runs), "sequence", "method", cell, "sequence: ATE mm (rotation scale)")


def pose_ate_rpe(runs: list[Run], work: Path) -> str:
    """Stage 1: ATE mm / RPE rotation deg per sequence and method."""
    return pivot(pose_rows(runs), "sequence", "method", lambda r: f"{r['ATE (mm)']} / {r['RPE rot (deg)']}",
                 "sequence: ATE mm / RPE rot deg")


def pose_two_references(runs: list[Run], work: Path) -> str:
    """Stage 1 on real sequences scored against their own reference and against ``--reference`` (rows "NAME vs
    STEM"): ATE mm / RPE rotation deg of the references against each other, of ours and of the best peer (the peer of
    lowest ATE against that reference) against each."""
    rows = pose_rows(runs)
    own = [name for name in dict.fromkeys(r["sequence"] for r in rows) if " vs " not in name]

    def figures(sequence: str, method: str) -> str:
        row = next((r for r in rows if r["sequence"] == sequence and r["method"] == method), None)
        return "-" if row is None else f"{row['ATE (mm)']} / {row['RPE rot (deg)']}"

    def best_peer(sequence: str) -> str:
        peers = [r for r in rows if r["sequence"] == sequence and r["method"] in PEERS]
        if not peers:
            return "-"
        best = min(peers, key=lambda r: float(r["ATE (mm)"]))
        return f"{best['ATE (mm)']} / {best['RPE rot (deg)']} ({best['method']})"

    table = []
    for name in own:
        other = next((r["sequence"] for r in rows if r["sequence"].startswith(name + " vs ")), None)
        table.append([name, figures(other, "the sequence's own reference") if other else "-",
                      figures(name, "ours"), best_peer(name),
                      figures(other, "ours") if other else "-", best_peer(other) if other else "-"])
    return markdown(["sequence: ATE mm / RPE rot deg", "the references against each other", "ours vs its own",
                     "best peer vs its own", "ours vs the other", "best peer vs the other"], table)


def e2e(runs: list[Run], work: Path) -> str:
    """``bench/e2e.py``: time and held-out quality per sequence length, with the gain over the floor (the blurred
    input, or on a recording the nearer training frames warped into the view)."""
    rows = [row for run in runs for row in markdown_tables(run.stdout)[0]]
    floor = next((k for k in ("blurred PSNR (dB)", "floor PSNR (dB)") if rows and k in rows[0]), "blurred PSNR (dB)")
    floor_ssim = floor.replace("PSNR (dB)", "SSIM")
    name = floor.split()[0]
    table = []
    for r in rows:
        gain = float(r["test PSNR (dB)"]) - float(r[floor])
        table.append([r["frames"], r["image"], r["total s"], r["s per frame"], r["Gaussians"], r["ATE (mm)"],
                      f"{r['test PSNR (dB)']} / {r['test SSIM']}", f"{r[floor]} / {r[floor_ssim]}", f"{gain:+.2f} dB"])
    return markdown(["frames", "image", "total s", "s per frame", "Gaussians", "ATE mm", "held-out PSNR / SSIM",
                     f"{name} PSNR / SSIM", "gain"], table)


def raster(runs: list[Run], work: Path) -> str:
    """``bench/raster.py``: ms per render (forward, forward + backward, phases) per scene size, and the device."""
    text = runs[0].stdout
    device = re.search(r"arch=(\S+)\s+device (.*?)\s+cpu threads", text)
    rows = []
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 11 and parts[0].isdigit() and "x" in parts[1]:
            rows.append([f"{int(parts[0]):,}", parts[1], f"{int(parts[2]):,}", *parts[3:11]])
    table = markdown(["Gaussians", "image", "slots", "forward ms", "forward + backward ms", "project", "sort", "blend",
                      "backward", "cover", "cores"], rows)
    ratio = re.search(r"reference \(NumPy.*", text)
    lines = [f"Backend {device.group(1)}, device {device.group(2)}." if device else "", table,
             f"\nSame run: {ratio.group(0)}." if ratio else ""]
    return "\n".join(line for line in lines if line)


def sample(runs: list[Run], work: Path) -> str:
    """The bundled sample end to end: seconds per stage, held-out quality against the sharp ground truth beside the
    blurred input's, ATE per stage."""
    metrics = json.loads((work / "room" / "metrics.json").read_text())
    stages = metrics["stages"]
    test = metrics["images"]["test"]
    ate = " / ".join(f"{1000 * metrics['trajectory'][s]['ate_m']:.2f}" for s in ("pose", "refine", "deblur"))
    return markdown(
        ["command wall s", "pose / refine / deblur s", "held-out PSNR / SSIM", "blurred input PSNR / SSIM",
         "ATE pose / refine / deblur mm", "backend"],
        [[f"{runs[0].seconds:.0f}", " / ".join(f"{stages[s]['seconds']:.1f}" for s in ("pose", "refine", "deblur")),
          f"{test['psnr_db']:.2f} / {test['ssim']:.3f}",
          f"{test['blurred_input_psnr_db']:.2f} / {test['blurred_input_ssim']:.3f}", ate, metrics.get("arch", "-")]])


def printed_table(text: str, header: str, script: str, last: bool = False) -> str:
    """The Markdown table that ``script`` printed whose header row starts with ``header`` (the first, or the last)."""
    start = text.rfind(header) if last else text.find(header)
    if start < 0:
        raise SystemExit(f"{script} printed no table")
    end = text.find("\n\n", start)
    return text[start:end if end >= 0 else None].strip()


def real_blur(runs: list[Run], work: Path) -> str:
    """bench/real_blur.py's own table: the last (complete) one it printed, after one per sequence as it went."""
    return printed_table(runs[-1].stdout, "| sequence", "bench/real_blur.py", last=True)


def launch_budget(runs: list[Run], work: Path) -> str:
    """bench/launch_budget.py's totals table (launches, tasks, host reads and writes, syncs, bytes per case)."""
    return printed_table(runs[-1].stdout, "| case", "bench/launch_budget.py")


# --- the tables -------------------------------------------------------------------------------------------------------

POSE = ("{python}", "bench/pose.py")
E2E = ("{python}", "bench/e2e.py", "--work", "{work}")
CLI = ("{python}", "-m", "taichi_gs.cli")

TUM_FR1 = ("{TAICHI_GS_TUM}", ("--camera", "fr1"))
SEVEN = ("{seven_scenes}", ())
REAL_BLUR_SEQUENCES = (  # name, recording, reader options, scale, W, first frame, averaged frames
    ("7s_w3_320", *SEVEN, "0.5", "3", "0", "40"), ("7s_w5_320", *SEVEN, "0.5", "5", "0", "40"),
    ("7s_w7_320", *SEVEN, "0.5", "7", "0", "35"), ("7s_w5_640", *SEVEN, "1", "5", "0", "40"),
    ("rpy_w5_320", *TUM_FR1, "0.5", "5", "0", "40"), ("rpy_w3_320_f300", *TUM_FR1, "0.5", "3", "300", "40"),
    ("rpy_w7_320_f300", *TUM_FR1, "0.5", "7", "300", "40"), ("rpy_w5_640_f200", *TUM_FR1, "1", "5", "200", "40"),
)

TABLES = {t.name: t for t in [
    Table("sample", "the bundled sample end to end (README's first command), fast preset, CPU",
          "2-6 minutes on 2 cores",
          (CLI + ("reconstruct", "samples/room", "--out", "{work}/room"), CLI + ("eval", "{work}/room", "--json")),
          sample),
    Table("sample_cuda", "the bundled sample end to end on a CUDA GPU", "about 2 minutes with a GPU",
          (CLI + ("--arch", "cuda", "reconstruct", "samples/room", "--out", "{work}/room"),
           CLI + ("--arch", "cuda", "eval", "{work}/room", "--json")),
          sample, needs=("CUDA",)),
    Table("stage1_sample", "stage 1 on the bundled sample: ours, the paper's path and the peers", "about 5 minutes",
          (POSE + ("--sequence", "samples/room", "--frames", "16", "--out", "{work}",
                   "--methods", ",".join(("ours", "paper", *PEERS))),),
          pose_ate),
    Table("stage1_synthetic", "stage 1 against its peers on synthetic extreme blur (60 frames, 320x240, seed 0)",
          "about an hour on 2 cores",
          (POSE + ("--size", "320x240", "--scenes", "room,office", "--trajectories", "turn,handheld", "--seeds", "0",
                   "--real-every", "", "--out", "{work}", "--methods", ",".join(("ours", "paper", *PEERS))),),
          pose_ate),
    Table("stage1_7scenes", "stage 1 on 7-Scenes RedKitchen (60 frames, 640x480, registered) against both references",
          "about 1.5 hours on 2 cores",
          (POSE + ("--frames", "60", "--scenes", "", "--real-every", "1,2,3", "--real-scale", "1.0",
                   "--real-camera", "registered", "--reference", "{TAICHI_GS_7SCENES_SFM}", "--out", "{work}",
                   "--methods", ",".join(("ours", *PEERS))),),
          pose_two_references, needs=("TAICHI_GS_7SCENES_SFM",)),
    Table("stage1_tum", "stage 1 on three 60-frame stretches of TUM fr1_rpy (640x480) against motion capture",
          "about an hour on 2 cores",
          tuple(POSE + ("--sequence", "{TAICHI_GS_TUM}", "--camera", "fr1", "--first", first, "--frames", "60",
                        "--out", "{work}", "--methods", "ours,ours global shutter,O3D hybrid")
                for first in ("100", "300", "500")),
          pose_ate_rpe, needs=("TAICHI_GS_TUM",)),
    Table("stage3_synthetic", "the fast preset end to end on synthetic hand-held sequences (320x240) as they grow",
          "about 30 minutes on 2 cores", (E2E + ("--frames", "30", "60", "120"),), e2e),
    Table("stage3_real", "the fast preset end to end on 7-Scenes RedKitchen (x0.5) as the slice grows",
          "about 35 minutes on 2 cores",
          (E2E + ("--sequence", "{seven_scenes}", "--scale", "0.5", "--frames", "30", "60", "120"),), e2e),
    Table("real_blur", "the fast preset on real extreme blur: 7-Scenes and TUM fr1_rpy frames averaged W = 3, 5, 7 "
          "in linear light (import --average), 320x240 and 640x480, held-out renders against the centre frames",
          "about a day on 2 cores (the paper preset left out: its 30000 stage-3 steps are a GPU's job)",
          tuple(CLI + ("import", source, *camera, "--scale", scale, "--average", w, "--first", first, "--count", count,
                       "--out", f"{{work}}/{name}")
                for name, source, camera, scale, w, first, count in REAL_BLUR_SEQUENCES)
          + (("{python}", "bench/real_blur.py", *(f"{{work}}/{s[0]}" for s in REAL_BLUR_SEQUENCES),
              "--out", "{work}/runs", "--no-paper"),),
          real_blur, needs=("TAICHI_GS_TUM",)),
    Table("launch_budget", "kernel launches, host reads and bytes copied per render and per training step, counted "
          "on the CPU backend (20000 Gaussians at 320x240)", "about 2 minutes",
          (("{python}", "bench/launch_budget.py", "--arch", "cpu"),), launch_budget),
    Table("raster_cpu", "the rasterizer on the CPU backend, 5k-200k Gaussians at 160x120-640x480 (f32, SH degree 0)",
          "about 5 minutes", (("{python}", "bench/raster.py", "--arch", "cpu"),), raster),
    Table("raster_cuda", "the rasterizer on CUDA (640x480, f32, SH degree 0)", "about a minute with a GPU",
          (("{python}", "bench/raster.py", "--arch", "cuda", "--quick"),), raster, needs=("CUDA",)),
]}


# --- running and writing ----------------------------------------------------------------------------------------------

def fill(command: tuple[str, ...], values: dict[str, str]) -> list[str]:
    """A command's arguments with its placeholders filled in."""
    return [re.sub(r"\{(\w+)\}", lambda m: values.get(m.group(1), m.group(0)), arg) for arg in command]


def shown(table: Table) -> str:
    """The table's bench commands as a reader would type them (``python``, ``taichi-gs``, ``WORK`` for the work
    folder, ``$NAME`` for what the table needs)."""
    values = {"python": "python", "work": "WORK", "seven_scenes": "../shared/data/7scenes_redkitchen_000-249"}
    values.update({need: f"${need}" for need in table.needs if need != "CUDA"})
    def quoted(arg: str) -> str:
        return arg if arg.startswith("$") else shlex.quote(arg)
    commands = (" ".join(quoted(a) for a in fill(c, values)) for c in table.commands)
    return "; ".join(c.replace("python -m taichi_gs.cli", "taichi-gs") for c in commands)


def missing_needs(table: Table) -> list[str]:
    """What the table needs that this machine lacks, each with the fix."""
    problems = []
    for need in table.needs:
        if need == "CUDA":
            if not gpu_name():
                problems.append("a CUDA GPU (nvidia-smi names none): run it on a machine with one")
        elif not os.environ.get(need) or not Path(os.environ[need]).exists():
            problems.append(f"${need}: set it to {NEED_HELP[need]}")
    return problems


def gpu_name() -> str:
    """The first GPU nvidia-smi names, or "" without one."""
    if not shutil.which("nvidia-smi"):
        return ""
    done = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True, text=True)
    return done.stdout.strip().splitlines()[0] if done.returncode == 0 and done.stdout.strip() else ""


NEED_HELP = {
    "TAICHI_GS_TUM": "TUM RGB-D's rgbd_dataset_freiburg1_rpy folder (rgb.txt, depth.txt, groundtruth.txt)",
    "TAICHI_GS_7SCENES_SFM": "the structure-from-motion reference of RedKitchen seq-01 as a TUM trajectory "
                             "(bench/pgt_to_tum.py on pgt/sfm/7scenes/redkitchen_train.txt of "
                             "tsattler/visloc_pseudo_gt_limitations)",
}


def run_table(table: Table, work: Path) -> str:
    """Run the table's commands in order (each must succeed) and format their output."""
    values = {"python": sys.executable, "work": str(work), "seven_scenes": SEVEN_SCENES,
              **{n: os.environ.get(n, "") for n in table.needs}}
    runs = []
    for command in table.commands:
        args = fill(command, values)
        print("running:", shlex.join(args), file=sys.stderr, flush=True)
        start = time.perf_counter()
        done = subprocess.run(args, cwd=ROOT, stdout=subprocess.PIPE, text=True)
        if done.returncode != 0:
            raise SystemExit(f"error: {shlex.join(args)} exited {done.returncode}; its output is above")
        runs.append(Run(done.stdout, time.perf_counter() - start))
    return table.format(runs, work)


def machine() -> str:
    """The CPU model (with its family and model numbers, which tell one EPYC generation from another), the cores this
    process may use, the GPU where nvidia-smi names one, and the load average when the table started."""
    model = platform.processor() or platform.machine()
    cpuinfo = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").is_file() else ""
    fields = {key: re.search(rf"^{key}\s*:\s*(.+)$", cpuinfo, re.M) for key in ("model name", "cpu family", "model")}
    if fields["model name"]:
        model = fields["model name"].group(1).strip()
        if fields["cpu family"] and fields["model"]:
            model += f" (family {fields['cpu family'].group(1).strip()}, model {fields['model'].group(1).strip()})"
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    gpu = gpu_name()
    load = f", load average {os.getloadavg()[0]:.1f} at the start" if hasattr(os, "getloadavg") else ""
    return f"{model}, {cores} cores" + (f", {gpu}" if gpu else "") + load


def stamp(table: Table, date: str, where: str) -> str:
    """The line above a table: when, where and how it was measured."""
    return f"Measured {date} on {where}. Regenerate: `python bench/results.py {table.name}` (runs `{shown(table)}`)."


def replace_block(text: str, name: str, body: str) -> str:
    """``text`` with the block between ``<!-- results:NAME -->`` and ``<!-- /results:NAME -->`` replaced by ``body``;
    a missing or doubled marker is an error naming it."""
    start, end = f"<!-- results:{name} -->", f"<!-- /results:{name} -->"
    if text.count(start) != 1 or text.count(end) != 1 or text.index(start) > text.index(end):
        raise ValueError(f"BENCHMARKS.md needs exactly one '{start}' followed by one '{end}'")
    head, rest = text.split(start)
    _, tail = rest.split(end)
    return f"{head}{start}\n{body.strip()}\n{end}{tail}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("table", nargs="?", choices=sorted(TABLES), help="the table to regenerate")
    parser.add_argument("--list", action="store_true", help="list the tables")
    parser.add_argument("--write", action="store_true", help="rewrite the table's block in BENCHMARKS.md")
    parser.add_argument("--work", type=Path, help="keep the runs here (default: a new temporary folder)")
    args = parser.parse_args()
    if args.list or args.table is None:
        for table in TABLES.values():
            needs = f"; needs {', '.join(table.needs)}" if table.needs else ""
            print(f"{table.name}: {table.summary} ({table.cost}{needs})\n    {shown(table)}")
        return
    table = TABLES[args.table]
    problems = missing_needs(table)
    if problems:
        print(f"error: table {table.name} needs " + "; ".join(problems), file=sys.stderr)
        raise SystemExit(2)
    if args.write and not BENCHMARKS.is_file():
        print(f"error: {BENCHMARKS} not found: run from a checkout of taichi-gs", file=sys.stderr)
        raise SystemExit(2)
    work = args.work or Path(tempfile.mkdtemp(prefix=f"results_{table.name}_"))
    work.mkdir(parents=True, exist_ok=True)
    where = machine()
    body = f"{stamp(table, datetime.date.today().isoformat(), where)}\n\n{run_table(table, work)}"
    print(body)
    if args.write:
        try:
            BENCHMARKS.write_text(replace_block(BENCHMARKS.read_text(), table.name, body))
        except ValueError as error:
            print(f"error: {error}", file=sys.stderr)
            raise SystemExit(2)


if __name__ == "__main__":
    main()
