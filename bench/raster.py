"""Rasterizer benchmark: forward and forward+backward times (median after warm-up) over scene
sizes and resolutions, a per-phase breakdown, and the NumPy reference renderer on a small scene
in the same run (so the speed ratio survives a noisy, shared machine).

    /work/venv/bin/python bench/raster.py [--arch cpu|cuda|vulkan|metal|auto] [--quick] [--combo N:WxH ...]
        [--run OUT ...]

``--run OUT`` adds a row per run folder: its newest splats rendered at every frame's newest pose in turn, at
the sequence's resolution (a reconstructed scene's uneven tiles instead of the grid's random Gaussians).

On a GPU backend the grid is 100k / 500k / 1M Gaussians at 640x480 (the GPU targets). "cores" is the
process's CPU-seconds over wall seconds while forward + backward repeat (on a GPU backend: host threads).
``TI_CPU_MAX_NUM_THREADS=1`` (Taichi reads it at init) gives the one-thread reference for a speed-up.
"""

from __future__ import annotations

import argparse
import datetime
import itertools
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from taichi_gs.kernels import runtime  # noqa: E402

SIZES = (5_000, 50_000, 200_000)
RESOLUTIONS = ((160, 120), (320, 240), (640, 480))
# The performance targets: forward+backward under 20 ms and under 400 ms on 2 CPU cores.
TARGETS = ((5_000, (160, 120)), (100_000, (320, 240)))
QUICK = ((50_000, (320, 240)), (200_000, (640, 480)))
GPU_GRID = ((100_000, (640, 480)), (500_000, (640, 480)), (1_000_000, (640, 480)))


def parse_combo(text: str) -> tuple[int, tuple[int, int]]:
    """"50000:320x240" -> (50000, (320, 240))."""
    n, res = text.split(":")
    w, h = res.lower().split("x")
    return int(n), (int(w), int(h))


def scene(n: int, width: int, height: int, seed: int = 0):
    """n Gaussians filling the view frustum at depth 2..8, each a few pixels across."""
    rng = np.random.default_rng(seed)
    fx = 0.8 * width
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1.0]])
    z = rng.uniform(2.0, 8.0, n)
    u = rng.uniform(-0.05, 1.05, n) * width
    v = rng.uniform(-0.05, 1.05, n) * height
    means = np.stack([(u - K[0, 2]) / fx * z, (v - K[1, 2]) / fx * z, z], axis=1)
    # screen sigma 0.5..1.5 px at 320x240 for 50k Gaussians, scaled so that the summed 3-sigma
    # footprints cover every pixel about 25 times whatever n and the resolution
    sigma_px = rng.uniform(0.5, 1.5, (n, 1)) * np.sqrt(50_000 / n) * width / 320
    log_scales = np.log(sigma_px * z[:, None] / fx * rng.uniform(0.5, 1.5, (n, 3)))
    quats = rng.normal(size=(n, 4))
    logits = rng.normal(size=n)
    colors = rng.normal(size=(n, 1, 3)) * 0.5
    return [means, quats, log_scales, logits, colors], K


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines() if Path("/proc/cpuinfo").exists() else []:
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def median_time(fn, repeats: int) -> float:
    return timed(fn, repeats)[0]


def timed(fn, repeats: int) -> tuple[float, float]:
    """(median wall seconds of ``repeats`` calls after a warm-up, CPU-seconds / wall seconds over them)."""
    fn()
    times = []
    cpu0 = os.times()
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    cpu1 = os.times()
    cpu = cpu1.user + cpu1.system - cpu0.user - cpu0.system
    return statistics.median(times), cpu / sum(times)


def synthetic_row(n: int, width: int, height: int):
    """(device Gaussians, [camera]) of :func:`scene`."""
    from taichi_gs.render import Camera, DeviceGaussians

    params, K = scene(n, width, height)
    return DeviceGaussians.from_numpy(*params), [Camera(K, np.eye(4), width, height)]


def run_row(run_dir: Path):
    """(device Gaussians, a camera per frame) of a run folder: its newest splats, every frame's newest pose."""
    from taichi_gs.export import final_poses, newest_splats_path
    from taichi_gs.geometry import raster_intrinsics
    from taichi_gs.io.ply import read_splats
    from taichi_gs.pipeline import open_run_sequence
    from taichi_gs.render import Camera, upload_splats

    path = newest_splats_path(run_dir)
    if path is None:
        raise SystemExit(f"{run_dir}: no splats.ply in deblur/ or refine/")
    sequence = open_run_sequence(run_dir)
    K, intr = raster_intrinsics(sequence.K()), sequence.intrinsics
    cameras = [Camera(K, pose, intr.width, intr.height) for pose in final_poses(run_dir, sequence)]
    return upload_splats(read_splats(path)), cameras


