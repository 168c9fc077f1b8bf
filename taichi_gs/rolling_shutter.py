"""[ours] Rolling shutters: a camera that reads its image rows one after another, top to bottom, over a
readout time, so that each row sees the scene from where the camera was when that row was read. Kinect v1's
colour camera is one (docs/notebook/benchmarks-2026-11.md, "A rolling shutter in TUM's Kinect frames"). Stage 3
models it by warping each virtual view's rows from global-shutter renders at the row's own pose (``stages.deblur.model``,
``kernels.warp``); stages 1 and 2 de-skew the frames instead: each frame's colour and depth moved to the pose of its
middle row (:class:`DeskewedSequence`). The camera's motion over the readout comes from the trajectory (the
neighbouring frames' poses)."""

from __future__ import annotations

import functools
from typing import Any

import cv2
import numpy as np

from .geometry import adjoint, invert, median_depths, se3_exp, se3_log
from .io.readout import camera_readout_ms


def shutter_rows(readout_motion: np.ndarray, height: int) -> np.ndarray:
    """(H, 4, 4) transforms from the pose at which image row v was read to the frame's pose,
    ``exp(((v + 1/2) / H - 1/2) readout_motion)``, for a camera whose motion from reading the first row to
    reading the last is the twist ``readout_motion`` (camera frame, [translation, rotation]; rows read at a
    steady rate, the middle row at the frame's pose)."""
    motion = np.asarray(readout_motion, dtype=np.float64)
    return np.stack([se3_exp(((v + 0.5) / height - 0.5) * motion) for v in range(height)])


def readout_motions(poses: np.ndarray, timestamps: np.ndarray, readout_s: float) -> np.ndarray:
    """(N, 6) each frame's motion over a readout of ``readout_s`` seconds: the camera's velocity (a twist in
    its own frame) from its neighbours' camera-to-world ``poses`` (the frames before and after; one side at
    the ends), times the readout. Zero for a global shutter (``readout_s`` 0), a single frame, or neighbours
    without a positive time between them."""
    poses = np.asarray(poses, dtype=np.float64)
    n = len(poses)
    motions = np.zeros((n, 6))
    if readout_s <= 0 or n < 2:
        return motions
    for i in range(n):
        a, b = max(i - 1, 0), min(i + 1, n - 1)
        dt = float(timestamps[b] - timestamps[a])
        if not dt > 0:
            continue
        velocity = se3_log(invert(poses[a]) @ poses[b]) / dt  # in frame a's axes
        motions[i] = adjoint(invert(poses[i]) @ poses[a]) @ velocity * readout_s  # in frame i's
    return motions


def readout_px(readout_motion: np.ndarray, focal: float, depth: float) -> float:
    """How far (pixels, at ``depth`` metres, focal ``focal``) the first or last row's pose lies from the
    frame's: half the readout motion's image travel, ``focal (|t| / depth + |angle|) / 2``."""
    motion = np.asarray(readout_motion, dtype=np.float64)
    return float(0.5 * focal * (np.linalg.norm(motion[:3]) / depth + np.linalg.norm(motion[3:])))


def stage_readout_ms(readout_ms: float, camera_readout: bool, source: dict) -> float:
    """A stage's readout (ms): its own ``readout_ms`` when set, else with ``camera_readout`` the known camera's
    (``io.readout.camera_readout_ms``), else 0."""
    if readout_ms == 0 and camera_readout:
        return camera_readout_ms(source)
    return readout_ms


# The most a frame's first or last row is moved when de-skewing, as a fraction of the image width (at the frame's
# median depth; readout_px): a readout motion beyond it comes from a pose jump between neighbours, not from the
# camera, and is scaled down to it. TUM fr1_rpy's fastest frames move their first and last rows 19 px of 640.
MAX_DESKEW_WIDTH_FRACTION = 0.1


def readout_skews(motions: np.ndarray, focal: float, depths: np.ndarray) -> np.ndarray:
    """Each frame's :func:`readout_px` (pixels, its readout motion at its depth in ``depths``)."""
    return np.array([readout_px(m, focal, z) for m, z in zip(motions, depths)])


def deskewing_motions(sequence: Any, motions: np.ndarray) -> tuple[np.ndarray, float]:
    """The readout ``motions`` (:func:`readout_motions`) scaled down where they would move a frame's rows by more
    than :data:`MAX_DESKEW_WIDTH_FRACTION` of the width, and the largest :func:`readout_px` of any frame after that
    (pixels, at its median depth)."""
    limit = MAX_DESKEW_WIDTH_FRACTION * sequence.intrinsics.width
    depths = median_depths([sequence.depth(i) for i in range(len(sequence))])
    skews = readout_skews(motions, sequence.K()[0, 0], depths)
    motions = motions * np.minimum(1.0, limit / np.maximum(skews, 1e-12))[:, None]
    return motions, float(min(skews.max(initial=0.0), limit))


