"""Stand-ins for earlier stages, for benchmarks and tests: perturbed ground-truth poses (stage 2's
input) and OUT/refine/ built from a synthetic sequence's ground-truth mid-exposure poses and its
sensor depth (so stage 3 is measured alone)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .geometry import backproject, se3_exp, transform
from .io.load import load_sequence
from .io.ply import write_splats
from .io.sequence import Sequence
from .io.trajectory import write_tum
from .splats import splats_from_points
from .synth import SynthConfig, generate


def fused_points(sequence: Sequence, poses: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Every frame's depth back-projected with ``poses``, averaged per voxel: points and colours."""
    points, colors = [], []
    for i in range(len(sequence)):
        depth = sequence.depth(i)
        valid = depth > 0
        points.append(transform(poses[i], backproject(depth, sequence.K())[valid]))
        colors.append(sequence.color(i)[valid])
    points, colors = np.concatenate(points), np.concatenate(colors)
    _, inverse, counts = np.unique(np.floor(points / voxel).astype(np.int64), axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    mean = lambda x: np.stack([np.bincount(inverse, x[:, c]) for c in range(3)], axis=1) / counts[:, None]  # noqa: E731
    return mean(points), mean(colors)


def write_refine_outputs(sequence: Sequence, out: Path, voxel: float = 0.03, opacity: float = 0.9) -> None:
    """OUT/refine/trajectory.txt (ground-truth mid poses) and splats.ply (fused depth), OUT/run.json."""
    poses = sequence.gt_poses
    points, colors = fused_points(sequence, poses, voxel)
    write_splats(out / "refine" / "splats.ply", splats_from_points(points, np.clip(colors, 0, 1), voxel / 2, opacity))
    write_tum(out / "refine" / "trajectory.txt", sequence.timestamps, poses, header="ground-truth stand-in for stage 2")
    (out / "run.json").write_text(json.dumps({"sequence": str(Path(sequence.root).resolve())}))


def synthetic_refine_outputs(folder: Path, config: SynthConfig, voxel: float) -> tuple[Sequence, Path]:
    """A synthetic clip generated into FOLDER/seq and stage 2's stand-in outputs for it in FOLDER/out
    (:func:`write_refine_outputs`): (the sequence, the run folder)."""
    generate(config, Path(folder) / "seq")
    sequence = load_sequence(Path(folder) / "seq")
    write_refine_outputs(sequence, Path(folder) / "out", voxel=voxel)
    return sequence, Path(folder) / "out"


def perturbed(gt: np.ndarray, seed: int = 1) -> np.ndarray:
    """GT with a drift growing to 3 cm / 2 degrees at the last frame and per-frame jitter of
    1 cm / 0.5 degrees (rms per axis); the first pose is left exact."""
    rng = np.random.default_rng(seed)
    drift = np.concatenate([rng.normal(size=3), rng.normal(size=3)])
    drift[:3] *= 0.03 / np.linalg.norm(drift[:3])
    drift[3:] *= np.radians(2.0) / np.linalg.norm(drift[3:])
    jitter = np.concatenate([rng.normal(size=(len(gt), 3)) * 0.01, rng.normal(size=(len(gt), 3)) * np.radians(0.5)], axis=1)
    jitter[0] = 0.0
    return np.stack([se3_exp(drift * i / (len(gt) - 1)) @ T @ se3_exp(jitter[i]) for i, T in enumerate(gt)])
