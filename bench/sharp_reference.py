"""Stage 3 scored against sharp frames of the same real recording (issue 16).

A real capture has no sharp ground truth, but a recording that slows down somewhere has sharp frames of the scene
it also shot blurred. This benchmark trains stage 3 on a fast, blurred stretch of a recording and holds out sharp
frames from elsewhere in it that look at the same part of the scene, so that a render is scored against a
photograph with little motion blur rather than against another blurred frame:

    python bench/sharp_reference.py --recording /tmp/fr1_rpy/data --camera fr1 --scale 0.5 \\
        --stretch 400:40 --references 712:10 --out DIR [--arm "NAME=DEBLUR ARGS" ...]

1. ``taichi-gs import`` reads the stretch and the references (``first:count`` of the recording's frames) into
   DIR/stretch and DIR/references; both need reference poses (groundtruth).
2. DIR/merged holds both, the references at positions 1, 1 + h, 1 + 2h, ... (``--holdout h`` = count of the
   stretch / count of the references + 1), the test views of ``taichi-gs deblur --holdout h``.
3. Stage 1 runs on the stretch alone. Each reference is placed relative to the stretch frame whose reference pose
   is closest in rotation: the reference poses' relative transform, refined by stage 1's point-to-plane ICP on the
   two depth maps (depth carries no motion blur; a fast frame's reference pose may lag its image).
4. ``taichi-gs pose`` on the merged sequence makes a run folder (DIR/merged_run), whose ``taichi-gs refine --poses
   --points`` starts from the poses and the cloud of step 3; each arm copies it and runs ``taichi-gs deblur
   --holdout h ARGS``.

Prints per arm, as means over the references: the sharp render against the reference (PSNR / SSIM), the same on the
pixels where the floor has a value, the floor (the two stretch frames nearest in view, warped into the reference with
its depth and stage 3's poses, the better of the two), and on the floor's pixels the gradient-energy ratio of the
render over the reference (1.0: as sharp as the reference) and of the floor over the reference (the blurred
input's). Writes DIR/ARM/sharp_reference.json and an image grid, DIR/ARM/sharp_reference.png, per arm. The
recording is read, never written.
"""

from __future__ import annotations

import argparse
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from taichi_gs.evaluate import psnr, rotation_angle_deg, ssim
from taichi_gs.icp import align, depth_cloud
from taichi_gs.io.jsonout import write_json
from taichi_gs.io.load import load_sequence
from taichi_gs.io.sequence import Sequence, read_color
from taichi_gs.io.trajectory import read_tum, write_tum
from taichi_gs.noreference import gradient_energy, masked_psnr, masked_ssim, warp_to_view
from taichi_gs.plots import image_grid
from taichi_gs.stages.pose_config import PoseConfig
from taichi_gs.stages.pose_pair import icp_levels

FLOOR_NEIGHBOURS = 2  # stretch frames nearest in view that the floor warps into each reference
GRID_VIEWS = 4  # references shown in each arm's image grid


def taichi_gs(*args: str) -> None:
    """Run the CLI of this code tree (``python -m taichi_gs.cli``, as the other bench scripts do); stop with its
    output on failure."""
    command = [sys.executable, "-m", "taichi_gs.cli", *args]
    done = subprocess.run(command, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"{shlex.join(command)} failed ({done.returncode}):\n"
                         f"{done.stdout[-2000:]}{done.stderr[-2000:]}")


def span(text: str) -> tuple[int, int]:
    """"400:40" -> (400, 40)."""
    first, count = (int(x) for x in text.split(":"))
    return first, count


def held_out_positions(n_frames: int, every: int) -> list[int]:
    """The test views of ``taichi-gs deblur --holdout every`` on ``n_frames`` frames."""
    return list(range(1, n_frames, every))


