"""Time one Adam step over stage 3's five Gaussian tensors (means, quats, log-scales, opacity logits, SH-0
colours; float32) at a scene's size, the step's rows fewer than the buffers' as in a running stage.

    python bench/adam_step.py [--arch cpu] [--rows 144006] [--blocks 16] [--rounds 3] [--baseline ROOT]

Each process times ``--blocks`` blocks of 10 steps after a warm-up and reports the median ms per step;
``--baseline ROOT`` runs another code root in alternating rounds (see ``ab.py``) and prints the ratio of the
medians. ``TI_CPU_MAX_NUM_THREADS=1`` (Taichi reads it at init) gives the one-thread time.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
from ab import add_arguments, alternate, run_line

STEPS_PER_BLOCK = 10
HEADROOM = 1.1  # buffer rows per stepped row (a store keeps capacity beyond its count)


def time_steps(arch: str, rows: int, blocks: int) -> float:
    """Median ms per Adam step over ``blocks`` blocks of STEPS_PER_BLOCK steps."""
    import taichi as ti

    from taichi_gs.kernels import runtime

    runtime.init(arch)
    from taichi_gs.kernels.host_copy import write
    from taichi_gs.kernels.optim import Adam

    capacity = int(rows * HEADROOM)
    shapes = {"means": (capacity, 3), "quats": (capacity, 4), "log_scales": (capacity, 3),
              "opacity_logits": (capacity,), "colors": (capacity, 1, 3)}
    rng = np.random.default_rng(0)
    params, grads = {}, {}
    for name, shape in shapes.items():
        params[name], grads[name] = ti.ndarray(ti.f32, shape), ti.ndarray(ti.f32, shape)
        write(params[name], rng.normal(size=shape).astype(np.float32))
        write(grads[name], (rng.normal(size=shape) * 1e-3).astype(np.float32))
    adam = Adam(params, grads, {name: 0.01 for name in shapes})
    for _ in range(3):
        adam.step(rows)
    ti.sync()
    times = []
    for _ in range(blocks):
        start = time.perf_counter()
        for _ in range(STEPS_PER_BLOCK):
            adam.step(rows)
        ti.sync()
        times.append((time.perf_counter() - start) / STEPS_PER_BLOCK * 1e3)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--rows", type=int, default=144_006, help="rows a step updates (the sample's Gaussians)")
    parser.add_argument("--blocks", type=int, default=16)
    add_arguments(parser)
    args = parser.parse_args()
    if args.json:
        print(json.dumps({"ms": time_steps(args.arch, args.rows, args.blocks)}))
        return
    rounds = alternate(__file__, ["--arch", args.arch, "--rows", str(args.rows), "--blocks", str(args.blocks)],
                       args.baseline, args.rounds)
    print(run_line(args.arch) + f", {args.rows} rows; median ms per Adam step per round")
    for name, results in rounds.items():
        print(f"{name}: " + " ".join(f"{r['ms']:.2f}" for r in results))
    if args.baseline:
        ratio = statistics.median(r["ms"] for r in rounds["this tree"]) / statistics.median(
            r["ms"] for r in rounds["baseline"])
        print(f"this tree / baseline (medians over rounds): {ratio:.2f}")


if __name__ == "__main__":
    main()
