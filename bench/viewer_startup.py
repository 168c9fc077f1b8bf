"""How long `taichi-gs view` takes to open a long run, and a headless Chromium to receive it.

    python bench/viewer_startup.py [--frames 300] [--gaussians 100000] [--size 320x240] [--work DIR] [--chromium PATH]

Makes a synthetic sequence (``taichi-gs synth``'s, ground-truth poses; kept in ``--work`` for reruns) and a run
folder whose stage 3 holds its poses, its exposures and random Gaussians, then times: reading the run
(``open_run``), building the viewer (the input thumbnails, one frustum node per camera, the exposures in one node,
the splats), and, with Chromium, the time until the page shows the Gaussian count. Needs the viewer extra (viser)
and, for the page, Playwright and a Chromium.
"""

import argparse
import shutil
import time
from pathlib import Path

import numpy as np

from taichi_gs.io.ply import write_splats
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import write_tum
from taichi_gs.pipeline import write_run_info
from taichi_gs.splats import splats_from_points
from taichi_gs.synth import SynthConfig, generate

CHROMIUM_FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage"]


def make_run(work: Path, frames: int, gaussians: int, width: int, height: int) -> Path:
    """A run folder with a finished stage 3 made from a synthetic sequence's ground truth (made once per size)."""
    run = work / f"run_{frames}_{gaussians}_{width}x{height}"
    if (run / "deblur" / "splats.ply").is_file():
        return run
    seq_dir = work / f"seq_{frames}_{width}x{height}"
    if not (seq_dir / "frames.txt").is_file():
        generate(SynthConfig(width=width, height=height, frames=frames, seed=4), seq_dir)
    sequence = load_sequence(seq_dir)
    write_run_info(run, sequence)
    write_tum(run / "deblur" / "trajectory.txt", sequence.timestamps, sequence.gt_poses)
    shutil.copyfile(seq_dir / "exposure.txt", run / "deblur" / "exposure.txt")
    rng = np.random.default_rng(0)
    centre = sequence.gt_poses[:, :3, 3].mean(axis=0)
    write_splats(run / "deblur" / "splats.ply",
                 splats_from_points(centre + rng.normal(size=(gaussians, 3)), rng.uniform(size=(gaussians, 3)), 0.02))
    return run


def time_page(url: str, gaussians: int, chromium: str) -> float:
    """Seconds from opening ``url`` in headless Chromium until the page shows the Gaussian count."""
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_FLAGS)
        try:
            page = browser.new_page(viewport={"width": 800, "height": 500})
            start = time.perf_counter()
            page.goto(url)
            page.get_by_text(f"Gaussians: {gaussians}").wait_for(timeout=300_000)
            return time.perf_counter() - start
        finally:
            browser.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=300)
    parser.add_argument("--gaussians", type=int, default=100_000)
    parser.add_argument("--size", default="320x240", help="frame width x height")
    parser.add_argument("--work", type=Path, default=Path("/tmp/taichi_gs_viewer_bench"))
    parser.add_argument("--chromium", default=shutil.which("chromium"), help="browser to time the page with "
                        "(default: chromium on PATH; none: no page timing)")
    args = parser.parse_args()
    from taichi_gs.viewer.app import RunViewer
    from taichi_gs.viewer.run_scene import open_run

    width, height = (int(v) for v in args.size.lower().split("x"))
    run = make_run(args.work, args.frames, args.gaussians, width, height)
    start = time.perf_counter()
    scene = open_run(run)
    opened = time.perf_counter()
    viewer = RunViewer(scene, "127.0.0.1", 0)
    built = time.perf_counter()
    print(f"{args.frames} frames at {width}x{height}, {args.gaussians} Gaussians: open_run {opened - start:.2f} s, "
          f"viewer built {built - opened:.2f} s ({len(viewer._nodes)} scene nodes)")
    try:
        if args.chromium:
            print(f"page shows the Gaussian count after {time_page(viewer.url, args.gaussians, args.chromium):.2f} s")
    finally:
        viewer.stop()


if __name__ == "__main__":
    main()
