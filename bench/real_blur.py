"""Real extreme blur with a sharp reference (issue 84): taichi-gs on sequences made by ``taichi-gs import --average W``
(W consecutive real frames averaged in linear light; the centre frame is the sharp reference, its depth and pose).

    python bench/real_blur.py SEQ [SEQ ...] --out DIR [--count N] [--arm "NAME=FILE.toml" ...] [--no-paper]
        [--json OUT] [--peers "O3D hybrid,O3D ICP"]

Per sequence folder (never written):
- ours: ``taichi-gs reconstruct SEQ`` (the default ``fast`` preset) in DIR/NAME/ours, then ``taichi-gs eval --json``;
- paper: the same with ``--preset paper`` (the paper's schedules: 30000 stage-3 iterations, hours on a CPU;
  ``--no-paper`` leaves it out);
- each ``--arm NAME=FILE.toml``: stage 3 alone (``taichi-gs deblur --config FILE``) on a copy of ours' stage-1 and
  stage-2 folders, in DIR/NAME/ARM (its seconds are ours' stages 1-2 plus its own stage 3).
``--count N`` runs each sequence's first N frames (``reconstruct --count N``; the issue's tables use 40). Finished runs
are read back (a killed benchmark resumes). With ``--peers``, ``bench/pose.py --sequence`` scores
those stage-1 peers on the same folders (its own table, printed after ours).

Prints one Markdown table, a row per sequence and method: W, size, frames, the median streak of the exposures
(blur.json, pixels), ATE after stage 1 and of the final (stage-3 mid-exposure) trajectory (mm), held-out PSNR / SSIM
of the sharp renders against the centre frames, the blurred input's against the same frames, the gain, two
registration figures (held-out means: the render as the rolling shutter reads it against the centre frame, which
was read so; the render moved by its best sub-pixel translation onto the centre frame, inside an 8 px border, with
the shift's length), and the run's wall seconds per frame. The grids to judge by eye are each run's report/test_views.png (input | ours | centre
frame | depth), listed after the table. ``--json OUT`` writes the rows.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from taichi_gs.evaluate import psnr
from taichi_gs.io.sequence import read_color

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "taichi_gs.cli"]
STAGE_1_2 = ("pose", "refine")
BORDER_PX = 8  # the shifted comparison leaves out this border (the shift moves the image edge in)


def _run(args: list[str], log: Path) -> None:
    """Run a taichi-gs command, its output appended to ``log``; a failure stops the benchmark with the log's tail."""
    with log.open("a") as handle:
        done = subprocess.run([*CLI, *args], cwd=ROOT, stdout=handle, stderr=subprocess.STDOUT, check=False)
    if done.returncode != 0:
        tail = log.read_text().splitlines()[-20:]
        sys.exit(f"{' '.join(args)} failed (exit {done.returncode}); {log}:\n" + "\n".join(tail))


def _evaluate(run: Path) -> dict[str, Any]:
    """``taichi-gs eval --json`` of a run folder (metrics.json is read back when it is newer than stage 3)."""
    metrics, done = run / "metrics.json", run / "deblur" / "done.json"
    if not (metrics.is_file() and done.is_file() and metrics.stat().st_mtime >= done.stat().st_mtime):
        _run(["eval", str(run), "--json", "--quiet"], run.parent / f"{run.name}.log")
    return json.loads(metrics.read_text())


def reconstruct(sequence: Path, run: Path, preset: str, count: int | None = None) -> dict[str, Any]:
    """A whole run with ``preset`` on the first ``count`` frames (all: None), resumed where it stopped, evaluated."""
    run.parent.mkdir(parents=True, exist_ok=True)
    if not (run / "deblur" / "done.json").is_file():
        _run(["reconstruct", str(sequence), "--out", str(run), "--preset", preset, "--quiet",
              *(["--count", str(count)] if count else [])],
             run.parent / f"{run.name}.log")
    return _evaluate(run)


def arm(base: Path, run: Path, config: Path) -> dict[str, Any]:
    """Stage 3 with ``config`` on a copy of ``base``'s stages 1 and 2, evaluated."""
    if not (run / "deblur" / "done.json").is_file():
        shutil.rmtree(run, ignore_errors=True)
        shutil.copytree(base, run, ignore=lambda folder, names: [n for n in names if folder == str(base)
                                                                 and n in ("deblur", "report", "metrics.json")])
        _run(["deblur", str(run), "--config", str(config), "--quiet"], run.parent / f"{run.name}.log")
    return _evaluate(run)


