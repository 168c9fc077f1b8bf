"""What stage 3 writes to OUT/deblur/: the result, splats, trajectories, the split, colour transforms,
full-resolution renders and a grid, the loss history; and the warning when k is too small for the blur."""

from __future__ import annotations

import math
import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ... import profiling
from ...geometry import virtual_pose
from ...io import jsonout
from ...io.atomic import write_text
from ...io.images import encode_depth, to_uint8, write_png
from ...io.ply import write_splats
from ...io.sequence import Sequence
from ...io.trajectory import format_tum, write_tum
from ...photometric import apply_affine
from ...plots import image_grid, line_plot
from ...splats import Splats
from .config import DeblurConfig
from .exposures import Exposures, exposure_px
from .frames import _Frames, _Shutter
from .gauge import FrameShift
from .model import BlurScene


@dataclass
class DeblurResult:
    mid_poses: np.ndarray  # (N, 4, 4) mid-exposure camera-to-world
    exposure: np.ndarray  # (N, 2, 4, 4) start and end
    train: list[int]
    test: list[int]
    loss_history: list[dict[str, float]]
    gaussians: int
    seconds_per_iteration: float
    warnings: list[str] = field(default_factory=list)
    readout_ms: float = 0.0  # the rolling shutter's readout modelled (0: a global shutter)

    def summary(self) -> str:
        """One line for the console; ``warnings`` are reported separately, one per line."""
        shutter = f", rolling shutter {self.readout_ms:g} ms" if self.readout_ms > 0 else ""
        return (f"{self.gaussians} Gaussians, {len(self.train)} train / {len(self.test)} test views, "
                f"{self.seconds_per_iteration * 1000:.0f} ms/iteration{shutter}")


def _step_warnings(offsets: np.ndarray, train: list[int], frames: _Frames, config: DeblurConfig) -> list[str]:
    """A warning if adjacent virtual views move more than ``max_step_px`` (k is then too small)."""
    if config.k < 2:
        return []
    steps = [exposure_px(*offsets[i], frames.K[0, 0], frames.median_depth[i]) / (config.k - 1) for i in train]
    worst = int(np.argmax(steps))
    if steps[worst] <= config.max_step_px:
        return []
    needed = math.ceil(steps[worst] * (config.k - 1) / config.max_step_px) + 1
    return [(f"adjacent virtual views move up to {steps[worst]:.2f} px (frame {train[worst]}) at the training "
             f"resolution, more than {config.max_step_px:g} px: k = {config.k} is likely too small for this blur "
             f"(--k {needed} keeps the steps under {config.max_step_px:g} px)")]


@profiling.timed("outputs (renders, PLY, plots: I/O)")
def _write_outputs(stage_dir: Path, sequence: Sequence, splats: Splats, exposures: Exposures, result: DeblurResult,
                   config: DeblurConfig, sharpness: list[float], shift: FrameShift | None, shutter: _Shutter) -> None:
    colours = exposures.trained_colours()
    write_splats(stage_dir / "splats.ply", splats)
    if shift is not None:
        write_text(stage_dir / "frame.json", jsonout.dumps(shift.as_dict(), indent=2) + "\n")
    else:
        (stage_dir / "frame.json").unlink(missing_ok=True)
    write_tum(stage_dir / "trajectory.txt", sequence.timestamps, result.mid_poses,
              header="taichi-gs stage 3 (deblur), mid-exposure camera-to-world")
    write_text(stage_dir / "exposure.txt", _format_exposure(sequence.timestamps, result.exposure))
    write_text(stage_dir / "split.json", jsonout.dumps({"train": result.train, "test": result.test,
                                                     "holdout_every": config.holdout_every, "holdout": config.holdout,
                                                     "laplacian_variance": sharpness}, indent=2) + "\n")
    if colours is not None:
        write_text(stage_dir / "colour_affine.json", jsonout.dumps(
            {"rows": "out = M[:, :3] @ rgb + M[:, 3]", "frames": {n: colours[i].round(6).tolist()
                                                                  for i, n in enumerate(sequence.names)}}) + "\n")
    _write_renders(stage_dir, sequence, splats, exposures.poses, exposures.offsets, exposures.bends, config,
                   result.test, colours, shutter)
    history = result.loss_history
    if history:
        it = np.array([h["iteration"] for h in history], dtype=float)
        line_plot(stage_dir / "loss.png", {"loss": (it, np.array([h["loss"] for h in history]))},
                  "stage 3: deblurring loss", "iteration", "loss", log_y=True)
    write_text(stage_dir / "history.json", jsonout.dumps(history) + "\n")


