"""What a run folder shows per stage: camera poses, exposures, splats or points, renders.

Plain data read with the project's readers (TUM trajectories, exposure.txt, PLYs, PNGs); the input
sequence is reopened from OUT/run.json for the blurred frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError
from ..geometry import quat_to_rotmat
from ..io.formats.own import read_exposure
from ..io.images import to_uint8
from ..io.ply import read_point_cloud, read_splats
from ..io.sequence import Sequence, read_color
from ..io.trajectory import check_frame_times, read_tum
from ..pipeline import STAGES, open_run_sequence
from ..splats import SH_C0, Splats

SHARP_RENDERS = Path("renders") / "sharp"  # a stage's stored sharp renders, NAME.png per frame


@dataclass
class StageView:
    """One stage's outputs: camera-to-world ``poses`` (N, 4, 4; stage 3: mid-exposure), ``exposures`` (N, 2, 4, 4:
    start and end, stage 3 only), its ``splats`` (stages 2 and 3) or fused ``points`` and colours (stage 1), and
    the folder of its stored sharp renders, if any."""

    name: str
    poses: np.ndarray
    exposures: np.ndarray | None = None
    splats: Splats | None = None
    points: tuple[np.ndarray, np.ndarray] | None = None
    renders: Path | None = None

    @property
    def gaussian_count(self) -> int:
        return 0 if self.splats is None else len(self.splats)


def stages_with_output(run_dir: Path) -> list[str]:
    """The stages of ``run_dir`` (in pipeline order) that wrote a trajectory and a splat or point PLY."""
    return [stage for stage in STAGES if (run_dir / stage / "trajectory.txt").is_file()
            and any((run_dir / stage / name).is_file() for name in ("splats.ply", "points.ply"))]


def load_stage(run_dir: Path, stage: str, sequence: Sequence) -> StageView:
    """Read one stage's outputs, its poses checked against the sequence's frames."""
    folder = run_dir / stage
    timestamps, poses = read_tum(folder / "trajectory.txt")
    check_frame_times(folder / "trajectory.txt", timestamps, sequence.timestamps,
                      "view a run made from this sequence, or rerun the stage")
    splats = read_splats(folder / "splats.ply") if (folder / "splats.ply").is_file() else None
    points = read_point_cloud(folder / "points.ply") if splats is None else None
    renders = folder / SHARP_RENDERS
    return StageView(stage, poses, read_exposure(folder / "exposure.txt", sequence.timestamps), splats, points,
                     renders if renders.is_dir() else None)


def gaussian_arrays(splats: Splats) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centres (N, 3), covariances R S^2 R^T (N, 3, 3), view-independent colours in [0, 1] (N, 3) and
    opacities (N, 1) of the Gaussians, as a splat renderer takes them."""
    rotations = quat_to_rotmat(splats.quats)
    scaled = rotations * np.exp(2.0 * splats.log_scales.astype(np.float64))[:, None, :]
    covariances = scaled @ np.swapaxes(rotations, 1, 2)
    colours = np.clip(SH_C0 * splats.sh[:, 0] + 0.5, 0.0, 1.0)
    return (splats.means.astype(np.float32), covariances.astype(np.float32), colours.astype(np.float32),
            splats.opacities.astype(np.float32)[:, None])


@dataclass
class RunScene:
    """A run folder opened for viewing: its input sequence and each stage that has outputs, in pipeline order."""

    run_dir: Path
    sequence: Sequence
    views: dict[str, StageView]

    @property
    def stages(self) -> list[str]:
        return list(self.views)

    def input_image(self, frame: int) -> np.ndarray:
        """The blurred input frame as 8-bit RGB."""
        return to_uint8(self.sequence.color(frame))

    def stored_render(self, view: StageView, frame: int) -> np.ndarray | None:
        """The stage's stored sharp render of ``frame`` as 8-bit RGB at the input's size, or None without one."""
        path = None if view.renders is None else view.renders / f"{self.sequence.names[frame]}.png"
        if path is None or not path.is_file():
            return None
        render, intr = read_color(path), self.sequence.intrinsics
        if render.shape[:2] != (intr.height, intr.width):  # a run whose frames were read at another --scale
            render = cv2.resize(render, (intr.width, intr.height), interpolation=cv2.INTER_AREA)
        return to_uint8(render)

    def live_render(self, view: StageView, frame: int) -> np.ndarray:
        """The stage's splats rendered at ``frame``'s pose, 8-bit RGB (Taichi initialised by the caller)."""
        from ..render import render_views

        intr = self.sequence.intrinsics
        rgb, _, _ = next(render_views(view.splats, self.sequence.K(), intr.width, intr.height, [view.poses[frame]]))
        return to_uint8(rgb)


def open_run(run_dir: Path) -> RunScene:
    """Open a run folder for viewing; a one-line error when it is no run folder or has no stage output."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise InputError(run_dir, "run folder not found", "give the --out folder of a taichi-gs run")
    sequence = open_run_sequence(run_dir)
    stages = stages_with_output(run_dir)
    if not stages:
        raise InputError(run_dir, "no stage output to show (pose/, refine/ or deblur/ with trajectory.txt and a PLY)",
                         "run 'taichi-gs reconstruct SEQUENCE --out' on this folder first")
    return RunScene(run_dir, sequence, {stage: load_stage(run_dir, stage, sequence) for stage in stages})