def shifted_onto(image: np.ndarray, reference: np.ndarray, inner: tuple[slice, slice],
                 steps: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """``image`` moved by the sub-pixel translation that best matches ``reference`` inside ``inner`` (phase
    correlation, then Gauss-Newton on the squared grey-level difference), and that translation (dx, dy)."""
    grey = [cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float64) for x in (image, reference)]
    (dx, dy), _ = cv2.phaseCorrelate(grey[1], grey[0])
    shift = np.array([dx, dy])

    def moved(x: np.ndarray, by: np.ndarray) -> np.ndarray:
        return cv2.warpAffine(x, np.float64([[1, 0, -by[0]], [0, 1, -by[1]]]), x.shape[1::-1],
                              flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)

    for _ in range(steps):
        current = moved(grey[0], shift)
        gx, gy = cv2.Sobel(current, cv2.CV_64F, 1, 0, ksize=1) / 2, cv2.Sobel(current, cv2.CV_64F, 0, 1, ksize=1) / 2
        J = np.stack([gx[inner].ravel(), gy[inner].ravel()], axis=1)  # d moved / d shift: moved(p) = x(p + shift)
        residual = (current - grey[1])[inner].ravel()
        shift = shift - np.linalg.solve(J.T @ J + 1e-9 * np.eye(2), J.T @ residual)
    return moved(image, shift), shift


def registration(sequence: Path, run: Path) -> dict[str, float | None]:
    """Mean over the held-out views of: the sharp render read as the rolling shutter reads it (deblur/renders/as_read/,
    where the run has one) against the centre frame, and the render moved by its best sub-pixel translation onto
    the centre frame (phase correlation) against it inside a BORDER_PX border, with that shift's length (pixels):
    how much of the gap to the centre frame is where the render sits rather than what it shows."""
    split_path = run / "deblur" / "split.json"
    if not (sequence / "sharp").is_dir() or not split_path.is_file():
        return {"as_read_psnr_db": None, "shifted_psnr_db": None, "shift_px": None}
    names = [line.split()[1].split("/", 1)[1].rsplit(".", 1)[0]
             for line in (sequence / "frames.txt").read_text().splitlines() if line and line[0] != "#"]
    inner = (slice(BORDER_PX, -BORDER_PX), slice(BORDER_PX, -BORDER_PX))
    as_read, shifted, shifts = [], [], []
    for i in json.loads(split_path.read_text())["test"]:
        sharp = read_color(sequence / "sharp" / f"{names[i]}.png")
        render = read_color(run / "deblur" / "renders" / "sharp" / f"{names[i]}.png")
        read = run / "deblur" / "renders" / "as_read" / f"{names[i]}.png"
        as_read.append(psnr(read_color(read) if read.is_file() else render, sharp))
        moved, shift = shifted_onto(render, sharp, inner)
        shifted.append(psnr(moved[inner], sharp[inner]))
        shifts.append(float(np.hypot(*shift)))
    if not shifts:
        return {"as_read_psnr_db": None, "shifted_psnr_db": None, "shift_px": None}
    return {"as_read_psnr_db": float(np.mean(as_read)), "shifted_psnr_db": float(np.mean(shifted)),
            "shift_px": float(np.mean(shifts))}