def measure(rast, gs, cameras) -> dict:
    """Median forward and forward + backward ms, cores, per-phase ms (mean of 3 passes over the cameras),
    slots and cover of rendering ``gs`` at ``cameras`` in turn (random image gradients)."""
    import taichi as ti

    from taichi_gs.kernels.splat import to_device

    width, height = cameras[0].width, cameras[0].height
    d_rgb = to_device(np.random.default_rng(1).normal(size=(height, width, 3)), ti.f32)
    d_depth = to_device(np.random.default_rng(2).normal(size=(height, width)), ti.f32)
    turns = itertools.cycle(cameras)

    def forward():
        rast.forward(gs, next(turns))
        ti.sync()

    def forward_backward():
        view = rast.forward(gs, next(turns))
        rast.backward(gs, view, d_rgb, d_depth)

    repeats = max(15 if gs.n * width < 50_000 * 640 else 5, len(cameras))
    row = {"forward": 1e3 * median_time(forward, repeats)}
    t_all, row["cores"] = timed(forward_backward, repeats)
    row["forward_backward"] = 1e3 * t_all
    phases: dict = {}
    passes = 3 * len(cameras)
    slots = covered = 0.0
    for i in range(passes):
        view = rast.forward(gs, cameras[i % len(cameras)], timings=phases)
        t0 = time.perf_counter()
        rast.backward(gs, view, d_rgb, d_depth)
        phases["backward"] = phases.get("backward", 0.0) + time.perf_counter() - t0
        rect = view.rect.to_numpy()[:gs.n]
        box = np.clip(rect[:, 2] - rect[:, 0] + 1, 0, None) * np.clip(rect[:, 3] - rect[:, 1] + 1, 0, None)
        slots += view.n_slots / passes
        covered += box.sum() / (width * height) / passes
    row.update({k: 1e3 * v / passes for k, v in phases.items()})
    row["slots"], row["cover"] = round(slots), covered
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--arch", default="cpu", choices=runtime.ARCH_CHOICES)
    parser.add_argument("--quick", action="store_true", help="only the target and a few large combos")
    parser.add_argument("--combo", action="append", type=parse_combo, default=[],
                        help="N:WxH to run instead of the grid (repeatable), e.g. 5000:160x120")
    parser.add_argument("--run", action="append", type=Path, default=[],
                        help="also a run folder's newest splats at its frames' poses (repeatable)")
    args = parser.parse_args()
    backend = runtime.init(args.arch)

    import reference_renderer
    import taichi as ti

    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer

    print(f"# {datetime.date.today()}  arch={backend.arch}  device {backend.device}  "
          f"cpu threads={backend.cpu_threads}  cpu {cpu_model()}  python {platform.python_version()}")
    print("# times in ms, median after warm-up; SH degree 0; cover = mean number of Gaussian support "
          "boxes per pixel")
    rast = Rasterizer(ti.f32)
    print(f"{'N':>8} {'res':>8} {'slots':>9} {'fwd ms':>8} {'fwd+bwd ms':>11} {'project':>8} {'sort':>7} "
          f"{'blend':>7} {'backward':>9} {'cover':>6} {'cores':>6}  scene")
    grid = [(n, res) for n in SIZES for res in RESOLUTIONS]
    if args.combo:
        combos = sorted(set(args.combo))
    elif backend.gpu_kernels:
        combos = sorted(set(GPU_GRID))
    else:
        combos = sorted(set(TARGETS) | set(QUICK if args.quick else grid))
    scenes = itertools.chain(((*synthetic_row(n, width, height), "random") for n, (width, height) in combos),
                             ((*run_row(run), str(run)) for run in args.run))
    for gs, cameras, label in scenes:
        row = measure(rast, gs, cameras)
        width, height = cameras[0].width, cameras[0].height
        print(f"{gs.n:>8} {width}x{height:<4} {row['slots']:>9} {row['forward']:>8.1f} "
              f"{row['forward_backward']:>11.1f} {row['project']:>8.1f} {row['sort']:>7.1f} {row['blend']:>7.1f} "
              f"{row['backward']:>9.1f} {row['cover']:>6.1f} {row['cores']:>6.2f}  {label}", flush=True)

    # same small scene through the NumPy reference renderer and the Taichi forward
    params, K = scene(500, 160, 120)
    gs = DeviceGaussians.from_numpy(*params)
    cam = Camera(K, np.eye(4), 160, 120)
    t_ref = median_time(lambda: reference_renderer.render(*params, K, np.eye(4), 160, 120), 3)
    t_ti = median_time(lambda: (rast.forward(gs, cam), ti.sync()), 15)
    print(f"reference (NumPy, per-pixel, 500 Gaussians, 160x120): {1e3 * t_ref:.1f} ms; "
          f"taichi forward {1e3 * t_ti:.2f} ms; ratio {t_ref / t_ti:.0f}x")


if __name__ == "__main__":
    main()
