"""Per-frame transforms a ``Sequence`` applies as it reads each frame (``io.load`` builds ``--scale`` on them).

A transform maps (file path, image) to an image. It is keyed by the frame's file path rather than
its index, so subsampling a sequence keeps it valid. Colour is float32 H x W x 3 in [0, 1]; depth is
float32 H x W in metres, 0 where invalid. Pixel convention throughout: OpenCV's (pixel centres at
integer coordinates), so resizing by s maps a coordinate c to (c + 0.5) s - 0.5.
"""

from __future__ import annotations

import dataclasses
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from ..errors import InputError


class FrameTransform:
    """The identity; subclasses override ``color`` and/or ``depth``."""

    def color(self, path: Path, image: np.ndarray) -> np.ndarray:
        return image

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        return depth

    def sourced(self, share: np.ndarray) -> np.ndarray:
        """The share of each output colour pixel that comes from camera pixels, given that share
        (float32 H x W, 1 where seen) on the input grid."""
        return share


@dataclasses.dataclass(frozen=True)
class Chain(FrameTransform):
    """Several transforms, applied in order."""

    steps: tuple[FrameTransform, ...]

    def color(self, path: Path, image: np.ndarray) -> np.ndarray:
        for step in self.steps:
            image = step.color(path, image)
        return image

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        for step in self.steps:
            depth = step.depth(path, depth)
        return depth

    def sourced(self, share: np.ndarray) -> np.ndarray:
        for step in self.steps:
            share = step.sourced(share)
        return share


def then(first: FrameTransform | None, second: FrameTransform) -> FrameTransform:
    """``first`` followed by ``second`` (``first`` may be None)."""
    if first is None:
        return second
    steps = first.steps if isinstance(first, Chain) else (first,)
    return Chain((*steps, second))


def scaled_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """Image size after scaling by ``scale`` (rounded, at least 1 pixel)."""
    return max(1, round(width * scale)), max(1, round(height * scale))


