"""The launch and sync budget (issue 87): kernel launches, host reads of device data, host writes, syncs and
bytes copied per training step and per render, counted (``taichi_gs.kernels.launch_budget``), not timed, so
the same figures come out on any machine with the same backend.

    python bench/launch_budget.py [--arch cpu|vulkan|cuda|metal] [--combo 20000:320x240] [--tasks] [--json]
        [--cases render "stage 3 paper" "stage 3 fast" "stage 2"]

Cases, each counted on its second call (the first compiles and sizes the buffers), on random Gaussians
filling the view (``raster.scene``) against a random frame and a plane's depth:

* ``render``: one virtual-view render, forward + backward (colour and depth gradients), as a training step
  renders each view: deferred (the slot count stays on the device), its pose gradient left in a device row;
* ``stage 3 paper``: ``BlurScene.step`` as the paper preset takes it: k = 15 rendered views, SH degree 3,
  depth term, Adam, densification statistics;
* ``stage 3 fast``: as the fast preset: k = 9 views warped from one padded anchor render, SH degree 0, the
  frame's affine colour transform, depth term, Adam, statistics;
* ``stage 2``: ``DepthRefiner.step`` on one camera (depth and alpha render, depth and coverage losses,
  opacity binarisation, Adam).

Launches are the kernels the host launched; ``--tasks`` (CPU and CUDA) turns Taichi's kernel profiler on and adds
what the device ran: each top-level loop of a kernel is one task (one GPU dispatch). Prints a table of totals, then per case the
launches (and tasks) per kernel and the reads, writes and syncs per site.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from ab import run_line
from kernel_tasks import init_with_profiler
from raster import parse_combo, scene

PAPER_K, FAST_K = 15, 9
LAMBDA_DSSIM, LAMBDA_DEPTH = 0.2, 0.1
FAST_WARP_MARGIN = 14  # the fast preset's warp_px 12 + 2 (stages/deblur/run.warp_margin)
TASK_ARCHS = ("cpu", "cuda")  # where Taichi's kernel profiler counts tasks
TOTALS = ("launches", "tasks", "host_reads", "host_writes", "syncs", "bytes_to_device", "bytes_to_host")


CASES = ("render", "stage 3 paper", "stage 3 fast", "stage 2")


def case(name: str, n: int, width: int, height: int) -> Callable[[], object]:
    """One call of case ``name`` (see the module) on ``n`` random Gaussians at ``width`` x ``height``; the
    blurred frame a fixed random image, its depth a plane (the counts do not depend on either)."""
    from taichi_gs.render import POSE_COLUMNS, Camera, DeviceGaussians, Rasterizer, StepValues, to_device
    from taichi_gs.splats import Splats
    from taichi_gs.stages.deblur.model import BlurScene, Rates
    from taichi_gs.stages.refine.model import DepthRefiner

    (means, quats, log_scales, logits, colors), K = scene(n, width, height)
    rng = np.random.default_rng(1)
    base = np.eye(4)
    frame, depth = rng.uniform(0.0, 1.0, (height, width, 3)), np.full((height, width), 4.0)
    d_start = np.array([-0.004, 0.002, 0.0, 0.0, -0.003, 0.001])
    rates = Rates(means=1e-4, quats=1e-3, log_scales=5e-3, opacity_logits=0.05, colors=2.5e-3)
    if name == "render":
        gaussians, rasterizer = DeviceGaussians.from_numpy(means, quats, log_scales, logits, colors), Rasterizer()
        camera = Camera(K, base, width, height)
        d_rgb = to_device(rng.normal(size=(height, width, 3)), gaussians.dtype)
        d_depth = to_device(rng.normal(size=(height, width)), gaussians.dtype)
        pose = StepValues(gaussians.dtype).rows("pose", 1, POSE_COLUMNS)  # left on the device, not read
        return lambda: rasterizer.backward(gaussians, rasterizer.forward(gaussians, camera, deferred=True), d_rgb,
                                           d_depth, pose_into=pose)
    if name == "stage 3 paper":
        sh3 = np.concatenate([colors, np.zeros((n, 15, 3))], axis=1)
        paper = BlurScene(Splats(means, quats, log_scales, logits, sh3), K, width, height)
        return lambda: paper.step(frame, depth, base, d_start, -d_start, PAPER_K, LAMBDA_DSSIM, LAMBDA_DEPTH, rates)
    if name == "stage 3 fast":
        fast = BlurScene(Splats(means, quats, log_scales, logits, colors), K, width, height,
                         warp_margin=FAST_WARP_MARGIN)
        identity = np.hstack([np.eye(3), np.zeros((3, 1))])
        return lambda: fast.step(frame, depth, base, d_start, -d_start, FAST_K, LAMBDA_DSSIM, LAMBDA_DEPTH, rates,
                                 colour=identity, anchors=1)
    if name == "stage 2":
        refiner = DepthRefiner(means, logits, float(np.exp(np.median(log_scales))), K, width, height)
        return lambda: refiner.step([depth], [base], lambda_depth=1.0, lambda_coverage=0.3, lambda_opacity=0.1,
                                    lrs={"means": 1e-4, "opacity_logits": 0.05})
    raise ValueError(f"unknown case {name!r}: choose one of {', '.join(CASES)}")


def measure(arch: str | None, n: int, size: tuple[int, int], only: tuple[str, ...] | None = None,
            tasks: bool = False) -> dict[str, dict]:
    """{case: LaunchBudget.summary()} of each case's second call on ``arch`` (None: ``TAICHI_GS_ARCH``), all
    cases or those in ``only``; ``tasks``: with the kernel profiler on (device tasks counted)."""
    init_with_profiler(arch, tasks)
    from taichi_gs.kernels import launch_budget

    results = {}
    for name in only or CASES:
        call = case(name, n, *size)
        call()
        with launch_budget.counting() as budget:
            call()
        results[name] = budget.summary()
    return results


def print_tables(results: dict[str, dict]) -> None:
    """Markdown: totals per case, then each case's launches per kernel and reads / writes / syncs per site."""
    print("| case | " + " | ".join(TOTALS) + " |")
    print("|---|" + "---:|" * len(TOTALS))
    for name, r in results.items():
        print(f"| {name} | " + " | ".join("-" if r[key] is None else f"{r[key]:,}" for key in TOTALS) + " |")
    for name, r in results.items():
        tasks = r["tasks_by_kernel"]
        print(f"\n### {name}\n\n| launches per kernel | count |" + (" tasks |\n|---|---:|---:|" if tasks else "\n|---|---:|"))
        for kernel, count in r["launches_by_kernel"].items():
            print(f"| {kernel} | {count} |" + (f" {tasks.get(kernel, 0)} |" if tasks else ""))
        for kind in ("read", "write", "sync"):
            sites = r[f"{kind}_sites"]
            if sites:
                print(f"\n| {kind}s per site | count |\n|---|---:|")
                for site, count in sites.items():
                    print(f"| {site} | {count} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--combo", default="20000:320x240", help="Gaussians:WxH")
    parser.add_argument("--tasks", action="store_true", help="count device tasks too (Taichi's kernel profiler on)")
    parser.add_argument("--cases", nargs="+", choices=CASES, default=list(CASES))
    parser.add_argument("--json", action="store_true", help="print the counts as JSON")
    args = parser.parse_args()
    if args.tasks and args.arch not in TASK_ARCHS:
        parser.error(f"--tasks needs --arch {' or '.join(TASK_ARCHS)}: Taichi 1.7's kernel profiler crashed or missed "
                     "kernels on Vulkan (lavapipe)")
    n, size = parse_combo(args.combo)
    results = measure(args.arch, n, size, tuple(args.cases), args.tasks)
    if args.json:
        print(json.dumps({"arch": args.arch, "gaussians": n, "size": list(size), "cases": results}, indent=1))
        return
    print(run_line(args.arch) + f", {n} Gaussians at {size[0]}x{size[1]}; counts of one call after a warm-up\n")
    print_tables(results)


if __name__ == "__main__":
    main()
