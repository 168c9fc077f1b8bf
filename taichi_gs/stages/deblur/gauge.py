"""[ours] Stage 3's scene and exposures back in stage 2's frame.

Colour fixes a scene and its cameras only up to a common translation and scale (moving both leaves every
image unchanged), and stage 3's depth term, at a tenth of the colour loss's weight, holds that gauge
loosely: on the bundled sample stage 3 moved every camera 5-8 mm from stage 2's and shrank the trajectory by
0.3%, which doubled its ATE. :func:`back_to_stage_2s_frame` undoes that drift after training: the
similarity (scale and translation, no rotation, so view-dependent colour needs no rotating) that maps the
training frames' mid-exposure centres onto stage 2's is applied to the Gaussians and to every exposure, the scale
only where the fit determines it. Colour renders stay the same; rendered depth scales with the scene.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ...geometry import fit_scale_translation, virtual_pose
from ...splats import Splats


@dataclass(frozen=True)
class FrameShift:
    """The similarity applied to stage 3's world: ``x -> scale x + translation`` (metres)."""

    scale: float
    translation: np.ndarray
    scale_error: float  # standard error of the fitted scale (inf: too few frames); above the limit, scale = 1

    def as_dict(self) -> dict[str, object]:
        return {"scale": self.scale, "translation_m": self.translation.tolist(), "scale_error": self.scale_error,
                "rule": "x -> scale x + translation maps stage 3's training mid-exposure centres onto stage 2's"}


def scale_error(source: np.ndarray, target: np.ndarray, scale: float, translation: np.ndarray) -> float:
    """Standard error of ``scale`` fitted with ``translation`` by :func:`fit_scale_translation` (4 parameters
    over 3 N coordinates; inf when N < 2)."""
    n = len(source)
    if n < 2:
        return float("inf")
    residual = scale * source + translation - target
    spread = ((source - source.mean(axis=0)) ** 2).sum()
    return float(np.sqrt((residual ** 2).sum() / (3 * n - 4) / spread)) if spread > 0 else float("inf")


def scaled_twists(twists: np.ndarray, scale: float) -> np.ndarray:
    """Twists ``[rho, phi]`` (..., 6) in a world scaled by ``scale``: their translations scale, their rotations
    do not (a camera frame's offsets, start and end or [ours] bend, move with the scene)."""
    scaled = np.array(twists, dtype=np.float64, copy=True)
    scaled[..., :3] *= scale
    return scaled


def back_to_stage_2s_frame(splats: Splats, poses: np.ndarray, offsets: np.ndarray, train: list[int],
                           max_scale_error: float) -> tuple[Splats, np.ndarray, np.ndarray, FrameShift]:
    """``(splats, poses, offsets)`` moved by the scale and translation that best map the ``train`` frames'
    mid-exposure centres ``virtual_pose(poses[i], *offsets[i], 0.5)`` onto stage 2's ``poses[i]``. The scale is
    kept at 1 (the translation alone) unless the fit determines it to ``max_scale_error`` (its standard error
    from the residuals: centres that hardly spread, or that drifted frame by frame, do not fix a scale).

    ``poses`` (N, 4, 4) are the exposures' bases (stage 2's cameras) and ``offsets`` (N, 2, 6) their start
    and end twists ``[rho, phi]``: a world scaled by s scales each camera frame too, so the bases' centres
    and the twists' translations scale and every virtual pose moves with the scene."""
    target = poses[train, :3, 3]
    mids = np.stack([virtual_pose(poses[i], *offsets[i], 0.5)[:3, 3] for i in train])
    scale, translation = fit_scale_translation(mids, target)
    error = scale_error(mids, target, scale, translation)
    if not error <= max_scale_error:
        scale, translation = fit_scale_translation(mids, target, with_scale=False)
    moved_poses = poses.copy()
    moved_poses[:, :3, 3] = scale * poses[:, :3, 3] + translation
    moved_offsets = scaled_twists(offsets, scale)
    moved = replace(splats, means=(scale * splats.means + translation).astype(splats.means.dtype),
                    log_scales=(splats.log_scales + np.log(scale)).astype(splats.log_scales.dtype))
    return moved, moved_poses, moved_offsets, FrameShift(scale, translation, error)