def merge(stretch: Sequence, references: Sequence, out: Path, every: int) -> list[int]:
    """One taichi-gs sequence of both (imported, own-layout) sequences, the references at
    :func:`held_out_positions`; frames are renamed by position and stamped 1/30 s apart (their order is the merged
    one), each with its own reference pose. Returns the test positions."""
    n = len(stretch) + len(references)
    test = held_out_positions(n, every)
    if len(test) != len(references):
        raise SystemExit(f"{len(references)} references do not fill the {len(test)} test views of "
                         f"--holdout {every} on {n} frames")
    (out / "rgb").mkdir(parents=True)
    (out / "depth").mkdir()
    if (stretch.root / "sourced.png").is_file():
        shutil.copy(stretch.root / "sourced.png", out)
    # the stretch's intrinsics without a rolling shutter's readout: the merged frames' made-up stamps put frames
    # from another part of the recording between stretch frames, so neighbours do not give a frame's velocity
    (out / "intrinsics.json").write_text(stretch.intrinsics.to_json())
    held = set(test)
    order = iter(range(len(stretch))), iter(range(len(references)))
    stamps = stretch.timestamps[0] + np.arange(n) / 30.0
    listing, poses = ["# timestamp rgb depth"], []
    for position, stamp in enumerate(stamps):
        source, i = (references, next(order[1])) if position in held else (stretch, next(order[0]))
        shutil.copy(source.rgb_paths[i], out / "rgb" / f"{position:04d}.png")
        shutil.copy(source.depth_paths[i], out / "depth" / f"{position:04d}.png")
        listing.append(f"{stamp:.6f} rgb/{position:04d}.png depth/{position:04d}.png")
        poses.append(source.gt_poses[i])
    (out / "frames.txt").write_text("\n".join(listing) + "\n")
    write_tum(out / "groundtruth.txt", stamps, np.array(poses))
    return test


def rotation_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (deg) of the rotation between two camera-to-world poses."""
    return rotation_angle_deg(a[:3, :3].T @ b[:3, :3])


def place_references(stretch: Sequence, references: Sequence,
                     stretch_poses: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Camera-to-world poses of the references in stage 1's frame (see the module's step 3), and one line per
    reference saying where it was placed from."""
    config, K = PoseConfig(), stretch.intrinsics.K()

    def cloud(sequence: Sequence, i: int):
        depth = sequence.depth(i)
        return depth_cloud(depth, K, config.reliable_depth(depth))

    placed, lines = [], []
    for r in range(len(references)):
        j = min(range(len(stretch)), key=lambda j: rotation_deg(stretch.gt_poses[j], references.gt_poses[r]))
        start = np.linalg.inv(stretch.gt_poses[j]) @ references.gt_poses[r]  # reference camera -> camera j
        result = align(icp_levels(cloud(references, r), cloud(stretch, j), config), start)
        placed.append(stretch_poses[j] @ result.transform)
        lines.append(f"- reference {references.names[r]}: from stretch frame {stretch.names[j]} "
                     f"({rotation_deg(stretch.gt_poses[j], references.gt_poses[r]):.1f} deg apart); ICP fitness "
                     f"{result.fitness:.2f}, moved the reference poses' estimate by "
                     f"{rotation_deg(start, result.transform):.2f} deg, "
                     f"{1000 * np.linalg.norm(start[:3, 3] - result.transform[:3, 3]):.1f} mm")
    return np.array(placed), lines


