"""Run evaluation: metrics.json for a run folder, from its stage outputs and the ground truth."""

from __future__ import annotations

import json
import platform
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .errors import InputError
from .evaluate import (ROTATION_SCALE_MIN_DEG, ROTATION_SCALE_SPAN, align_trajectory, inverse_depth_rmse,
                       match_by_time, psnr, ssim, trajectory_errors)
from .io.jsonout import finite_or_null, write_json
from .io.sequence import Sequence, read_color, read_depth
from .io.trajectory import read_tum
from .noreference_report import no_reference_metrics
from .pipeline import STAGES, iter_stage_records, open_run_sequence
from .plots import colour_map, colour_scale, image_grid, line_plot, trajectory_plot

SHARP_TRUTH = "sharp images"  # metrics.json images.ground_truth when the sequence has sharp ground truth

GRID_VIEWS = 4
GRID_MIN_WIDTH = 240  # pixels per grid tile at least
IMAGE_NULL_REASONS = {
    "psnr_db": "a render equals its reference exactly (infinite PSNR)",
    "blurred_input_psnr_db": "an input equals its sharp reference exactly (infinite PSNR)",
    "inverse_depth_rmse": "no pixel where both the rendered and the input depth are valid",
}


def evaluate_run(run_dir: Path, gt: Path | None = None) -> dict[str, Any]:
    """Every figure of a run's finished stages that its sequence can score: trajectory errors against ground-truth
    poses, stage 3's images against sharp frames, the no-reference figures, time and memory per stage; what the
    sequence cannot score is named with its reason in ``not_scored``. Writes RUN_DIR/metrics.json and
    RUN_DIR/report/."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder not found", "give the --out folder of a taichi-gs run")
    sequence = open_run_sequence(run_dir, gt)
    estimates = {stage: read_tum(run_dir / stage / "trajectory.txt") for stage in STAGES
                 if (run_dir / stage / "trajectory.txt").is_file()}
    if not estimates:
        raise InputError(run_dir, "no stage output (pose/, refine/, deblur/) with a trajectory.txt", "run 'taichi-gs reconstruct' first")
    if sequence.gt_poses is None:
        trajectories: dict[str, Any] = {}
        trajectory_plot(run_dir / "report" / "trajectory_top.png",
                        {stage: est for stage, (_, est) in estimates.items()},
                        "estimated trajectories (top view; no ground truth: not aligned)")
    else:
        trajectories = scored_trajectories(run_dir, sequence, estimates)
    stages = {stage: {k: record.get(k) for k in ("seconds", "peak_rss_mb", "arch", "summary", "warnings")}
              for stage, record in iter_stage_records(run_dir)}
    images = image_metrics(run_dir, sequence)
    metrics = {
        "trajectory": trajectories,
        "images": images,
        "no_reference": no_reference_metrics(run_dir, sequence),
        "not_scored": not_scored(sequence, stage_3_ran=images is not None),
        "stages": stages,
        "arch": next((s["arch"] for s in stages.values() if s.get("arch") not in (None, "none")), "none"),
        "versions": _versions(),
        "sequence": str(sequence.root),
    }
    metrics["warnings"] = [f"{stage}: {w}" for stage, record in iter_stage_records(run_dir) for w in record.get("warnings", [])]
    metrics = finite_or_null(metrics, IMAGE_NULL_REASONS)
    write_json(run_dir / "metrics.json", metrics)
    return metrics


def scored_trajectories(run_dir: Path, sequence: Sequence,
                        estimates: dict[str, tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    """Each stage's trajectory record against the sequence's ground truth (matched by timestamp); writes
    RUN_DIR/report/trajectory_top.png and position_error.png (after alignment) where a stage aligns."""
    trajectories: dict[str, Any] = {}
    aligned: dict[str, np.ndarray] = {"ground truth": sequence.gt_poses}
    position_errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for stage, (t_est, est) in estimates.items():
        i, j = match_by_time(t_est, sequence.timestamps)
        gt = sequence.gt_poses[j]
        finite = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
        dropped = _dropped_frames(len(t_est), len(i), [sequence.names[k] for k in j[~finite]])
        trajectories[stage] = trajectory_record(est[i], gt, dropped)
        if finite.sum() >= 3:
            moved = align_trajectory(est[i][finite], gt[finite])
            aligned[stage] = moved
            position_errors[stage] = (j[finite], 1000 * np.linalg.norm(moved[:, :3, 3] - gt[finite][:, :3, 3], axis=1))
    if position_errors:
        trajectory_plot(run_dir / "report" / "trajectory_top.png", aligned, "trajectories, aligned to ground truth (top view)")
        line_plot(run_dir / "report" / "position_error.png", position_errors, "position error after alignment",
                  "frame", "error (mm)")
    return trajectories


def not_scored(sequence: Sequence, stage_3_ran: bool) -> list[dict[str, str]]:
    """The figures the run's sequence has no reference for (or that stage 3 has not made yet), each with its reason."""
    missing = []
    if sequence.gt_poses is None:
        missing.append({"what": "trajectory errors (ATE, RPE, rotation drift and scale), position-error plot",
                        "reason": "the sequence has no ground-truth poses "
                                  "(groundtruth.txt or its layout's pose files)"})
    if not stage_3_ran:
        missing.append({"what": "images and no-reference figures", "reason": "stage 3 (deblur) has not run"})
        return missing
    if sequence.sharp_paths is None:
        missing.append({"what": "images: PSNR/SSIM of the renders and of the blurred input against sharp frames",
                        "reason": "the sequence has no sharp/ folder"})
    if sequence.exposure_poses is not None and sequence.gt_poses is None:
        missing.append({"what": "no_reference true_exposure_px (the blur of the sequence's exposure.txt)",
                        "reason": "its exposures are seen from the ground-truth poses, which the sequence lacks"})
    return missing


