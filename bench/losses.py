"""Image-loss kernels' times: L1 (+ clipped MSE), D-SSIM and masked depth L1, value and gradient in one
call each, float32 on the chosen backend, median over repeats after a warm-up.

    python bench/losses.py [--arch cpu] [--size 256x192 ...] [--repeats 60] [--rounds 3] [--baseline ROOT]

``--baseline ROOT`` times the same kernels from another code root (e.g. a ``git worktree`` of an older
commit) in alternating rounds, each in its own process (cwd and ``PYTHONPATH`` set to ROOT), and prints the
ratio of this tree's median to the baseline's, so the comparison survives a machine whose speed drifts.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parents[1]
KERNELS = ("l1_and_clipped_mse", "dssim", "masked_depth_l1")


def parse_size(text: str) -> tuple[int, int]:
    """"256x192" -> (256, 192)."""
    w, h = text.lower().split("x")
    return int(w), int(h)


def time_kernels(arch: str, sizes: list[tuple[int, int]], repeats: int) -> dict[str, dict[str, float]]:
    """{"WxH": {kernel: median ms}} for this process's ``taichi_gs``."""
    import taichi as ti

    from taichi_gs.kernels import losses, runtime
    from taichi_gs.kernels.splat import to_device

    runtime.init(arch)
    rng = np.random.default_rng(0)
    results = {}
    for w, h in sizes:
        pred = rng.uniform(0, 1, (h, w, 3))
        target = 0.6 * pred + 0.4 * rng.uniform(0, 1, (h, w, 3))
        p, t, g = (to_device(a, ti.f32) for a in (pred, target, np.zeros_like(pred)))
        dp, dt, dg = (to_device(a, ti.f32) for a in (rng.uniform(1, 2, (h, w)), rng.uniform(0, 2, (h, w)),
                                                      np.zeros((h, w))))
        calls = {"l1_and_clipped_mse": lambda: losses.l1_and_clipped_mse(p, t, g, weight=0.8),
                 "dssim": lambda: losses.dssim(p, t, g, weight=0.2),
                 "masked_depth_l1": lambda: losses.masked_depth_l1(dp, dt, dg, weight=0.1)}
        row = {}
        for name in KERNELS:
            for _ in range(3):
                calls[name]()
            ti.sync()
            times = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                calls[name]()
                ti.sync()
                times.append(time.perf_counter() - t0)
            row[name] = 1e3 * statistics.median(times)
        results[f"{w}x{h}"] = row
    return results


def run_in(root: Path, args: argparse.Namespace) -> dict[str, dict[str, float]]:
    """:func:`time_kernels` in a fresh process importing ``taichi_gs`` from ``root``."""
    command = [sys.executable, str(Path(__file__).resolve()), "--arch", args.arch, "--repeats", str(args.repeats),
               "--json", "--size", *args.size]
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run(command, cwd=root, env=env, capture_output=True, text=True, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--size", nargs="+", default=["256x192", "320x240", "640x480"])
    parser.add_argument("--repeats", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds with --baseline")
    parser.add_argument("--baseline", type=Path, help="another code root to time in the same run")
    parser.add_argument("--json", action="store_true", help=argparse.SUPPRESS)  # one process's raw result
    args = parser.parse_args()
    if args.json:
        print(json.dumps(time_kernels(args.arch, [parse_size(s) for s in args.size], args.repeats)))
        return
    roots = {"this tree": HERE} | ({"baseline": args.baseline.resolve()} if args.baseline else {})
    rounds: dict[str, list] = {name: [] for name in roots}
    for _ in range(args.rounds if args.baseline else 1):
        for name, root in roots.items():
            rounds[name].append(run_in(root, args))
    print(f"# {datetime.date.today()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
          f"--arch {args.arch}; median ms per call (median over rounds)")
    header = "| size | kernel | this tree |" + (" baseline | ratio |" if args.baseline else "")
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for size in args.size:
        for kernel in KERNELS:
            ours = statistics.median(r[size][kernel] for r in rounds["this tree"])
            cells = f"| {size} | {kernel} | {ours:.2f} |"
            if args.baseline:
                base = statistics.median(r[size][kernel] for r in rounds["baseline"])
                cells += f" {base:.2f} | {ours / base:.2f} |"
            print(cells)


if __name__ == "__main__":
    main()
