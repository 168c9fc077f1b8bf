"""The CPU path's blending work on a trained scene: Gaussian-pixel evaluations of one render's forward and backward
(``kernels/rasterize.py``'s loops, counted from the render's own tile lists), and the CPU time that work is worth.

    python bench/cpu_work.py RUN_DIR [--frames 4] [--margin 14] [--flops-fwd 40] [--flops-bwd 90] [--gflops 4.9]

RUN_DIR is a finished ``taichi-gs reconstruct`` folder (deblur/splats.ply, the final trajectory); its frames are
rendered at the input size from their final poses, with ``--margin`` pixels more on every side (stage 3's padded
anchor renders: 14 px in the fast preset at the sample's size). Counts per render:
- entries: tile slots (a Gaussian in a tile's depth-sorted list);
- forward visits: pixels inside each entry's row spans (``row_span``), every entry of every tile (an upper bound:
  a tile whose pixels all saturate stops early);
- backward visits: the same spans over each tile's replayed entries (up to its largest last contributor), and
  "backward evaluations" those the replay evaluates (entry index <= the pixel's last contributor), and "backward
  evaluations inside" those of pixels inside the unpadded image (a margin pixel has gradients only where a warped
  view samples it).
The time estimate is evaluations x flops per evaluation / (cores x sustained flop rate per core): a model, not a
measurement; the flop counts and the rate are the arguments (their defaults and why: ``--help``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from kernel_tasks import run_scene

from taichi_gs.kernels.tiles import TILE


def spans(entries: np.ndarray, tile_of: np.ndarray, tiles_x: int, width: int, height: int) -> tuple[np.ndarray, ...]:
    """(entry index, row v, lo, hi) of every row of every entry's box inside its tile (``rasterize.row_span``,
    in float64; rows with no pixels have lo > hi)."""
    from taichi_gs.kernels.project import (
        P_CONIC_A,
        P_CONIC_B,
        P_CONIC_C,
        P_CUTOFF,
        P_MEAN_X,
        P_MEAN_Y,
    )
    from taichi_gs.kernels.rasterize import E_BOX

    e = entries.astype(np.float64)
    tx0 = (tile_of % tiles_x) * TILE
    ty0 = (tile_of // tiles_x) * TILE
    u0 = np.maximum(e[:, E_BOX].astype(np.int64), tx0)
    v0 = np.maximum(e[:, E_BOX + 1].astype(np.int64), ty0)
    u1 = np.minimum(e[:, E_BOX + 2].astype(np.int64), np.minimum(tx0 + TILE, width) - 1)
    v1 = np.minimum(e[:, E_BOX + 3].astype(np.int64), np.minimum(ty0 + TILE, height) - 1)
    rows = np.maximum(v1 - v0 + 1, 0)
    idx = np.repeat(np.arange(len(e)), rows)
    v = v0[idx] + (np.arange(len(idx)) - np.repeat(np.cumsum(rows) - rows, rows))
    a, b, c = e[idx, P_CONIC_A], e[idx, P_CONIC_B], e[idx, P_CONIC_C]
    dy = e[idx, P_MEAN_Y] - (v + 0.5)
    disc = b * b * dy * dy - a * (c * dy * dy + 2.0 * e[idx, P_CUTOFF])
    root = np.sqrt(np.maximum(disc, 0.0))
    centre = e[idx, P_MEAN_X] - 0.5 + b * dy / a
    lo = np.maximum(np.ceil(centre - root / a - 1e-3), u0[idx])
    hi = np.minimum(np.floor(centre + root / a + 1e-3), u1[idx])
    empty = (disc < 0) | (lo > hi)
    lo = np.where(empty, 1, lo).astype(np.int64)
    hi = np.where(empty, 0, hi).astype(np.int64)
    return idx, v, lo, hi


def count_render(view, width: int, height: int, margin: int = 0) -> dict:
    """Counts of one CPU render (see the module docstring)."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    n_tiles = tiles_x * tiles_y
    start = view.tile_start.to_numpy()[: n_tiles + 1].astype(np.int64)
    n_entries = int(start[-1])
    entries = view.entries.to_numpy()[:n_entries]
    tile_of = np.repeat(np.arange(n_tiles), np.diff(start))
    local = np.arange(n_entries) - start[tile_of]
    last = view.last.to_numpy().astype(np.int64)
    trans = view.transmittance.to_numpy()
    idx, v, lo, hi = spans(entries, tile_of, tiles_x, width, height)
    length = hi - lo + 1
    max_last = np.full(n_tiles, -1)
    np.maximum.at(max_last, (np.arange(height)[:, None] // TILE * tiles_x + np.arange(width)[None, :] // TILE).ravel(),
                  last.ravel())
    replayed = local[idx] <= max_last[tile_of[idx]]
    # per pixel visit: expand the spans (a few million ints)
    pix_entry = np.repeat(idx, length)
    pix_v = np.repeat(v, length)
    pix_u = np.repeat(lo, length) + (np.arange(length.sum()) - np.repeat(np.cumsum(length) - length, length))
    evaluated = local[pix_entry] <= last[pix_v, pix_u]
    inside = (pix_v >= margin) & (pix_v < height - margin) & (pix_u >= margin) & (pix_u < width - margin)
    return {
        "entries": n_entries, "tiles": n_tiles, "pixels": width * height,
        "rows": len(idx), "forward_visits": int(length.sum()),
        "backward_visits": int(length[replayed].sum()), "backward_evaluations": int(evaluated.sum()),
        "backward_evaluations_inside": int((evaluated & inside).sum()),
        "saturated_pixels": int((trans < 1e-2).sum()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_dir", type=Path)
    parser.add_argument("--frames", type=int, default=4, help="frames rendered, spread over the sequence")
    parser.add_argument("--flops-fwd", type=float, default=40.0,
                        help="flops per forward evaluation: offset, quadratic form (~9), exp (~15), alpha, "
                             "transmittance, colour and depth sums (~10), tests (~5)")
    parser.add_argument("--flops-bwd", type=float, default=90.0,
                        help="flops per backward evaluation: the forward's ~25 to re-derive alpha, a division, "
                             "the running sums (~15), 10 gradient accumulations (~35), tests (~5)")
    parser.add_argument("--gflops", type=float, default=4.9,
                        help="sustained scalar Gflop/s per core (2 per cycle at 2.45 GHz: scalar code, FMA "
                             "counted as 2; AVX2 would be 8x that)")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--margin", type=int, default=0, help="pixels added on every side (padded anchor renders)")
    args = parser.parse_args()

    from taichi_gs.kernels import runtime
    from taichi_gs.render import Camera, DeviceGaussians, Rasterizer

    runtime.init("cpu")
    params, K, (width, height), poses = run_scene(args.run_dir)
    gaussians = DeviceGaussians.from_numpy(*params)
    rasterizer = Rasterizer(gaussians.dtype)
    frames = [int(i) for i in np.linspace(0, len(poses) - 1, args.frames).round()]
    K = K.copy()
    K[:2, 2] += args.margin
    width, height = width + 2 * args.margin, height + 2 * args.margin
    counts = []
    for i in frames:
        view = rasterizer.forward(gaussians, Camera(K, poses[i], width, height))
        counts.append(count_render(view, width, height, args.margin))
    mean = {k: float(np.mean([c[k] for c in counts])) for k in counts[0]}
    fwd_ms = mean["forward_visits"] * args.flops_fwd / (args.cores * args.gflops * 1e9) * 1e3
    bwd_ms = mean["backward_evaluations"] * args.flops_bwd / (args.cores * args.gflops * 1e9) * 1e3
    print(f"# {args.run_dir}: {len(params[0])} Gaussians, frames {frames} at {width}x{height} (margin "
          f"{args.margin}); mean per render")
    print("| count | per render |\n|---|---:|")
    for k, value in mean.items():
        print(f"| {k.replace('_', ' ')} | {value:,.0f} |")
    print(f"\nmodel: forward {mean['forward_visits'] / 1e6:.2f} M visits x {args.flops_fwd:.0f} flops, backward "
          f"{mean['backward_evaluations'] / 1e6:.2f} M evaluations x {args.flops_bwd:.0f} flops, at "
          f"{args.gflops} Gflop/s x {args.cores} cores: forward blend {fwd_ms:.1f} ms, backward replay "
          f"{bwd_ms:.1f} ms wall")


if __name__ == "__main__":
    main()
