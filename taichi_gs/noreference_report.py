"""The real-data image protocol of ``taichi-gs eval``: scores of stage 3's renders that need no
sharp ground truth (see :mod:`noreference` for the measures).

Per split (``test`` = held-out views, ``train``), means over views of:
- ``reblur_psnr_db`` / ``reblur_ssim``: the re-blurred render (k-view average over the frame's
  exposure; a held-out frame's exposure is fitted at test time against its own input, scene frozen)
  against the blurred input. High values say the model explains the capture.
- ``gradient_energy_ratio``: gradient energy of the sharp mid-exposure render over the input's
  (above 1: sharper than the capture); ``ground_truth_gradient_energy_ratio`` when sharp images exist.
- ``dark_hole_fraction``: share of pixels dark in the render (below half the input's grey level,
  where the input is at least 0.1).
- [ours] ``exposure_px``: the mean length (pixels, input resolution) of the streaks that the frame's sensor-depth
  points draw over its exposure as stage 3 learned it (:func:`streaks.exposure_smear`, points seen from the
  stage-3 mid-exposure pose): the blur the model found. It bounds what deblurring can add to the sharpness
  above: a capture whose exposures draw 1-2 px streaks has next to no blur to remove, and held-out frames
  whose own exposures draw as long streaks as their neighbours' are not sharp references. The learned start and
  end are the first and last of the k virtual views, so a continuous shutter of the same blur is about
  k / (k - 1) longer (docs/notebook/benchmarks-2026-11.md, "Why the learned exposures look short").
  ``true_exposure_px`` is the same over the sequence's own exposure.txt where it has one (synthetic data; the
  generator samples its exposure at both ends too, with one sub-frame per 0.8 px of its longest streak).
And for held-out views only:
- ``held_out_psnr_db`` / ``held_out_ssim``: sharp render against the held-out frame's own image.
  With ``holdout = "sharpest"`` those frames are the least blurred of their windows: the closest
  thing to sharp ground truth a real capture has (it still holds some blur, noise and exposure
  change, so this is a lower bound on quality).
- ``sharpest_over_neighbours_gradient_energy_ratio``: the held-out frame's gradient energy over the
  mean of its nearest training frames' (before and after): the sharpness gain a render exactly as
  sharp as the sharpest frames would score on training views, i.e. the measure's ceiling for a
  capture whose sharpest frames are the best it holds (at 160x120 on 7-Scenes it is ~1.02).
- ``warped_neighbour_psnr_db`` / ``..._ssim``: the floor. The two nearest training frames (before
  and after) are warped into the held-out view through its sensor depth and the stage-3 poses, the
  better one (PSNR) scored against the held-out frame over the pixels the warp reaches (SSIM: over
  those whose whole 11 x 11 window the warp reaches); ``render_on_warp_mask_psnr_db`` / ``..._ssim``
  score the render over the same pixels. [ours] ``reblur_on_warp_mask_psnr_db`` / ``..._ssim`` score the
  re-blurred render there: like the floor, it carries the held-out frame's own blur, so it tells a scene
  worse than the neighbours apart from a held-out frame that is itself blurred (which the sharp render
  loses to however good it is).
``per_view`` lists every view's figures (``frame``: its name, ``index``, ``split``), in frame order.
Where the reader's transforms leave pixels without a camera source (``Sequence.sourced_pixels``: an
undistorted frame's border, which OpenCV fills by copying the edge), every figure leaves them out
(SSIM: pixels whose whole window was seen); the result gives ``sourced_fraction``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .evaluate import psnr, ssim
from .io.formats.own import read_exposure
from .io.sequence import SOURCED, Sequence, read_color
from .io.trajectory import read_tum
from .noreference import dark_hole_fraction, gradient_energy, masked_psnr, masked_ssim, warp_to_view
from .plots import image_grid, line_plot
from .streaks import exposure_smear

GRID_VIEWS = 4


def protocol_text(split: dict[str, Any]) -> str:
    """One line naming how the held-out views were chosen and what they are scored against."""
    every = split.get("holdout_every", 0)
    if split.get("holdout") == "sharpest":
        chosen = (f"held-out views: the sharpest frame (variance of the Laplacian) of each window of {every} "
                  f"frames (a shorter last window joins the one before it) that lies between two training "
                  f"frames (not the first or last frame, not next to another held-out frame)")
    elif every:
        chosen = f"held-out views: frames 1, 1 + {every}, 1 + 2 x {every}, ... (not chosen by sharpness)"
    else:
        chosen = "no held-out views"
    return (chosen + "; renders scored against the held-out frames' own images, re-blurred renders against "
            "each frame's blurred input; floor: the nearer training frames warped into the view by depth")


def no_reference_metrics(run_dir: Path, sequence: Sequence) -> dict[str, Any] | None:
    """The protocol's figures for a run with stage-3 output (None before stage 3); writes
    RUN_DIR/report/no_reference_views.png (held-out frame | sharp render | re-blurred | warped neighbour) and
    RUN_DIR/report/blur_streaks.png (each frame's streak length, learned and true)."""
    deblur = Path(run_dir) / "deblur"
    split_path, trajectory = deblur / "split.json", deblur / "trajectory.txt"
    if not split_path.is_file() or not trajectory.is_file():
        return None
    split = json.loads(split_path.read_text())
    _, poses = read_tum(trajectory)
    train, test = split.get("train", []), split.get("test", [])
    result: dict[str, Any] = {"protocol": protocol_text(split), "holdout": split.get("holdout", "every"),
                              "holdout_every": split.get("holdout_every")}
    sourced = sequence.sourced_pixels()
    seen = None if sourced.all() else sourced
    result["sourced_fraction"] = float(sourced.mean())
    rolling = (deblur / "renders" / "as_read").is_dir()  # stage 3 modelled a rolling shutter
    if rolling:
        result["protocol"] += ("; a rolling shutter (stage 3's readout_ms): renders scored against held-out frames are "
                               "read along its rows (renders/as_read: each row at its own pose), and so are the dark holes "
                               "(a pixel comparison with the frame); the gradient energy is the global-shutter sharp render's")
    if seen is not None:
        result["protocol"] += (f"; every figure over the {100 * sourced.mean():.1f}% of pixels the camera saw (the "
                               "undistorted frame's border without a source pixel left out)")
    streaks = _streak_lengths(deblur / "exposure.txt", sequence, poses)
    if streaks:
        names = {"exposure_px": "learned (stage 3)", "true_exposure_px": "true (the sequence's exposure.txt)"}
        line_plot(Path(run_dir) / "report" / "blur_streaks.png",
                  {names[key]: (np.arange(len(lengths)), lengths) for key, lengths in streaks.items()},
                  "blur: mean streak over each frame's exposure", "frame", "streak length (px)")
    grid_rows, grid_titles, per_view = [], [], []
    for group, frames in (("test", test), ("train", train)):
        scores: dict[str, list[float]] = {}
        for i in frames:
            name = sequence.names[i]
            frame = sequence.color(i)
            sharp = read_color(deblur / "renders" / "sharp" / f"{name}.png")
            as_read = read_color(deblur / "renders" / "as_read" / f"{name}.png") if rolling else sharp
            reblurred = read_color(deblur / "renders" / "reblurred" / f"{name}.png")
            energy = gradient_energy(frame, mask=seen)
            values = {"reblur_psnr_db": _psnr(reblurred, frame, seen), "reblur_ssim": _ssim(reblurred, frame, seen),
                      "gradient_energy_ratio": gradient_energy(sharp, mask=seen) / max(energy, 1e-12),
                      "dark_hole_fraction": dark_hole_fraction(as_read, frame, mask=seen)}
            values.update({key: lengths[i] for key, lengths in streaks.items()})
            if sequence.sharp_paths is not None:
                values["ground_truth_gradient_energy_ratio"] = (gradient_energy(sequence.sharp(i), mask=seen)
                                                                / max(energy, 1e-12))
            if group == "test":
                warped, mask = _best_neighbour_warp(sequence, poses, train, i, frame, seen)
                values.update({"held_out_psnr_db": _psnr(as_read, frame, seen),
                               "held_out_ssim": _ssim(as_read, frame, seen),
                               "sharpest_over_neighbours_gradient_energy_ratio": _over_neighbours(sequence, train, i,
                                                                                                  energy, seen),
                               "warped_neighbour_psnr_db": masked_psnr(warped, frame, mask),
                               "warped_neighbour_ssim": masked_ssim(warped, frame, mask),
                               "render_on_warp_mask_psnr_db": masked_psnr(as_read, frame, mask),
                               "render_on_warp_mask_ssim": masked_ssim(as_read, frame, mask),
                               "reblur_on_warp_mask_psnr_db": masked_psnr(reblurred, frame, mask),
                               "reblur_on_warp_mask_ssim": masked_ssim(reblurred, frame, mask),
                               "warp_coverage": float(mask.mean())})
                if len(grid_rows) < GRID_VIEWS:
                    grid_rows.append([frame, as_read, reblurred, np.where(mask[..., None], warped, 0.0)])
                    grid_titles.append(name)
            for key, value in values.items():
                scores.setdefault(key, []).append(value)
            per_view.append({"frame": name, "index": i, "split": group, **{k: float(v) for k, v in values.items()}})
        if scores:
            result[group] = {"views": len(frames), **{k: float(np.nanmean(v)) for k, v in scores.items()}}
    result["per_view"] = sorted(per_view, key=lambda view: view["index"])
    if grid_rows:
        image_grid(Path(run_dir) / "report" / "no_reference_views.png", grid_rows,
                   ["held-out frame", "sharp render" + (", as read" if rolling else ""),
                    "re-blurred render", "warped neighbour"], grid_titles)
    return result


def _streak_lengths(learned: Path, sequence: Sequence, mids: np.ndarray) -> dict[str, list[float]]:
    """Per frame mean streak length (pixels) over stage 3's exposure (``exposure_px``, from ``learned``, its
    exposure.txt, seen from the stage-3 mid-exposure poses ``mids``) and over the sequence's own
    (``true_exposure_px``, from its ground-truth poses, where it has exposures and those poses), through the sensor
    depth."""
    exposures = {"exposure_px": (read_exposure(learned, sequence.timestamps), mids),
                 "true_exposure_px": (sequence.exposure_poses, sequence.gt_poses)}
    exposures = {key: pair for key, pair in exposures.items() if pair[0] is not None and pair[1] is not None}
    lengths: dict[str, list[float]] = {key: [] for key in exposures}
    K = sequence.K()
    for i in range(len(sequence) if exposures else 0):
        depth = sequence.depth(i)  # read once for both exposures
        for key, (poses, views) in exposures.items():
            lengths[key].append(exposure_smear(depth, K, views[i], *poses[i])[0])
    return lengths


def _psnr(image: np.ndarray, reference: np.ndarray, seen: np.ndarray | None) -> float:
    """PSNR over the pixels the camera saw (None: the whole frame)."""
    return psnr(image, reference) if seen is None else masked_psnr(image, reference, seen)


def _ssim(image: np.ndarray, reference: np.ndarray, seen: np.ndarray | None) -> float:
    """SSIM over the pixels whose whole window the camera saw (None: the whole frame)."""
    return ssim(image, reference) if seen is None else masked_ssim(image, reference, seen)


def _nearest_training(train: list[int], i: int) -> list[int]:
    """The training views nearest to view i: the last before it and the first after it (those that exist)."""
    before = [j for j in train if j < i]
    after = [j for j in train if j > i]
    return ([before[-1]] if before else []) + ([after[0]] if after else [])


def _over_neighbours(sequence: Sequence, train: list[int], i: int, energy: float, seen: np.ndarray | None) -> float:
    """``energy`` (view i's gradient energy) over the mean of its nearest training frames', over the
    pixels the camera saw; NaN without any."""
    near = _nearest_training(train, i)
    if not near:
        return float("nan")
    neighbours = np.mean([gradient_energy(sequence.color(j), mask=seen) for j in near])
    return energy / max(float(neighbours), 1e-12)


def _best_neighbour_warp(sequence: Sequence, poses: np.ndarray, train: list[int], i: int, frame: np.ndarray,
                         seen: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """The nearest training frame before or after ``i`` warped into view i, whichever scores the
    higher PSNR against ``frame``; (image, mask). With ``seen`` (the pixels the camera saw; None: all)
    the mask keeps the pixels seen in both views, warped with the colour as a fourth channel; it is
    empty if there is no neighbour."""
    depth, K = sequence.depth(i), sequence.K()
    best = (np.zeros_like(frame), np.zeros(frame.shape[:2], bool), -np.inf)
    for j in _nearest_training(train, i):
        source = sequence.color(j)
        if seen is not None:
            source = np.dstack([source, seen.astype(np.float32)])
        warped, mask = warp_to_view(source, poses[j], depth, poses[i], K)
        if seen is not None:
            mask &= seen & (warped[..., 3] >= SOURCED)
            warped = warped[..., :3]
        score = masked_psnr(warped, frame, mask)
        if np.isfinite(score) and score > best[2]:
            best = (warped, mask, score)
    return best[0], best[1]
