"""[ours] Rolling shutters: a camera that reads its image rows one after another, top to bottom, over a
readout time, so that each row sees the scene from where the camera was when that row was read. Kinect v1's
colour camera is one (BENCHMARKS, "A rolling shutter in TUM's Kinect frames"). Stage 3 models it by warping
each virtual view's rows from global-shutter renders at the row's own pose (``deblur_model``, ``kernels.warp``);
the camera's motion over the readout comes from the trajectory (the neighbouring frames' poses)."""

from __future__ import annotations

import numpy as np

from .geometry import adjoint, invert, se3_exp, se3_log

# Readouts (ms) of the colour cameras of known (format, camera) readings: Kinect v1's, 25 ms, the best of 0, 15, 25
# and 35 ms on a TUM fr1 stretch and near bench/rolling_shutter_readout.py's estimates (BENCHMARKS.md, "A rolling
# shutter in TUM's Kinect frames"). 7-Scenes was shot with a Kinect v1 as well.
KNOWN_READOUT_MS = {("tum", "fr1"): 25.0, ("7scenes", "registered"): 25.0, ("7scenes", "shipped"): 25.0}


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


def camera_readout_ms(source: dict) -> float:
    """The readout (ms) of a sequence's camera where its reading names a known one (``Sequence.source``: format
    and camera; :data:`KNOWN_READOUT_MS`), else 0."""
    return KNOWN_READOUT_MS.get((source.get("format"), source.get("camera")), 0.0)
