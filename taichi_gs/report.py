"""Run evaluation: metrics.json for a run folder, from its stage outputs and the ground truth."""

from __future__ import annotations

import json
import platform
from pathlib import Path
from typing import Any

import numpy as np

from . import __version__
from .errors import InputError
from .evaluate import align_trajectory, match_by_time, trajectory_errors
from .io.atomic import write_text
from .io.sequence import load_sequence
from .io.trajectory import read_tum
from .plots import line_plot, trajectory_plot

STAGES = ("pose", "refine", "deblur")
RUN_INFO = "run.json"


def write_run_info(run_dir: Path, sequence_folder: Path) -> None:
    """Record which sequence a run folder was made from, so `eval` can find its ground truth."""
    write_text(run_dir / RUN_INFO, json.dumps({"sequence": str(sequence_folder.resolve())}, indent=2) + "\n")


def sequence_folder(run_dir: Path, gt: Path | None = None) -> Path:
    """The input sequence of a run: ``gt`` if given, else the one recorded in RUN_DIR/run.json."""
    if gt is not None:
        return gt
    info = run_dir / RUN_INFO
    if not info.is_file():
        raise InputError(run_dir, f"no {RUN_INFO} naming the input sequence", "pass --gt SEQUENCE_FOLDER")
    return Path(json.loads(info.read_text())["sequence"])


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
        raise InputError(run_dir, "no stage output (pose/, refine/, deblur/) with a trajectory.txt", "run 'taichi-gs pose' first")
    if position_errors:
        trajectory_plot(run_dir / "report" / "trajectory_top.png", aligned, "trajectories, aligned to ground truth (top view)")
        line_plot(run_dir / "report" / "position_error.png", position_errors, "position error after alignment",
                  "frame", "error (m)")
    metrics = {
        "trajectory": trajectories,
        "versions": {"taichi-gs": __version__, "python": platform.python_version()},
        "sequence": str(sequence.root),
    }
    write_text(run_dir / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return metrics