def _format_exposure(timestamps: np.ndarray, exposure: np.ndarray) -> str:
    """``timestamp`` then start and end poses as ``tx ty tz qx qy qz qw`` each, one frame a line."""
    starts = format_tum(timestamps, exposure[:, 0]).splitlines()
    ends = format_tum(timestamps, exposure[:, 1]).splitlines()
    lines = ["# timestamp start(tx ty tz qx qy qz qw) end(tx ty tz qx qy qz qw), camera-to-world"]
    lines += [f"{s} {e.split(maxsplit=1)[1]}" for s, e in zip(starts, ends)]
    return "\n".join(lines) + "\n"


def _write_renders(stage_dir: Path, sequence: Sequence, splats: Splats, poses: np.ndarray, offsets: np.ndarray,
                   bends: np.ndarray, config: DeblurConfig, test: list[int], colours: np.ndarray | None,
                   shutter: _Shutter) -> None:
    """Full-resolution sharp mid-exposure, re-blurred and depth renders of every frame (exposures bowed by their
    ``bends``), and a grid;
    with per-frame ``colours`` the colour renders are in each frame's own colour (its transform applied).
    The sharp renders are global-shutter; the re-blurred ones read their rows as ``shutter`` does, and with a
    rolling shutter ``renders/as_read/`` holds the sharp render read so (each row at its mid-exposure pose)."""
    first = sequence.color(0)
    K = sequence.K()
    shutil.rmtree(stage_dir / "renders" / "as_read", ignore_errors=True)  # an earlier run's, with another readout
    skew = shutter.skew_px(K[0, 0])
    full = BlurScene(splats, K, first.shape[1], first.shape[0], warp_margin=math.ceil(skew) + 2 if skew > 0 else 0)
    scale = sequence.intrinsics.depth_scale
    rows, names = [], []
    has_truth = sequence.sharp_paths is not None
    grid_frames = set(_grid_frames(len(sequence), test, config.grid_frames))
    for i, name in enumerate(sequence.names):
        sharp, depth = full.render(virtual_pose(poses[i], *offsets[i], 0.5, bends[i]))
        reblurred = full.render_blurred(poses[i], offsets[i, 0], offsets[i, 1], config.k, shutter.motions[i],
                                        shutter.median_depth[i], bends[i])
        as_read = None
        if shutter.motions[i].any():  # the sharp render as the rolling shutter reads it: rows at their own poses
            as_read = full.render_blurred(poses[i], offsets[i, 0], offsets[i, 1], 1, shutter.motions[i],
                                          shutter.median_depth[i], bends[i])
        if colours is not None:
            sharp, reblurred = apply_affine(sharp, colours[i]), apply_affine(reblurred, colours[i])
            as_read = None if as_read is None else apply_affine(as_read, colours[i])
        write_png(stage_dir / "renders" / "sharp" / f"{name}.png", to_uint8(sharp))
        write_png(stage_dir / "renders" / "reblurred" / f"{name}.png", to_uint8(reblurred))
        if as_read is not None:
            write_png(stage_dir / "renders" / "as_read" / f"{name}.png", to_uint8(as_read))
        write_png(stage_dir / "renders" / "depth" / f"{name}.png", encode_depth(depth, scale))
        if i in grid_frames:
            rows.append([sequence.color(i), sharp] + ([sequence.sharp(i)] if has_truth else []))
            names.append(name)
    titles = ["blurred input", "deblurred (ours)"] + (["sharp ground truth"] if has_truth else [])
    image_grid(stage_dir / "grid.png", rows, titles, names, min_width=0)


def _grid_frames(n_frames: int, test: list[int], count: int) -> list[int]:
    """A few frames spread over the sequence, test views first when there are any."""
    pool = test or list(range(n_frames))
    picks = np.linspace(0, len(pool) - 1, min(count, len(pool))).round().astype(int)
    return [pool[p] for p in sorted(set(picks))]
