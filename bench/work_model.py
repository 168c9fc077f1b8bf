"""Work model of the GPU rasterizer's kernels (no GPU needed): threads launched, serial work per
thread, block barriers and bytes moved per kernel for one forward + backward.

    python bench/work_model.py [--n 500000] [--size 640x480] [--markdown]

The scene is bench/raster.py's (n Gaussians filling the frustum, SH degree 0). Its binning, tile
lists and per-pixel last contributors come from one CPU forward (the same projection, tiles and
depth order as the GPU path: tests/test_gpu_backend.py checks the slot counts and images agree); the
rest is counted from the kernels' loop structure in ``taichi_gs/kernels/raster_gpu.py`` and
``scan.py``. These are counts, not times: GPU times are unmeasured here (no GPU was available).

Bytes are DRAM-side reads + writes of f32 / i32 (4 B), ignoring caches; "atomics" are global
float atomic adds. The forward blend's early exit (a block stops once all its pixels saturate)
is bounded: "upper" visits every record of the tile, "estimate" stops after the batch holding
the last contributor of the tile when every pixel has transmittance below 1e-2 (a pixel that
stopped early must have: T * (1 - 0.99) < 1e-4). The backward's replay length (the tile's
largest last index + 1) is exact.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from taichi_gs.kernels import runtime  # noqa: E402

F = 4  # bytes per f32 / i32
P_WIDTH = 11  # screen record (project.P_WIDTH)
N_SLOT_GRADS = 10


def tile_statistics(n: int, width: int, height: int) -> dict:
    """Binning and blending statistics of bench/raster.py's scene from one CPU forward."""
    import taichi as ti

    from raster import scene
    from taichi_gs.kernels.tiles import TILE
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer

    params, K = scene(n, width, height)
    gs = DeviceGaussians.from_numpy(*params, dtype=ti.f32)
    view = Rasterizer(ti.f32).forward(gs, Camera(K, np.eye(4), width, height))
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    n_tiles = tiles_x * tiles_y
    start = view.tile_start.to_numpy()[: n_tiles + 1].astype(np.int64)
    count = np.diff(start)
    last = view.last.to_numpy()
    trans = view.transmittance.to_numpy()
    pad = lambda a, fill: np.pad(a, ((0, tiles_y * TILE - height), (0, tiles_x * TILE - width)),  # noqa: E731
                                 constant_values=fill)
    per_tile = lambda a, fill: pad(a, fill).reshape(tiles_y, TILE, tiles_x, TILE).swapaxes(1, 2) \
        .reshape(n_tiles, TILE * TILE)  # noqa: E731
    max_last = per_tile(last, -1).max(axis=1).astype(np.int64)
    saturated = (per_tile(trans, 0.0) < 1e-2).all(axis=1)
    replay = max_last + 1  # backward: records replayed per tile (exact)
    batch = TILE * TILE
    fwd_est = np.where(saturated, np.minimum(count, -(-(max_last + 2) // batch) * batch), count)
    proj = view.proj.to_numpy()[:n]
    rect = view.rect.to_numpy()[:n]
    visible = rect[:, 0] <= rect[:, 2]
    det_conic = proj[visible, 2] * proj[visible, 4] - proj[visible, 3] ** 2
    # pixels inside each visible Gaussian's support ellipse: pi * ext^2 * sqrt(det cov2d)
    support_px = np.pi * (-2 * proj[visible, 10]) / np.sqrt(det_conic)
    return {
        "n": n, "width": width, "height": height, "n_tiles": n_tiles, "n_slots": int(view.n_slots),
        "visible": int(visible.sum()), "count": count, "replay": replay, "fwd_est": fwd_est,
        "saturated_tiles": int(saturated.sum()), "support_pairs": float(support_px.sum()),
        "tiles_per_gaussian": view.tiles_per_gaussian()[visible],
    }


def work_model(s: dict) -> list[dict]:
    """One row per kernel launch group of forward + backward (raster_gpu.GpuPipeline)."""
    n, slots, n_tiles, pixels = s["n"], s["n_slots"], s["n_tiles"], s["width"] * s["height"]
    block = 256
    rows = []

    def row(kernel, threads, serial, syncs, nbytes, atomics=0, note=""):
        rows.append({"kernel": kernel, "threads": threads, "serial": serial, "syncs": syncs,
                     "bytes": nbytes, "atomics": atomics, "note": note})

    def scan_cost(m):
        """exclusive_scan of m elements (one launch, a task per level): (tasks, threads, bytes) over the
        levels that hold more than one block."""
        tasks, threads, nbytes = 0, 0, 0
        while True:
            blocks = m // block + 1
            tasks += 1
            threads += blocks * block
            nbytes += 2 * m * F + blocks * F
            if blocks == 1:
                return tasks, threads, nbytes
            tasks += 1
            threads += m + 1
            nbytes += 2 * (m + 1) * F + (m + 1) * F / block
            m = blocks

    def radix_cost(m, bits, name):
        passes = math.ceil(bits / 8)
        chunks = max(1, -(-m // 1024))
        _, scan_threads, scan_bytes = scan_cost(256 * chunks)
        row(f"{name}: digit_histogram x{passes}", chunks * block, "4 keys", 3, passes * (m * F + 256 * chunks * F))
        row(f"{name}: scan of digit table x{passes}", scan_threads, "1 element, 8 steps", 9,
            passes * scan_bytes)
        row(f"{name}: scatter x{passes}", chunks * block, "4 keys x rank loop <= 255 compares", 13,
            passes * (m * 2 * F + m * 2 * F + 256 * chunks * F), note="rank by counting in shared memory")

    tpg = s["tiles_per_gaussian"]
    row("project_keys", n, "1 Gaussian (SH deg 0)", 0, n * (14 + P_WIDTH + 4 + 2) * F)
    radix_cost(n, 31, "depth sort")
    row("bin_slots: count tiles", n, "1 Gaussian", 0, n * (1 + 4 + 1) * F)
    _, t, b = scan_cost(n)
    row("bin_slots: exclusive scan", t, "1 element, 8 steps", 9, b)
    row("bin_slots: emit", n, f"tiles/Gaussian: mean {tpg.mean():.2f}, max {tpg.max()}", 0,
        n * 6 * F + slots * 3 * F)
    radix_cost(slots, max(1, int(n_tiles - 1).bit_length()), "tile sort")
    row("ranges_and_gather", slots, "1 slot", 0, slots * (4 + 3 + P_WIDTH + 4 + 15) * F)
    cnt, est = s["count"], s["fwd_est"]
    row("blend_forward", n_tiles * block,
        f"records/tile: upper mean {cnt.mean():.0f} max {cnt.max()}; estimate mean {est.mean():.0f} "
        f"max {est.max()}",
        "2 + 2 per batch of 256: per block mean {:.1f}, max {}".format(
            2 + 2 * np.ceil(cnt / block).mean(), 2 + 2 * int(np.ceil(cnt / block).max())),
        int(est.sum()) * P_WIDTH * F + pixels * 6 * F,
        note=f"bytes use the estimate (upper {(int(cnt.sum()) * P_WIDTH * F + pixels * 6 * F) / 1e6:.1f} MB)")
    rep = s["replay"]
    pairs = s["support_pairs"]
    row("blend_backward", n_tiles * block, f"records replayed/tile: mean {rep.mean():.0f} max {rep.max()}",
        "3 + 2 per batch of 256: per block mean {:.1f}, max {}".format(
            3 + 2 * np.ceil(rep / block).mean(), 3 + 2 * int(np.ceil(rep / block).max())),
        int(rep.sum()) * (P_WIDTH + 1) * F + pixels * 7 * F + slots * N_SLOT_GRADS * F,
        atomics=int(pairs * N_SLOT_GRADS),
        note="atomics: per pixel hit (CUDA path), upper bound = pixels inside supports x 10")
    row("gaussian_backward", n, f"slot rows summed: mean {tpg.mean():.2f}, then projection VJP", 0,
        slots * N_SLOT_GRADS * F + n * (14 + 14 + 14 + 2 + 6) * F)
    levels, t_sum = 0, 0
    m = n
    while True:
        levels += 1
        t_sum += -(-m // block) * block
        m = -(-m // block)
        if m == 1:
            break
    row(f"sum_rows x{levels} (pose)", t_sum, "1 row, 8 tree steps", 10, n * 6 * F)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=500_000)
    parser.add_argument("--size", default="640x480")
    parser.add_argument("--markdown", action="store_true")
    args = parser.parse_args()
    width, height = map(int, args.size.lower().split("x"))
    runtime.init("cpu")
    s = tile_statistics(args.n, width, height)
    rows = work_model(s)
    cnt = s["count"]
    print(f"# work model: {args.n} Gaussians (bench/raster.py scene, SH degree 0) at {width}x{height}: "
          f"{s['visible']} visible, {s['n_slots']} tile slots, {s['n_tiles']} tiles; records per tile mean "
          f"{cnt.mean():.0f}, max {cnt.max()}; tiles with every pixel saturated {s['saturated_tiles']}; "
          f"pixel-Gaussian pairs inside supports {s['support_pairs'] / 1e6:.1f} M. GPU times: unmeasured.")
    total = sum(r["bytes"] for r in rows)
    if args.markdown:
        print("\n| kernel | threads | serial work per thread | block syncs | MB moved | float atomics |")
        print("|---|---:|---|---|---:|---:|")
    for r in rows:
        if args.markdown:
            print(f"| `{r['kernel']}` | {r['threads']:,} | {r['serial']} | {r['syncs']} | "
                  f"{r['bytes'] / 1e6:.1f} | {r['atomics']:,} |")
        else:
            print(f"{r['kernel']:36s} threads {r['threads']:>10,}  serial {r['serial']}  syncs {r['syncs']}  "
                  f"MB {r['bytes'] / 1e6:.1f}  atomics {r['atomics']:,}  {r['note']}")
    print(f"\ntotal bytes moved (forward + backward): {total / 1e6:.0f} MB")
    if args.markdown:
        for r in rows:
            if r["note"]:
                print(f"- `{r['kernel']}`: {r['note']}")


if __name__ == "__main__":
    main()