def trajectory_record(est: np.ndarray, ref: np.ndarray, dropped: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """ATE/RPE of matched poses as a JSON-ready dict: a metric that cannot be computed is None
    with a ``<name>_null_reason``; ``dropped`` lists the frames left out and why."""
    errors = trajectory_errors(est, ref).as_dict()
    few = f"only {errors['frames']} frame(s) with both an estimate and ground truth"
    reasons = {"ate_m": f"{few}; ATE needs at least 3",
               "rpe_trans_m": f"{few}; RPE needs two consecutive such frames",
               "rpe_rot_deg": f"{few}; RPE needs two consecutive such frames",
               "rpe_rot_drift_deg": f"{few}; RPE needs two consecutive such frames",
               "rotation_scale": (f"{few}; the rotation scale needs more than {ROTATION_SCALE_SPAN}"
                                  if errors["frames"] <= ROTATION_SCALE_SPAN else
                                  f"the reference turns less than {ROTATION_SCALE_MIN_DEG:g} deg over every "
                                  f"{ROTATION_SCALE_SPAN} frames")}
    record = finite_or_null(errors, reasons)
    record["dropped_frames"] = dropped or []
    return record


def _dropped_frames(estimated: int, matched: int, no_gt: list[str]) -> list[dict[str, Any]]:
    """The frames left out of the trajectory metrics, grouped by reason (first 10 names each)."""
    dropped = []
    if estimated > matched:
        dropped.append({"reason": "estimated pose matches no input frame by timestamp (within 0.01 s)",
                        "count": estimated - matched, "frames": []})
    if no_gt:
        dropped.append({"reason": "no ground truth at this frame's time (groundtruth.txt does not cover it)",
                        "count": len(no_gt), "frames": no_gt[:10]})
    return dropped


def _number(value: Any, scale: float = 1.0, digits: int = 2) -> str:
    """A figure times ``scale`` as text with ``digits`` decimals; "n/a" when missing."""
    return "n/a" if value is None else f"{value * scale:.{digits}f}"


def format_metrics(metrics: dict[str, Any]) -> str:
    """metrics.json as aligned plain-text tables: trajectory errors per stage (where there is ground truth), image
    scores per split (with the blurred input's as the floor), the no-reference means of real captures, time and
    memory per stage, what was not scored and why, warnings."""

    lines = ["trajectory (after rigid alignment)",
             f"  {'stage':8s} {'ATE mm':>9s} {'RPE mm':>9s} {'RPE deg':>9s} {'drift deg':>9s} {'rot scale':>9s} "
             f"{'frames':>7s}  dropped"] if metrics["trajectory"] else []
    for stage, t in metrics["trajectory"].items():
        dropped = sum(d["count"] for d in t.get("dropped_frames", []))
        lines.append(f"  {stage:8s} {_number(t['ate_m'], 1000):>9s} {_number(t['rpe_trans_m'], 1000):>9s} "
                     f"{_number(t['rpe_rot_deg'], 1, 3):>9s} {_number(t.get('rpe_rot_drift_deg'), 1, 3):>9s} "
                     f"{_number(t.get('rotation_scale'), 1, 3):>9s} {t['frames']:>7d}  {dropped}")
    images = metrics.get("images")
    if images:
        as_read = [("as read PSNR", "as_read_psnr_db", 1, 2), ("as read SSIM", "as_read_ssim", 1, 3)] \
            if "as_read_psnr_db" in images.get("test", images.get("train", {})) else []
        lines += _split_table(f"images (stage 3 renders vs {images['ground_truth']})", images, [
            ("PSNR dB", "psnr_db", 1, 2), ("SSIM", "ssim", 1, 3), ("input PSNR", "blurred_input_psnr_db", 1, 2),
            ("input SSIM", "blurred_input_ssim", 1, 3), *as_read, ("inv-depth RMSE", "inverse_depth_rmse", 1, 4)])
    if not images or images["ground_truth"] != SHARP_TRUTH:  # with sharp ground truth, its scores say more
        lines += _no_reference_lines(metrics.get("no_reference"))
    if metrics.get("stages"):
        lines += ["", f"stages (arch {metrics.get('arch', 'none')})", f"  {'stage':8s} {'seconds':>9s} {'peak MB':>9s}"]
        for stage, s in metrics["stages"].items():
            lines.append(f"  {stage:8s} {_number(s.get('seconds'), 1, 1):>9s} {_number(s.get('peak_rss_mb'), 1, 0):>9s}")
    if metrics.get("not_scored"):
        lines += ["", "not scored"] + [f"  {item['what']}: {item['reason']}" for item in metrics["not_scored"]]
    for warning in metrics.get("warnings", []):
        lines.append(f"warning: {warning}")
    return "\n".join(lines).lstrip("\n")


def _no_reference_lines(figures: dict[str, Any] | None) -> list[str]:
    """The real-data protocol's means per split (re-blur, sharpness, dark holes, exposure length) and, for held-out
    views, the sharp render against the held-out frames beside the warped-neighbour floor and the re-blurred render
    on the floor's pixels."""
    if not figures or not any(split in figures for split in ("test", "train")):
        return []
    lines = _split_table(
        "no-reference figures (real captures; metrics.json no_reference.protocol says how)", figures,
        [("re-blur dB", "reblur_psnr_db", 1, 2), ("SSIM", "reblur_ssim", 1, 3),
         ("sharpness", "gradient_energy_ratio", 1, 3), ("dark %", "dark_hole_fraction", 100, 2),
         ("blur px", "exposure_px", 1, 1)])
    held = figures.get("test", {})
    if "held_out_psnr_db" in held:
        lines += [f"  held-out frames against the sharp render: {_number(held['held_out_psnr_db'])} dB",
                  f"  on the floor's pixels: render {_number(held.get('render_on_warp_mask_psnr_db'))}, re-blurred render "
                  f"{_number(held.get('reblur_on_warp_mask_psnr_db'))}, floor (warped neighbours) "
                  f"{_number(held.get('warped_neighbour_psnr_db'))} dB"]
    return lines


def _split_table(title: str, figures: dict[str, Any], columns: list[tuple[str, str, float, int]]) -> list[str]:
    """A titled block with a row per split (test, train) present in ``figures``: its views, then each column's
    (header, key, scale, digits) figure."""
    widths = [max(len(header), 6) for header, *_ in columns]
    lines = ["", title, f"  {'split':6s} {'views':>5s} " + " ".join(f"{h:>{w}s}" for (h, *_), w in zip(columns, widths))]
    for split in ("test", "train"):
        if split in figures:
            s = figures[split]
            lines.append(f"  {split:6s} {s['views']:>5d} " + " ".join(
                f"{_number(s.get(key), scale, digits):>{w}s}" for (_, key, scale, digits), w in zip(columns, widths)))
    return lines


def _versions() -> dict[str, str]:
    """Versions of the packages that shaped the result (read without importing them: importing
    taichi prints a banner on stdout)."""
    from importlib.metadata import PackageNotFoundError, version

    found = {"taichi-gs": __version__, "python": platform.python_version()}
    for name in ("taichi", "numpy", "open3d", "opencv-python-headless", "scikit-image"):
        try:
            found[name] = version(name)
        except PackageNotFoundError:
            found[name] = "not installed"
    return found


def image_metrics(run_dir: Path, sequence: Sequence) -> dict[str, Any] | None:
    """PSNR/SSIM of stage 3's sharp renders against the sharp ground truth (with the blurred input's
    own scores as the floor) and inverse-depth RMSE of its depth renders against the input depth,
    per split (test views are held out of training); None before stage 3 has run. Where stage 3 modelled a
    rolling shutter, ``as_read_psnr_db`` / ``as_read_ssim`` also score its sharp renders as that shutter reads
    them (deblur/renders/as_read/: each row at the pose it was read from), as a real camera took the truth.

    LPIPS needs network weights that cannot be fetched here, so it is reported as unavailable.
    Writes RUN_DIR/report/test_views.png (input | deblurred | sharp ground truth, where there is one | depth)."""
    deblur = run_dir / "deblur"
    split_path = deblur / "split.json"
    if not split_path.is_file():
        return None
    split = json.loads(split_path.read_text())
    has_sharp = sequence.sharp_paths is not None
    result: dict[str, Any] = {"lpips": "unavailable (no LPIPS network weights on this machine)",
                              "ground_truth": SHARP_TRUTH if has_sharp else "none: only depth is scored"}
    grid_rows, grid_titles = [], []
    for group in ("test", "train"):
        scores: dict[str, list[float]] = {}
        for i in split.get(group, []):
            stem = sequence.names[i]
            render = read_color(deblur / "renders" / "sharp" / f"{stem}.png")
            depth = read_depth(deblur / "renders" / "depth" / f"{stem}.png", sequence.intrinsics.depth_scale)
            scores.setdefault("inverse_depth_rmse", []).append(inverse_depth_rmse(depth, sequence.depth(i)))
            in_grid = group == "test" and len(grid_rows) < GRID_VIEWS
            blurred = sequence.color(i) if has_sharp or in_grid else None
            sharps = [sequence.sharp(i)] if has_sharp else []
            as_read_path = deblur / "renders" / "as_read" / f"{stem}.png"
            as_read = read_color(as_read_path) if has_sharp and as_read_path.is_file() else None
            for sharp in sharps:
                for name, value in (("psnr_db", psnr(render, sharp)), ("ssim", ssim(render, sharp)),
                                    ("blurred_input_psnr_db", psnr(blurred, sharp)),
                                    ("blurred_input_ssim", ssim(blurred, sharp))):
                    scores.setdefault(name, []).append(value)
                if as_read is not None:  # [ours] the sharp render read along the rows as the camera read the truth
                    scores.setdefault("as_read_psnr_db", []).append(psnr(as_read, sharp))
                    scores.setdefault("as_read_ssim", []).append(ssim(as_read, sharp))
            if in_grid:
                grid_rows.append([blurred, render, *sharps, depth])
                grid_titles.append(stem)
        if scores:
            result[group] = {"views": len(split.get(group, [])), **{k: float(np.mean(v)) for k, v in scores.items()}}
    if grid_rows:
        depths = np.concatenate([row[-1][row[-1] > 0] for row in grid_rows])
        lo, hi = np.percentile(depths, [2, 98]) if depths.size else (0.0, 1.0)
        for row in grid_rows:
            row[-1] = colour_map(row[-1], lo, hi)
        width = grid_rows[0][0].shape[1]
        scale = colour_scale(width * max(1, -(-GRID_MIN_WIDTH // width)), lo, hi, "rendered depth (m); black: none")
        image_grid(run_dir / "report" / "test_views.png", grid_rows,
                   ["blurred input", "deblurred (ours)", *(["sharp ground truth"] if has_sharp else []),
                    "rendered depth"], grid_titles, min_width=GRID_MIN_WIDTH, footer=scale)
    return result