DESKEW_CACHE_FRAMES = 16  # frames whose de-skewing maps a DeskewedSequence keeps (stage 1's window of frames)

# De-skewing inverts the rows' displacement by fixed-point steps; displacements are a few pixels and smooth
# along the image, so a few steps settle them to well under a hundredth of a pixel.
DESKEW_STEPS = 4


def deskew_maps(depth: np.ndarray, K: np.ndarray, readout_motion: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each pixel of a frame seen from its middle row's pose (the frame's pose) was read: ``(map_u,
    map_v)`` (H, W float32, for ``cv2.remap``) and ``depth_at_pose`` (H, W float32: each read pixel's depth
    from the frame's pose, 0 where the reading has none). Pixels without depth move as if at the median
    depth (the readout's rotation, which dominates, moves them alike at any depth)."""
    height, width = depth.shape
    rows = shutter_rows(readout_motion, height)
    valid = np.isfinite(depth) & (depth > 0)
    fill = float(np.median(depth[valid])) if valid.any() else 1.0
    z = np.where(valid, depth, fill).astype(np.float64)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    read = ((u - cx) / fx * z, (v - cy) / fy * z, z)
    R, t = rows[:, None, :3, :3], rows[:, None, :3, 3]  # each row's rotation and translation, broadcast along it
    at_pose = [R[..., a, 0] * read[0] + R[..., a, 1] * read[1] + R[..., a, 2] * read[2] + t[..., a] for a in range(3)]
    shift_u = (fx * at_pose[0] / at_pose[2] + cx - u).astype(np.float32)
    shift_v = (fy * at_pose[1] / at_pose[2] + cy - v).astype(np.float32)
    # the pixel read at s lands at s + shift(s); find s for every landing pixel x: s = x - shift(s)
    map_u, map_v = u.astype(np.float32), v.astype(np.float32)
    for _ in range(DESKEW_STEPS):
        moved_u = cv2.remap(shift_u, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        moved_v = cv2.remap(shift_v, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        map_u, map_v = (u - moved_u).astype(np.float32), (v - moved_v).astype(np.float32)
    depth_at_pose = np.where(valid, at_pose[2], 0.0).astype(np.float32)
    return map_u, map_v, depth_at_pose


class DeskewedSequence:
    """[ours] A sequence whose frames are seen from their poses as a global shutter would see them: colour and
    depth of each frame moved from the pose at which each row was read (its readout motion, :func:`shutter_rows`)
    to the frame's pose. Colour is resampled bilinearly, depth by nearest pixel (its values taken from the frame's
    pose); pixels the readout brought in from outside the frame have no depth and repeat the edge's colour.
    Everything else is the wrapped sequence's; frames with no motion are its own. The maps of the
    :data:`DESKEW_CACHE_FRAMES` frames read last are kept, so a frame's colour and depth share one."""

    def __init__(self, sequence: Any, readout_motions: np.ndarray):
        self.sequence = sequence
        self.readout_motions = np.asarray(readout_motions, dtype=np.float64)
        if len(self.readout_motions) != len(sequence):
            raise ValueError(f"{len(self.readout_motions)} readout motions for {len(sequence)} frames")
        self._maps = functools.lru_cache(maxsize=DESKEW_CACHE_FRAMES)(self._deskew_maps)

    def __len__(self) -> int:
        return len(self.sequence)

    def __getattr__(self, name: str) -> Any:
        if name == "sequence":  # not set yet: an instance made without __init__ (copy, pickle)
            raise AttributeError(name)
        return getattr(self.sequence, name)

    def color(self, i: int) -> np.ndarray:
        color = self.sequence.color(i)
        if not self.readout_motions[i].any():
            return color
        map_u, map_v, _ = self._maps(i)
        return cv2.remap(color, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def depth(self, i: int) -> np.ndarray:
        if not self.readout_motions[i].any():
            return self.sequence.depth(i)
        return self._maps(i)[2]

    def _deskew_maps(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Frame ``i``'s :func:`deskew_maps`, with its de-skewed depth in place of the depth at its pose."""
        map_u, map_v, depth_at_pose = deskew_maps(self.sequence.depth(i), self.sequence.K(), self.readout_motions[i])
        depth = cv2.remap(depth_at_pose, map_u, map_v, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        for image in (map_u, map_v, depth):
            image.flags.writeable = False  # shared by every caller
        return map_u, map_v, depth
