"""Benchmark the whole pipeline (`taichi-gs reconstruct`) as sequences grow.

    python bench/e2e.py [--frames 30 60 120] [--width 320 --height 240] [--preset fast] [--arch cpu]
        [--sequence PATH [--first F] [--scale S] [--camera C]] [--config TOML]

For each length: a synthetic hand-held sequence with extreme blur is generated (or, with ``--sequence``, that
many frames of a recording in any layout `taichi-gs` reads, from frame F, read at S times its size), `taichi-gs
reconstruct --profile` runs in its own process (so peak memory is that run's alone), then `taichi-gs
eval`. Prints a Markdown table: wall seconds, CPU-seconds (user + sys) and cores per stage (from the
run's profile.json), seconds per frame, peak resident memory, Gaussians after stage 3, final ATE, and
PSNR/SSIM of the held-out views against the sharp ground truth next to the blurred input's own scores (on a
recording: the render against its held-out frames, next to the floor: the nearer training frames warped into
each held-out view).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2

from taichi_gs.synth import SynthConfig, generate


STAGES = ("pose", "refine", "deblur")


def taichi_gs(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "taichi_gs.cli", *args], check=True, stdout=subprocess.DEVNULL)


def recording_options(args: argparse.Namespace, frames: int) -> list[str]:
    """`reconstruct` options that read ``frames`` frames of ``--sequence`` from ``--first`` at ``--scale``."""
    options = ["--first", str(args.first), "--count", str(frames), "--scale", str(args.scale)]
    return options + (["--camera", args.camera] if args.camera else [])


def run_one(frames: int, args: argparse.Namespace, work: Path) -> dict:
    if args.sequence:
        seq, reading = args.sequence, recording_options(args, frames)
    else:
        seq = generate(SynthConfig(width=args.width, height=args.height, frames=frames, trajectory="handheld",
                                   blur="extreme", seed=0), work / f"seq{frames}")
        reading = []
    out = work / f"run{frames}"
    config = ["--config", str(args.config)] if args.config else []
    start = time.perf_counter()
    taichi_gs("--arch", args.arch, "reconstruct", str(seq), *reading, "--out", str(out), "--preset", args.preset,
              *config, "--profile")
    wall = time.perf_counter() - start
    taichi_gs("eval", str(out))
    metrics = json.loads((out / "metrics.json").read_text())
    profile = json.loads((out / "profile.json").read_text())
    stages = metrics["stages"]
    height, width = cv2.imread(str(min((out / "deblur" / "renders" / "sharp").glob("*.png")))).shape[:2]
    return {
        "frames": frames, "size": f"{width}x{height}", "wall": wall,
        **{f"{s}_s": stages[s]["seconds"] for s in STAGES},
        **{f"{s}_cpu": profile[s]["cpu_s"] for s in STAGES},
        "gaussians": json.loads((out / "deblur" / "history.json").read_text())[-1]["gaussians"],
        "peak_mb": max(s["peak_rss_mb"] for s in stages.values()),
        "ate_mm": 1000 * metrics["trajectory"]["deblur"]["ate_m"],
        **held_out_scores(metrics, recording=args.sequence is not None),
        "arch": metrics["arch"],
    }


def held_out_scores(metrics: dict, recording: bool) -> dict[str, float]:
    """PSNR / SSIM of the held-out views and of their floor: against the sharp ground truth, the floor being the
    blurred input; on a recording (no ground truth), against the held-out frames, the floor being the nearer
    training frames warped into each view (``eval``'s no-reference section). NaN where ``eval`` has no score."""
    nan = float("nan")
    if recording:
        test = metrics["no_reference"]["test"]
        keys = ("held_out_psnr_db", "held_out_ssim", "warped_neighbour_psnr_db", "warped_neighbour_ssim")
    else:
        test = (metrics.get("images") or {}).get("test", {})
        keys = ("psnr_db", "ssim", "blurred_input_psnr_db", "blurred_input_ssim")
    return {name: test.get(key, nan) for name, key in zip(("psnr", "ssim", "floor_psnr", "floor_ssim"), keys)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, nargs="+", default=[30, 60, 120])
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--preset", default="fast")
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--work", type=Path, default=None, help="keep sequences and runs here")
    parser.add_argument("--sequence", type=Path, help="a recording to read instead of synthetic sequences")
    parser.add_argument("--first", type=int, default=0, help="the recording's first frame")
    parser.add_argument("--scale", type=float, default=1.0, help="read the recording at this scale")
    parser.add_argument("--camera", help="the recording's camera, as `taichi-gs reconstruct --camera` takes it")
    parser.add_argument("--config", type=Path, help="a TOML file for `taichi-gs reconstruct --config`")
    args = parser.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="bench_e2e_"))
    floor = "floor" if args.sequence else "blurred"
    print("| frames | image | pose s (CPU-s, cores) | refine s (CPU-s, cores) | deblur s (CPU-s, cores) | total s "
          "| s per frame | CPU-s per frame | peak RSS (MB) | Gaussians | ATE (mm) | test PSNR (dB) | test SSIM "
          f"| {floor} PSNR (dB) | {floor} SSIM | arch |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for frames in args.frames:
        r = run_one(frames, args, work)
        per_stage = " | ".join(f"{r[f'{s}_s']:.0f} ({r[f'{s}_cpu']:.0f}, {r[f'{s}_cpu'] / r[f'{s}_s']:.2f})"
                               for s in STAGES)
        cpu = sum(r[f"{s}_cpu"] for s in STAGES)
        print(f"| {r['frames']} | {r['size']} | {per_stage} | {r['wall']:.0f} | {r['wall'] / frames:.1f} "
              f"| {cpu / frames:.1f} | {r['peak_mb']:.0f} | {r['gaussians']} | {r['ate_mm']:.2f} | {r['psnr']:.2f} "
              f"| {r['ssim']:.3f} | {r['floor_psnr']:.2f} | {r['floor_ssim']:.3f} | {r['arch']} |", flush=True)


if __name__ == "__main__":
    main()
