"""Where a render's time goes inside its kernels: Taichi's kernel profiler times every offloaded task (each
top-level loop of a kernel) of rasterizer forward + backward passes on the synthetic scene of ``raster.py``,
float32 on the chosen backend.

    python bench/kernel_tasks.py [--arch cpu] [--combo 100000:256x192] [--passes 30] [--rounds 3] [--baseline ROOT]
        [--run RUN_DIR] [--margin 14]

Tasks are named ``kernel:task loop`` (Taichi's numbering of a kernel's top-level loops; the compile counter
is dropped so that two code roots line up, as long as their loops are the same). A second table sums each
kernel's loops. ``--baseline ROOT`` profiles another code root in alternating rounds (see ``ab.py``) and
prints the ratio of this tree's median to the baseline's per task and per kernel. ``--run RUN_DIR`` profiles a
finished ``taichi-gs reconstruct`` folder's trained scene instead (deblur/splats.ply at the input size, the passes
cycling over the run's final poses; ``--combo`` is then ignored). ``--margin M`` renders M pixels more on every side
with no image gradient there, as stage 3's padded anchor renders (14 px in the fast preset at the sample's size,
where a warped view samples only part of it).
"""

from __future__ import annotations

import argparse
import json
import re
import statistics
from pathlib import Path

import numpy as np

from ab import add_arguments, alternate, run_line
from raster import parse_combo, scene

MIN_MS = 0.05  # tasks under this many ms per pass are summed into "other tasks"


def task_name(profiler_name: str) -> str:
    """"backward_c86_0_kernel_1_range_for" -> "backward:1 range_for"."""
    match = re.fullmatch(r"(\w+?)_c\d+_\d+_kernel_(\d+)_(\w+)", profiler_name)
    return f"{match[1]}:{match[2]} {match[3]}" if match else profiler_name


def init_with_profiler(arch: str, profiler: bool = True):
    """``taichi_gs``'s one Taichi init on ``arch``, with Taichi's kernel profiler on or off; the backend it got."""
    import taichi as ti

    from taichi_gs.kernels import runtime

    init = ti.init
    ti.init = lambda **kw: init(**{**kw, "kernel_profiler": profiler})  # runtime.init is the one place that inits
    try:
        return runtime.init(arch)
    finally:
        ti.init = init


def run_scene(run_dir: Path) -> tuple[list[np.ndarray], np.ndarray, tuple[int, int], list[np.ndarray]]:
    """(Gaussian parameters, K, (width, height), camera-to-world poses) of a finished run's trained scene."""
    from taichi_gs.export import final_poses
    from taichi_gs.io.ply import read_splats
    from taichi_gs.pipeline import open_run_sequence
    from taichi_gs.render import raster_intrinsics

    sequence = open_run_sequence(run_dir)  # with the options the run loaded it with (--first, --count, --scale ...)
    intr = sequence.intrinsics
    s = read_splats(run_dir / "deblur" / "splats.ply")
    params = [s.means, s.quats, s.log_scales, s.opacity_logits, s.sh]
    return params, raster_intrinsics(intr.K()), (intr.width, intr.height), list(final_poses(run_dir, sequence))


