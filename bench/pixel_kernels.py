"""The per-pixel kernels outside the rasterizer: stage 3's image losses (L1 + clipped MSE, D-SSIM, masked
depth L1; value and gradient in one call each), stage 2's depth terms (alpha-normalised depth L1 and
coverage) and the warped virtual views (forward and backward of six views warped from one padded anchor
render), float32 on the chosen backend, median over repeats after a warm-up.

    python bench/pixel_kernels.py [--arch cpu] [--size 256x192 ...] [--repeats 60] [--rounds 3] [--baseline ROOT]

``--baseline ROOT`` times the same kernels from another code root in alternating rounds (see ``ab.py``)
and prints the ratio of this tree's median to the baseline's ("-" for a kernel the baseline lacks).
(Before 2026-11-27 this script was ``bench/losses.py`` and timed the losses only.)
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from ab import add_arguments, alternate, run_line

KERNELS = ("l1_and_clipped_mse", "dssim", "masked_depth_l1", "stage2_depth_terms", "warp_forward", "warp_backward")
WARP_VIEWS = 6
WARP_MARGIN = 8


def parse_size(text: str) -> tuple[int, int]:
    """"256x192" -> (256, 192)."""
    w, h = text.lower().split("x")
    return int(w), int(h)


def warp_views(width: int) -> np.ndarray:
    """(WARP_VIEWS, 4, 4) target -> anchor transforms of a blur trail: up to 1.5 cm and 0.75 degrees
    (about 4-6 px at 2 m for the focal length of ``width``), rotation and translation mixed. One of them is
    the anchor's own pose, which the warp reads instead of interpolating (since 2026-11-29, seventh session)."""
    from taichi_gs.geometry import se3_exp

    steps = np.arange(WARP_VIEWS) - WARP_VIEWS // 2
    return np.stack([se3_exp(np.array([0.005 * i, 0.002 * i, 0.0, 0.001 * i, 0.0025 * i, 0.0])) for i in steps])


def surface_depth(height: int, width: int) -> np.ndarray:
    """Blended z of an opaque scene: a wall slanting from 1.8 to 2.4 m with a box at 1.2 m in the middle."""
    z = np.tile(np.linspace(1.8, 2.4, width), (height, 1))
    z[height // 3: 2 * height // 3, width // 3: 2 * width // 3] = 1.2
    return z


def time_kernels(arch: str, sizes: list[tuple[int, int]], repeats: int) -> dict[str, dict[str, float]]:
    """{"WxH": {kernel: median ms}} for this process's ``taichi_gs``."""
    import taichi as ti

    from taichi_gs.kernels import losses, runtime, warp
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
        trans = to_device(rng.uniform(0, 0.8, (h, w)), ti.f32)
        grad_alpha = to_device(np.zeros((h, w)), ti.f32)
        hp, wp = h + 2 * WARP_MARGIN, w + 2 * WARP_MARGIN
        K = np.array([[0.85 * w, 0, w / 2], [0, 0.85 * w, h / 2], [0, 0, 1.0]])
        anchor = to_device(rng.uniform(0, 1, (hp, wp, 3)), ti.f32)
        anchor_depth = to_device(surface_depth(hp, wp), ti.f32)
        anchor_trans = to_device(np.zeros((hp, wp)), ti.f32)
        warped, grad_anchor = to_device(np.zeros((h, w, 3)), ti.f32), to_device(np.zeros((hp, wp, 3)), ti.f32)
        z = to_device(np.zeros((WARP_VIEWS, h, w)), ti.f32)
        views = warp_views(w)
        warp.accumulate(anchor, anchor_depth, anchor_trans, views, K, WARP_MARGIN, 2.0, 1 / WARP_VIEWS, warped, z)
        calls = {"l1_and_clipped_mse": lambda: losses.l1_and_clipped_mse(p, t, g, weight=0.8),
                 "dssim": lambda: losses.dssim(p, t, g, weight=0.2),
                 "masked_depth_l1": lambda: losses.masked_depth_l1(dp, dt, dg, weight=0.1),
                 "stage2_depth_terms": lambda: losses.normalised_depth_l1_and_coverage(dp, trans, dt, dg, grad_alpha,
                                                                                       0.5, 1.0, 0.3),
                 "warp_forward": lambda: warp.accumulate(anchor, anchor_depth, anchor_trans, views, K, WARP_MARGIN,
                                                         2.0, 1 / WARP_VIEWS, warped, z, first=True),
                 "warp_backward": lambda: warp.backward(t, anchor, z, views, K, WARP_MARGIN, 1 / WARP_VIEWS,
                                                        grad_anchor)}
        row = {}
        # a baseline root from before stage 2's depth terms moved onto the device lacks that kernel
        if not hasattr(losses, "normalised_depth_l1_and_coverage"):
            del calls["stage2_depth_terms"]
        for name in calls:
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--arch", default="cpu")
    parser.add_argument("--size", nargs="+", default=["256x192", "320x240", "640x480"])
    parser.add_argument("--repeats", type=int, default=60)
    add_arguments(parser)
    args = parser.parse_args()
    if args.json:
        print(json.dumps(time_kernels(args.arch, [parse_size(s) for s in args.size], args.repeats)))
        return
    rounds = alternate(__file__, ["--arch", args.arch, "--repeats", str(args.repeats), "--size", *args.size],
                       args.baseline, args.rounds)
    print(run_line(args.arch) + "; median ms per call (median over rounds)")
    header = "| size | kernel | this tree |" + (" baseline | ratio |" if args.baseline else "")
    print(header)
    print("|" + "---|" * (header.count("|") - 1))
    for size in args.size:
        for kernel in KERNELS:
            ours = statistics.median(r[size][kernel] for r in rounds["this tree"])
            cells = f"| {size} | {kernel} | {ours:.2f} |"
            if args.baseline and kernel not in rounds["baseline"][0][size]:
                cells += " - | - |"
            elif args.baseline:
                base = statistics.median(r[size][kernel] for r in rounds["baseline"])
                cells += f" {base:.2f} | {ours / base:.2f} |"
            print(cells)


if __name__ == "__main__":
    main()