def sequence_facts(sequence: Path, count: int | None = None) -> dict[str, Any]:
    """W, image size, frame count and median streak (pixels) of an averaged sequence folder's first ``count`` frames
    (all: None)."""
    intrinsics = json.loads((sequence / "intrinsics.json").read_text())
    frames = [line for line in (sequence / "frames.txt").read_text().splitlines() if line and line[0] != "#"][:count]
    blur_path = sequence / "blur.json"
    blur = json.loads(blur_path.read_text()) if blur_path.is_file() else {}
    streaks = sorted(f["median_px"] for f in blur.get("frames", [])[:count] if f.get("median_px") is not None)
    return {"window": blur.get("window"), "size": f"{intrinsics['width']}x{intrinsics['height']}",
            "frames": len(frames), "streak_px": streaks[len(streaks) // 2] if streaks else None}


def row(sequence: Path, run: Path, method: str, metrics: dict[str, Any], seconds: float,
        count: int | None = None) -> dict[str, Any]:
    """One table row from a run's metrics (a run of the sequence's first ``count`` frames; all: None)."""
    trajectory, test = metrics.get("trajectory") or {}, (metrics.get("images") or {}).get("test") or {}
    facts = sequence_facts(sequence, count)
    final = next((trajectory[s] for s in ("deblur", "refine", "pose") if s in trajectory), {})
    return {"sequence": sequence.name, "method": method, **facts,
            "stage1_ate_mm": _mm((trajectory.get("pose") or {}).get("ate_m")), "final_ate_mm": _mm(final.get("ate_m")),
            "psnr_db": test.get("psnr_db"), "ssim": test.get("ssim"),
            "input_psnr_db": test.get("blurred_input_psnr_db"), "input_ssim": test.get("blurred_input_ssim"),
            "seconds_per_frame": seconds / facts["frames"], **registration(sequence, run)}


def _mm(metres: float | None) -> float | None:
    return None if metres is None else 1000.0 * metres


def stage_seconds(metrics: dict[str, Any], stages: tuple[str, ...]) -> float:
    """Wall seconds of ``stages`` as the run recorded them."""
    return sum((metrics["stages"].get(s) or {}).get("seconds") or 0.0 for s in stages)


def _cell(value: float | None, digits: int) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def table(rows: list[dict[str, Any]]) -> str:
    """The Markdown table of ``rows``."""
    lines = [("| sequence | W | size | frames | streak px | method | stage-1 ATE mm | final ATE mm | held-out PSNR / SSIM "
              "| input PSNR / SSIM | gain dB / SSIM | as read dB | shifted dB (px) | s / frame |"),
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        gain = (None, None) if r["psnr_db"] is None or r["input_psnr_db"] is None else \
            (r["psnr_db"] - r["input_psnr_db"], r["ssim"] - r["input_ssim"])
        lines.append(f"| {r['sequence']} | {r['window'] or '-'} | {r['size']} | {r['frames']} | "
                     f"{_cell(r['streak_px'], 1)} | {r['method']} | {_cell(r['stage1_ate_mm'], 1)} | "
                     f"{_cell(r['final_ate_mm'], 1)} | {_cell(r['psnr_db'], 2)} / {_cell(r['ssim'], 3)} | "
                     f"{_cell(r['input_psnr_db'], 2)} / {_cell(r['input_ssim'], 3)} | "
                     f"{_cell(gain[0], 2)} / {_cell(gain[1], 3)} | {_cell(r['as_read_psnr_db'], 2)} | "
                     f"{_cell(r['shifted_psnr_db'], 2)} ({_cell(r['shift_px'], 2)}) | {_cell(r['seconds_per_frame'], 1)} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", type=Path, nargs="+", help="folders made by taichi-gs import --average W")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--count", type=int, default=None, help="run each sequence's first N frames")
    parser.add_argument("--arm", action="append", default=[], help="NAME=FILE.toml: stage 3 with this config")
    parser.add_argument("--no-paper", action="store_true", help="leave out the paper preset (hours on a CPU)")
    parser.add_argument("--json", type=Path, default=None, help="write the rows here")
    parser.add_argument("--peers", default="", help="bench/pose.py --methods for the stage-1 peers' ATE")
    args = parser.parse_args()
    arms = [tuple(a.split("=", 1)) for a in args.arm]
    if any(len(a) != 2 or not Path(a[1]).is_file() for a in arms):
        sys.exit(f"--arm needs NAME=FILE.toml with an existing file, got {args.arm}")
    rows, grids = [], []
    for sequence in args.sequences:
        if not (sequence / "frames.txt").is_file():
            sys.exit(f"{sequence}: not a sequence folder (no frames.txt); make one with taichi-gs import --average W")
        folder = args.out / sequence.name
        ours = reconstruct(sequence, folder / "ours", "fast", args.count)
        runs = [("ours", folder / "ours", ours, stage_seconds(ours, (*STAGE_1_2, "deblur")))]
        for name, config in arms:
            metrics = arm(folder / "ours", folder / name, Path(config))
            runs.append((name, folder / name, metrics,
                         stage_seconds(ours, STAGE_1_2) + stage_seconds(metrics, ("deblur",))))
        if not args.no_paper:
            paper = reconstruct(sequence, folder / "paper", "paper", args.count)
            runs.append(("paper", folder / "paper", paper, stage_seconds(paper, (*STAGE_1_2, "deblur"))))
        for name, run, metrics, seconds in runs:
            rows.append(row(sequence, run, name, metrics, seconds, args.count))
            grids.append(run / "report" / "test_views.png")
        print(table(rows[-len(runs):]), flush=True)
    print("\n" + table(rows))
    print("\ngrids (input | ours | centre frame | depth):\n" + "\n".join(f"- {g}" for g in grids))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    if args.peers:
        subprocess.run([sys.executable, str(ROOT / "bench" / "pose.py"), "--methods", args.peers,
                        "--out", str(args.out / "peers"),
                        *[a for s in args.sequences for a in ("--sequence", str(s))]], cwd=ROOT, check=True)


if __name__ == "__main__":
    main()