def profile_tasks(arch: str, n: int, size: tuple[int, int], passes: int, run_dir: Path | None = None,
                  margin: int = 0) -> dict[str, float]:
    """{task: mean ms per forward + backward pass} over ``passes`` passes after three warm-up passes; the
    camera turns a little between passes (with ``run_dir``: its trained scene at its poses, in turn); ``margin``
    pixels more on every side, without image gradients."""
    import taichi as ti
    from taichi.lang import impl

    from taichi_gs.geometry import se3_exp

    init_with_profiler(arch)
    from taichi_gs.kernels.splat import to_device
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer

    if run_dir is None:
        width, height = size
        params, K = scene(n, width, height)
        poses = [se3_exp(np.array([0.01 * i, 0.0, 0.0, 0.0, 0.004 * i, 0.0])) for i in range(-2, 3)]
    else:
        params, K, (width, height), poses = run_scene(run_dir)
    K = K.copy()
    K[:2, 2] += margin
    width, height = width + 2 * margin, height + 2 * margin
    inside = np.zeros((height, width))
    inside[margin:height - margin, margin:width - margin] = 1.0
    gs = DeviceGaussians.from_numpy(*params)
    rast = Rasterizer(ti.f32)
    d_rgb = to_device(np.random.default_rng(1).normal(size=(height, width, 3)) * inside[..., None], ti.f32)
    d_depth = to_device(np.random.default_rng(2).normal(size=(height, width)) * inside, ti.f32)
    cameras = [Camera(K, pose, width, height) for pose in poses]
    for i in range(passes + 3):
        if i == 3:
            ti.sync()
            ti.profiler.clear_kernel_profiler_info()
        view = rast.forward(gs, cameras[i % len(cameras)])
        rast.backward(gs, view, d_rgb, d_depth)
    ti.sync()
    prog = impl.get_runtime().prog
    prog.sync_kernel_profiler()
    prog.update_kernel_profiler()
    totals: dict[str, float] = {}
    for record in prog.get_kernel_profiler_records():
        name = task_name(record.name)
        totals[name] = totals.get(name, 0.0) + record.kernel_time
    return {name: ms / passes for name, ms in totals.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--combo", default="100000:256x192", help="Gaussians:WxH")
    parser.add_argument("--passes", type=int, default=30)
    parser.add_argument("--run", type=Path, help="a finished reconstruct folder: profile its trained scene")
    parser.add_argument("--margin", type=int, default=0, help="pixels added on every side, without gradients")
    add_arguments(parser)
    args = parser.parse_args()
    if args.json:
        n, (w, h) = parse_combo(args.combo)
        print(json.dumps(profile_tasks(args.arch, n, (w, h), args.passes, args.run, args.margin)))
        return
    n, size = args.combo.split(":")
    run_args = (["--run", str(args.run.resolve())] if args.run else []) + ["--margin", str(args.margin)]
    rounds = alternate(__file__, ["--arch", args.arch, "--combo", args.combo, "--passes", str(args.passes), *run_args],
                       args.baseline, args.rounds)

    def median(name: str, task: str) -> float:
        return statistics.median(r.get(task, 0.0) for r in rounds[name])

    tasks = sorted({t for results in rounds.values() for r in results for t in r},
                   key=lambda t: -median("this tree", t))  # a loop of one tree alone shows 0 in the other
    scene_name = f"{args.run}'s trained scene at its poses" if args.run else f"{n} Gaussians at {size}"
    scene_name += f", {args.margin} px margin without gradients" if args.margin else ""
    print(run_line(args.arch) + f", {scene_name}; mean ms per forward + backward pass (median over rounds)")
    header = "| task | this tree |" + (" baseline | ratio |" if args.baseline else "")
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    names = ["this tree"] + (["baseline"] if args.baseline else [])
    rows = [(t, [median(name, t) for name in names]) for t in tasks]
    shown = [(t, ms) for t, ms in rows if max(ms) >= MIN_MS]
    other = [sum(ms[i] for t, ms in rows if max(ms) < MIN_MS) for i in range(len(names))]
    total = [sum(ms[i] for _, ms in rows) for i in range(len(names))]
    kernels: dict[str, list[float]] = {}
    for task, ms in rows:
        kernel = task.split(":")[0]
        kernels[kernel] = [a + b for a, b in zip(kernels.get(kernel, [0.0] * len(names)), ms)]
    print_rows(shown + [("other tasks", other), ("total", total)], bool(args.baseline))
    print("\nPer kernel (its loops summed; they line up between trees whose loops were numbered differently):\n")
    print(header.replace("| task |", "| kernel |"))
    print("|" + "---|" * (header.count("|") - 1))
    print_rows(sorted(kernels.items(), key=lambda item: -item[1][0]), bool(args.baseline))


def print_rows(rows: list[tuple[str, list[float]]], baseline: bool) -> None:
    """Markdown rows: name, ms per tree, and this tree / baseline."""
    for name, ms in rows:
        ratio = (f" | {ms[0] / ms[1]:.2f}" if ms[1] > 0 else " | -") if baseline else ""
        print(f"| {name} | " + " | ".join(f"{x:.2f}" for x in ms) + ratio + " |")


if __name__ == "__main__":
    main()