def scale_matrix(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """3x3 intrinsics matrix on a grid resized by (sx, sy), pixel-centre convention."""
    return np.array([[K[0, 0] * sx, 0.0, (K[0, 2] + 0.5) * sx - 0.5],
                     [0.0, K[1, 1] * sy, (K[1, 2] + 0.5) * sy - 0.5],
                     [0.0, 0.0, 1.0]])


def resize_color(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Colour resized by area averaging (bilinear when enlarging)."""
    if (image.shape[1], image.shape[0]) == (width, height):
        return image
    enlarging = width > image.shape[1] or height > image.shape[0]
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR if enlarging else cv2.INTER_AREA)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Depth resized without mixing surfaces or holes: an integer shrink takes the lower median of
    each block's valid pixels (0 if it has none), any other size the nearest pixel to each centre."""
    h, w = depth.shape
    if (w, h) == (width, height):
        return depth
    kx, ky = w // width, h // height
    if kx >= 1 and ky >= 1 and kx * width == w and ky * height == h and kx * ky > 1:
        blocks = depth.reshape(height, ky, width, kx).transpose(0, 2, 1, 3).reshape(height, width, kx * ky)
        valid = blocks > 0
        ordered = np.sort(np.where(valid, blocks, np.inf), axis=2)
        count = valid.sum(axis=2)
        pick = np.take_along_axis(ordered, (np.maximum(count - 1, 0) // 2)[..., None], axis=2)[..., 0]
        return np.where(count > 0, pick, 0.0).astype(np.float32)
    xs = np.minimum(((np.arange(width) + 0.5) * (w / width)).astype(int), w - 1)
    ys = np.minimum(((np.arange(height) + 0.5) * (h / height)).astype(int), h - 1)
    return depth[np.ix_(ys, xs)]


@dataclasses.dataclass(frozen=True)
class Resize(FrameTransform):
    """Colour and depth resized to width x height (``resize_color``, ``resize_depth``)."""

    width: int
    height: int

    def color(self, path: Path, image: np.ndarray) -> np.ndarray:
        return resize_color(image, self.width, self.height)

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        return resize_depth(depth, self.width, self.height)

    def sourced(self, share: np.ndarray) -> np.ndarray:
        return resize_color(share, self.width, self.height)


@dataclasses.dataclass(frozen=True)
class ResampleColor(FrameTransform):
    """Colour taken from a camera with intrinsics ``source_K`` onto the grid of a camera at the same
    place with ``target_K`` (width x height), e.g. a larger colour image onto the depth image's grid.
    Shrinks by area first when the target is coarser, then warps bilinearly."""

    source_K: np.ndarray
    target_K: np.ndarray
    width: int
    height: int

    def color(self, path: Path, image: np.ndarray) -> np.ndarray:
        return self._warp(image, cv2.BORDER_REPLICATE)

    def sourced(self, share: np.ndarray) -> np.ndarray:
        return self._warp(share, cv2.BORDER_CONSTANT)

    def _warp(self, image: np.ndarray, border: int) -> np.ndarray:
        K = self.source_K
        shrink = self.target_K[0, 0] / K[0, 0]
        if shrink < 1.0:
            h, w = image.shape[:2]
            nw, nh = scaled_size(w, h, shrink)
            image = cv2.resize(image, (nw, nh), interpolation=cv2.INTER_AREA)
            K = scale_matrix(K, nw / w, nh / h)
        source_of_target = (K @ np.linalg.inv(self.target_K))[:2]
        return cv2.warpAffine(image, source_of_target, (self.width, self.height),
                              flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderMode=border, borderValue=0)


@dataclasses.dataclass
class Undistort(FrameTransform):
    """Lens distortion removed (OpenCV's model, same K before and after): colour bilinear, depth
    nearest-neighbour (depth is registered to colour, so it shares the colour camera's distortion)."""

    K: np.ndarray
    distortion: np.ndarray
    width: int
    height: int

    @cached_property
    def _maps(self) -> tuple[np.ndarray, np.ndarray]:
        return cv2.initUndistortRectifyMap(self.K, self.distortion, None, self.K, (self.width, self.height), cv2.CV_32FC1)

    def _check_raw(self, path: Path, shape: tuple[int, ...]) -> None:
        if shape[:2] != (self.height, self.width):
            raise InputError(path, f"image is {shape[1]}x{shape[0]}, but its camera's calibration is for "
                             f"{self.width}x{self.height}", "give the frames as the camera recorded them, or pass "
                             "--fx --fy --cx --cy for frames that are already undistorted")

    def color(self, path: Path, image: np.ndarray) -> np.ndarray:
        self._check_raw(path, image.shape)
        return cv2.remap(image, *self._maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        self._check_raw(path, depth.shape)
        return cv2.remap(depth, *self._maps, interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)

    def sourced(self, share: np.ndarray) -> np.ndarray:
        return cv2.remap(share, *self._maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                         borderValue=0)


@dataclasses.dataclass(frozen=True)
class MaskDepth(FrameTransform):
    """Depth set to 0 where the frame's confidence map (8-bit PNG, same size) is below ``minimum``."""

    confidence: dict[Path, Path]
    minimum: int

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        conf_path = self.confidence[path]
        conf = cv2.imread(str(conf_path), cv2.IMREAD_UNCHANGED)
        if conf is None or conf.ndim != 2:
            raise InputError(conf_path, "confidence map is missing, unreadable or not single-channel",
                             "restore it, or remove the confidence/ folder to use all depth")
        if conf.shape != depth.shape:
            raise InputError(conf_path, f"confidence map is {conf.shape[1]}x{conf.shape[0]}, depth {depth.shape[1]}x{depth.shape[0]}",
                             "give confidence maps at the depth resolution")
        return np.where(conf >= self.minimum, depth, 0.0).astype(np.float32)


@dataclasses.dataclass(frozen=True)
class DropDepthAbove(FrameTransform):
    """Depth at or beyond ``limit`` metres set to 0 (a sensor's 'no reading' code, e.g. 65535 mm)."""

    limit: float

    def depth(self, path: Path, depth: np.ndarray) -> np.ndarray:
        return np.where(depth >= self.limit, 0.0, depth).astype(np.float32)
