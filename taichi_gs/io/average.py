"""Real motion blur with a sharp reference: consecutive frames averaged into one long exposure.

``taichi-gs import --average W`` reads any sequence and writes, per window of W consecutive frames (W odd),
one frame whose colour is the windows' mean in linear light (sRGB decoded, averaged, encoded again), as
the GoPro and REDS deblurring benchmarks are made (Nah et al., CVPR 2017). The window's centre frame is the
reference: its colour goes to ``sharp/`` (its ``sharp/`` image where the input has one), and its depth,
timestamp and ground-truth pose are the averaged frame's. The exposure runs from the window's first frame to
its last (``exposure.txt`` where ground truth covers both), and ``blur.json`` records each frame's measured
streak: the path its scene points draw over the window, from the reference poses and the centre depth where
the poses exist, else the optical flow summed over the window's consecutive frames.
"""

from __future__ import annotations

import copy

import cv2
import numpy as np

from ..errors import InputError
from ..streaks import path_lengths, point_tracks
from .sequence import Sequence

STREAK_STRIDE_PX = 4  # pixel grid stride of the points whose streaks blur.json measures


def srgb_to_linear(image: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] to linear light (IEC 61966-2-1)."""
    image = np.clip(image, 0.0, 1.0)
    return np.where(image <= 0.04045, image / 12.92, ((image + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(image: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] to sRGB-encoded values (IEC 61966-2-1)."""
    image = np.clip(image, 0.0, 1.0)
    return np.where(image <= 0.0031308, image * 12.92, 1.055 * image ** (1 / 2.4) - 0.055)


def average_in_linear_light(frames: list[np.ndarray]) -> np.ndarray:
    """The mean of sRGB frames taken in linear light, encoded to sRGB again (float32 in [0, 1])."""
    linear = np.mean([srgb_to_linear(np.asarray(f, np.float64)) for f in frames], axis=0)
    return linear_to_srgb(linear).astype(np.float32)


class AveragedSequence(Sequence):
    """A sequence whose frame j is the linear-light mean of ``window`` consecutive frames of ``source``
    (frames j W .. j W + W - 1); depth, timestamp, name and pose are the window's centre frame's."""

    def __init__(self, source: Sequence, window: int):
        if window < 3 or window % 2 == 0:
            raise InputError(None, f"--average {window} is not an odd window of 3 or more frames",
                             "give an odd count, e.g. --average 5 (the centre frame is the sharp reference)")
        count = len(source) // window
        if count < 2:
            raise InputError(source.root, f"{len(source)} frames make {count} window(s) of {window}",
                             f"give at least {2 * window} frames (--first/--count) or a smaller --average")
        self.base, self.window = source, window
        centres = [j * window + window // 2 for j in range(count)]
        pick = (lambda values: None if values is None else [values[c] for c in centres])
        super().__init__(source.root, source.layout, source.intrinsics, source.timestamps[centres],
                         pick(source.rgb_paths), pick(source.depth_paths),
                         gt_poses=None if source.gt_poses is None else source.gt_poses[centres],
                         exposure_poses=self._exposures(source, centres, window),
                         sharp_paths=pick(source.sharp_paths) or pick(source.rgb_paths),
                         names=pick(source.names), transform=source.transform, sourced_path=source.sourced_path,
                         depth_timestamps=None if source.depth_timestamps is None else source.depth_timestamps[centres])
        self.centres = centres
        self.source = {**source.source, "average": window}
        self.load_options = copy.copy(source.load_options)

    @staticmethod
    def _exposures(source: Sequence, centres: list[int], window: int) -> np.ndarray | None:
        """Start and end poses of each window (its first and last frame's reference poses), or None where
        ground truth does not cover every window's ends."""
        if source.gt_poses is None:
            return None
        half = window // 2
        ends = np.stack([source.gt_poses[[c - half, c + half]] for c in centres])
        return ends if np.all(np.isfinite(ends)) else None

    def window_of(self, j: int) -> range:
        """Frame indices of the source that make frame j."""
        return range(self.centres[j] - self.window // 2, self.centres[j] + self.window // 2 + 1)

    def color(self, j: int) -> np.ndarray:
        """The window's linear-light mean, float32 H x W x 3 in [0, 1]."""
        return average_in_linear_light([self.base.color(i) for i in self.window_of(j)])

    def sharp(self, j: int) -> np.ndarray:
        """The window's centre frame (its sharp image where the source has one)."""
        centre = self.centres[j]
        return self.base.sharp(centre) if self.base.sharp_paths is not None else self.base.color(centre)

    def depth(self, j: int) -> np.ndarray:
        return self.base.depth(self.centres[j])

    def sourced_pixels(self) -> np.ndarray:
        return self.base.sourced_pixels()

    def streak(self, j: int) -> dict[str, float | str]:
        """Frame j's measured blur in pixels: median and 95th percentile of its points' paths over the
        window, from the reference poses and the centre depth ("poses"), else the median and 95th
        percentile of the optical flow summed over the window's consecutive frames ("flow")."""
        frames = list(self.window_of(j))
        poses = None if self.base.gt_poses is None else self.base.gt_poses[frames]
        if poses is not None and np.all(np.isfinite(poses)):
            tracks = point_tracks(self.depth(j), self.K(), poses[len(frames) // 2], list(poses), STREAK_STRIDE_PX)
            lengths = path_lengths(tracks)[0]
            how = "poses"
        else:
            colours = [self.base.color(i) for i in frames]
            lengths = sum(_flow_lengths(a, b) for a, b in zip(colours, colours[1:]))
            how = "flow"
        if lengths.size == 0:
            return {"median_px": float("nan"), "p95_px": float("nan"), "from": how}
        return {"median_px": float(np.median(lengths)), "p95_px": float(np.percentile(lengths, 95)), "from": how}


def _flow_lengths(first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """Per-pixel optical-flow magnitudes (DIS, medium) from one colour frame to another."""
    grey = [cv2.cvtColor((np.clip(f, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY) for f in (first, last)]
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM).calc(grey[0], grey[1], None)
    return np.linalg.norm(flow, axis=-1).ravel()


def blur_record(sequence: AveragedSequence) -> dict:
    """``blur.json``: the window, the exposure it stands for, and each frame's source frames and streak."""
    spans = [sequence.base.timestamps[w[-1]] - sequence.base.timestamps[w[0]]
             for w in map(sequence.window_of, range(len(sequence)))]
    frames = [{"name": name, "sources": [sequence.base.names[i] for i in sequence.window_of(j)], **sequence.streak(j)}
              for j, name in enumerate(sequence.names)]
    return {"window": sequence.window, "exposure_s": float(np.median(spans)), "frames": frames}