def score(run: Path, merged: Sequence, test: list[int]) -> dict[str, float]:
    """The module's figures for one arm's run, means over the references; writes RUN/sharp_reference.png
    (reference | sharp render | floor, for the first ``GRID_VIEWS`` references)."""
    _, poses = read_tum(run / "deblur" / "trajectory.txt")
    held = set(test)
    stretch = [i for i in range(len(merged)) if i not in held]
    K = merged.intrinsics.K()
    figures: dict[str, list[float]] = {}
    grid_rows = []
    for i in test:
        reference = merged.color(i)
        render = read_color(run / "deblur" / "renders" / "sharp" / f"{merged.names[i]}.png")
        nearest = sorted(stretch, key=lambda j: rotation_deg(poses[j], poses[i]))[:FLOOR_NEIGHBOURS]
        floor = max((warp_to_view(merged.color(j), poses[j], merged.depth(i), poses[i], K) for j in nearest),
                    key=lambda warp: masked_psnr(warp[0], reference, warp[1]) if warp[1].any() else -np.inf)
        warped, mask = floor
        reference_energy = max(gradient_energy(reference, mask=mask), 1e-12)
        values = {"render_psnr_db": psnr(render, reference), "render_ssim": ssim(render, reference),
                  "render_on_floor_pixels_psnr_db": masked_psnr(render, reference, mask),
                  "render_on_floor_pixels_ssim": masked_ssim(render, reference, mask),
                  "floor_psnr_db": masked_psnr(warped, reference, mask),
                  "floor_ssim": masked_ssim(warped, reference, mask),
                  "floor_coverage": float(mask.mean()),
                  "gradient_energy_render_over_reference": gradient_energy(render, mask=mask) / reference_energy,
                  "gradient_energy_floor_over_reference": gradient_energy(warped, mask=mask) / reference_energy}
        for key, value in values.items():
            figures.setdefault(key, []).append(float(value))
        if len(grid_rows) < GRID_VIEWS:
            grid_rows.append([reference, render, np.where(mask[..., None], warped, 0.0)])
    image_grid(run / "sharp_reference.png", grid_rows,
               ["sharp reference", "sharp render", "floor: stretch frame warped"],
               [merged.names[i] for i in test[:GRID_VIEWS]])
    return {key: float(np.nanmean(values)) for key, values in figures.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--recording", type=Path, required=True, help="a recording taichi-gs import reads, with poses")
    parser.add_argument("--camera", default=None, help="taichi-gs import --camera (e.g. fr1)")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--stretch", type=span, required=True, help="first:count of the fast stretch")
    parser.add_argument("--references", type=span, required=True, help="first:count of the sharp frames")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--arm", action="append", default=None,
                        help='"NAME=extra taichi-gs deblur arguments" (default: "default=" and "no blur model=--k 1")')
    args = parser.parse_args()
    arms = dict(a.split("=", 1) for a in (args.arm or ["default=", "no blur model=--k 1"]))
    camera = ["--camera", args.camera] if args.camera else []
    for name, (first, count) in (("stretch", args.stretch), ("references", args.references)):
        if not (args.out / name / "frames.txt").is_file():
            taichi_gs("import", str(args.recording), *camera, "--first", str(first), "--count", str(count),
                      "--scale", f"{args.scale:g}", "--out", str(args.out / name))
    stretch, references = load_sequence(args.out / "stretch"), load_sequence(args.out / "references")
    every = len(stretch) // len(references) + 1
    merged_dir = args.out / "merged"
    test = (merge(stretch, references, merged_dir, every) if not merged_dir.is_dir()
            else held_out_positions(len(stretch) + len(references), every))
    merged = load_sequence(merged_dir)
    stage1 = args.out / "stage1"
    if not (stage1 / "pose" / "trajectory.txt").is_file():
        taichi_gs("pose", str(args.out / "stretch"), "--out", str(stage1))
    _, stretch_poses = read_tum(stage1 / "pose" / "trajectory.txt")
    placed, lines = place_references(stretch, references, stretch_poses)
    print(*lines, sep="\n")
    poses, held = np.empty((len(merged), 4, 4)), set(test)
    poses[test] = placed
    poses[[i for i in range(len(merged)) if i not in held]] = stretch_poses
    trajectory = args.out / "merged_trajectory.txt"
    write_tum(trajectory, merged.timestamps, poses, header="stage 1 on the stretch; references placed by depth ICP")
    print("\n| arm | render vs reference PSNR / SSIM | on the floor's pixels: render / floor PSNR (SSIM) | floor coverage "
          "| gradient energy on the floor's pixels: render / reference (floor / reference) |")
    print("|---|---|---|---|---|")
    base = args.out / "merged_run"
    if not (base / "refine" / "done.json").is_file():
        taichi_gs("pose", str(merged_dir), "--out", str(base))
        taichi_gs("refine", str(base), "--poses", str(trajectory), "--points", str(stage1 / "pose" / "points.ply"))
    for name, extra in arms.items():
        run = args.out / "".join(c if c.isalnum() else "_" for c in name)
        if not (run / "deblur" / "done.json").is_file():
            shutil.rmtree(run, ignore_errors=True)
            shutil.copytree(base, run, ignore=shutil.ignore_patterns("deblur"))
            taichi_gs("deblur", str(run), "--holdout", str(every), *shlex.split(extra))
        f = score(run, merged, test)
        write_json(run / "sharp_reference.json", f)  # strict JSON: a figure without pixels becomes null
        print(f"| {name} | {f['render_psnr_db']:.2f} / {f['render_ssim']:.3f} | {f['render_on_floor_pixels_psnr_db']:.2f} "
              f"/ {f['floor_psnr_db']:.2f} ({f['render_on_floor_pixels_ssim']:.3f} / {f['floor_ssim']:.3f}) | "
              f"{f['floor_coverage']:.2f} | {f['gradient_energy_render_over_reference']:.2f} "
              f"({f['gradient_energy_floor_over_reference']:.2f}) |", flush=True)


if __name__ == "__main__":
    main()
