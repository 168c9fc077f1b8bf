"""Run evaluation: metrics.json for a run folder, from its stage outputs and the ground truth."""

from __future__ import annotations

import json
import platform
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .errors import InputError
from .evaluate import align_trajectory, inverse_depth_rmse, match_by_time, psnr, ssim, trajectory_errors
from .io.atomic import write_text
from .io.sequence import Sequence, load_sequence, read_color, read_depth
from .io.trajectory import read_tum
from .noreference_report import no_reference_metrics
from .pipeline import iter_stage_records, sequence_folder
from .plots import image_grid, line_plot, trajectory_plot

STAGES = ("pose", "refine", "deblur")
GRID_VIEWS = 4


def evaluate_run(run_dir: Path, gt: Path | None = None) -> dict[str, Any]:
    """Trajectory errors of every finished stage against ground truth; writes RUN_DIR/metrics.json."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder not found", "give the --out folder of a taichi-gs run")
    sequence = load_sequence(sequence_folder(run_dir, gt))
    if sequence.gt_poses is None:
        raise InputError(sequence.root, "sequence has no groundtruth.txt", "evaluate against a sequence with ground truth")
    trajectories: dict[str, Any] = {}
    aligned: dict[str, np.ndarray] = {"ground truth": sequence.gt_poses}
    position_errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for stage in STAGES:
        path = run_dir / stage / "trajectory.txt"
        if not path.is_file():
            continue
        t_est, est = read_tum(path)
        i, j = match_by_time(t_est, sequence.timestamps)
        gt = sequence.gt_poses[j]
        trajectories[stage] = trajectory_errors(est[i], gt).as_dict()
        finite = np.all(np.isfinite(gt.reshape(len(gt), -1)), axis=1)
        if finite.sum() >= 3:
            moved = align_trajectory(est[i][finite], gt[finite])
            aligned[stage] = moved
            position_errors[stage] = (j[finite], np.linalg.norm(moved[:, :3, 3] - gt[finite][:, :3, 3], axis=1))
    if not trajectories:
        raise InputError(run_dir, "no stage output (pose/, refine/, deblur/) with a trajectory.txt", "run 'taichi-gs reconstruct' first")
    if position_errors:
        trajectory_plot(run_dir / "report" / "trajectory_top.png", aligned, "trajectories, aligned to ground truth (top view)")
        line_plot(run_dir / "report" / "position_error.png", position_errors, "position error after alignment",
                  "frame", "error (m)")
    stages = {stage: {k: record.get(k) for k in ("seconds", "peak_rss_mb", "arch", "summary")}
              for stage, record in iter_stage_records(run_dir)}
    metrics = {
        "trajectory": trajectories,
        "images": image_metrics(run_dir, sequence),
        "no_reference": no_reference_metrics(run_dir, sequence),
        "stages": stages,
        "arch": next((s["arch"] for s in stages.values() if s.get("arch") not in (None, "none")), "none"),
        "versions": _versions(),
        "sequence": str(sequence.root),
    }
    write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return metrics


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
    per split (test views are held out of training); None before stage 3 has run.

    LPIPS needs network weights that cannot be fetched here, so it is reported as unavailable.
    Writes RUN_DIR/report/test_views.png (input | deblurred | ground truth | depth)."""
    deblur = run_dir / "deblur"
    split_path = deblur / "split.json"
    if not split_path.is_file():
        return None
    split = json.loads(split_path.read_text())
    has_sharp = sequence.sharp_paths is not None
    result: dict[str, Any] = {"lpips": "unavailable (no LPIPS network weights on this machine)",
                              "ground_truth": "sharp images" if has_sharp else "none: only depth is scored"}
    grid_rows, grid_titles = [], []
    for group in ("test", "train"):
        scores: dict[str, list[float]] = {}
        for i in split.get(group, []):
            stem = sequence.names[i]
            render = read_color(deblur / "renders" / "sharp" / f"{stem}.png")
            depth = read_depth(deblur / "renders" / "depth" / f"{stem}.png", sequence.intrinsics.depth_scale)
            scores.setdefault("inverse_depth_rmse", []).append(inverse_depth_rmse(depth, sequence.depth(i)))
            if has_sharp:
                sharp, blurred = sequence.sharp(i), sequence.color(i)
                for name, value in (("psnr_db", psnr(render, sharp)), ("ssim", ssim(render, sharp)),
                                    ("blurred_input_psnr_db", psnr(blurred, sharp)),
                                    ("blurred_input_ssim", ssim(blurred, sharp))):
                    scores.setdefault(name, []).append(value)
                if group == "test" and len(grid_rows) < GRID_VIEWS:
                    grid_rows.append([blurred, render, sharp, _depth_image(depth)])
                    grid_titles.append(stem)
        if scores:
            result[group] = {"views": len(split.get(group, [])), **{k: float(np.mean(v)) for k, v in scores.items()}}
    if grid_rows:
        image_grid(run_dir / "report" / "test_views.png", grid_rows,
                   ["blurred input", "deblurred (ours)", "sharp ground truth", "rendered depth"], grid_titles)
    return result


def _depth_image(depth: np.ndarray) -> np.ndarray:
    """Depth as a grey image (near = bright), for grids."""
    valid = depth > 0
    if not valid.any():
        return np.zeros_like(depth)
    lo, hi = np.percentile(depth[valid], [2, 98])
    return np.where(valid, 1.0 - np.clip((depth - lo) / max(hi - lo, 1e-6), 0, 1), 0.0)
