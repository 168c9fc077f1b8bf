"""Synthetic blurred RGB-D sequences with exact ground truth.

The scene is a closed room of one of several kinds (:mod:`taichi_gs.synth_scenes`: the textured
``room`` with spheres, cylinders and boxes; an ``office`` with furniture; a ``plain`` low-texture,
planar-dominant room; a ``corridor``), every object kept outside a central disc in which every
camera path runs. It is ray cast exactly (:mod:`taichi_gs.kernels.raycast`); depth is the camera z
of the first hit.

Each frame's exposure is centred on its timestamp ``i / fps``: the mid-exposure pose is the ground
truth, and the start and end poses are ``mid @ exp(-+delta)``, so SE(3) interpolation from start to
end passes through the mid pose at tau = 0.5. The blurred colour is the plain mean of ``k`` sharp
renders at ``interpolate(start, end, tau)`` for ``tau = linspace(0, 1, k)``, with ``k`` chosen per
frame so that adjacent renders move every visible point by less than ``SUBFRAME_STEP_PX``. The
exposure fraction of the frame interval is chosen per sequence so that the mean smear reaches the
blur level's target (a fraction of the image width), capped at the full frame interval.

[ours] ``readout_ms`` > 0 makes a rolling shutter, as Kinect v1's colour camera has: image row v is exposed
``readout ((v + 1/2) / H - 1/2)`` later than the frame's timestamp (rows read top to bottom, the middle row at
the timestamp), over an exposure of the same length, along the camera's path itself. Each row averages the
sharp renders (spaced as above over the whole readout and exposure) whose times fall in its exposure, and its
depth is the depth of its row at its own mid-exposure time (the sensor's rows follow the colour's). The sharp
ground truth stays a global-shutter render at the timestamp's pose, and ``exposure.txt`` the middle row's
exposure.

Taichi is imported (through :mod:`taichi_gs.kernels.raycast`) only when something is rendered, so
building and validating a :class:`SynthConfig` stays cheap.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from . import __version__
from .choices import BLUR_LEVELS, SCENES, TRAJECTORIES
from .geometry import intrinsics_matrix, invert, pose_from_rt, se3_exp, se3_log, so3_exp
from .io import jsonout
from .io.atomic import write_text
from .io.images import encode_depth, to_uint8, write_png
from .io.sequence import Intrinsics
from .io.trajectory import format_tum, write_tum
from .streaks import exposure_poses, exposure_smear, path_lengths, point_tracks
from .synth_scenes import CAMERA_DISC_RADIUS_M, build_scene  # noqa: F401 (CAMERA_DISC_RADIUS_M re-exported)

GENERATOR_VERSION = 1
# Target mean smear per blur level as a fraction of the image width (7.5 px and 30 px at 640 wide).
BLUR_TARGET_WIDTH_FRACTION = {"none": 0.0, "moderate": 7.5 / 640, "extreme": 30.0 / 640}
MAX_EXPOSURE_FRACTION = 1.0
SUBFRAME_STEP_PX = 0.8
MAX_SUBFRAMES = 400
MOTION_PASS_DOWNSCALE = 4  # the exposure-fraction pass renders depth at 1/4 resolution

DEPTH_NOISE_QUADRATIC = 0.0015  # sigma = 0.0015 z^2 (metres)
MAX_RANGE_M = 5.0
DROPOUT_BLOB_FRACTION = 0.015
DROPOUT_PIXEL_FRACTION = 0.005
EDGE_RELATIVE_STEP = 0.03
EDGE_DROP_PROBABILITY = 0.7


@dataclass
class SynthConfig:
    """What to generate; validated on construction (ValueError names the allowed values)."""

    width: int = 320
    height: int = 240
    frames: int = 60
    trajectory: str = "handheld"  # translation | turn | handheld
    scene: str = "room"  # room | office | plain | corridor (see taichi_gs.synth_scenes)
    blur: str = "extreme"  # none | moderate | extreme
    seed: int = 0
    depth_noise: bool = True
    holes: bool = True
    fps: float = 30.0
    fov_deg: float = 60.0  # horizontal; fx = fy
    depth_scale: float = 5000.0
    readout_ms: float = 0.0  # [ours] rolling shutter: rows read top to bottom over this time (0: global shutter)

    def __post_init__(self) -> None:
        if self.trajectory not in TRAJECTORIES:
            raise ValueError(f"unknown trajectory {self.trajectory!r}: choose one of {', '.join(TRAJECTORIES)}")
        if self.scene not in SCENES:
            raise ValueError(f"unknown scene {self.scene!r}: choose one of {', '.join(SCENES)}")
        if self.blur not in BLUR_LEVELS:
            raise ValueError(f"unknown blur {self.blur!r}: choose one of {', '.join(BLUR_LEVELS)}")
        if self.width < 16 or self.height < 16:
            raise ValueError(f"image size {self.width}x{self.height} too small: give at least 16x16")
        if self.frames < 2:
            raise ValueError(f"frames must be at least 2, got {self.frames}")
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not 10.0 <= self.fov_deg <= 150.0:
            raise ValueError(f"fov_deg must lie in [10, 150], got {self.fov_deg}")
        if not self.depth_scale > 0:
            raise ValueError(f"depth_scale must be positive, got {self.depth_scale}")
        if not (math.isfinite(self.readout_ms) and 0.0 <= self.readout_ms <= 1000.0 / self.fps):
            raise ValueError(f"readout_ms must lie in [0, {1000.0 / self.fps:g}] (one frame interval), "
                             f"got {self.readout_ms}")


# ---------------------------------------------------------------------------------------------
# Camera


def camera_matrix(config: SynthConfig) -> np.ndarray:
    """Pinhole K with fx = fy from the horizontal field of view, principal point at the centre."""
    fx = 0.5 * config.width / math.tan(math.radians(config.fov_deg) / 2.0)
    return intrinsics_matrix(fx, fx, (config.width - 1) / 2.0, (config.height - 1) / 2.0)


def _downscaled(K: np.ndarray, factor: int) -> np.ndarray:
    """Intrinsics of an image shrunk by ``factor`` (OpenCV pixel-centre convention)."""
    return intrinsics_matrix(K[0, 0] / factor, K[1, 1] / factor,
                             (K[0, 2] + 0.5) / factor - 0.5, (K[1, 2] + 0.5) / factor - 0.5)


# ---------------------------------------------------------------------------------------------
# Rendering


def render_view(
    pose: np.ndarray, K: np.ndarray, width: int, height: int, seed: int = 0, scene: str = "room"
) -> tuple[np.ndarray, np.ndarray]:
    """Sharp colour (H x W x 3 float32 in [0, 1]) and exact z-depth (H x W float32, metres)."""
    return _render_mean([pose], K, width, height, seed, scene)


def _render_mean(
    poses, K: np.ndarray, width: int, height: int, seed: int, scene: str = "room"
) -> tuple[np.ndarray, np.ndarray]:
    """Mean colour over poses, depth at the first pose."""
    from .kernels.raycast import render

    room = build_scene(seed, scene)
    rgb, depth = render(np.asarray(poses), K, width, height, room.prims, room.textures)
    return np.clip(rgb, 0.0, 1.0), depth


# ---------------------------------------------------------------------------------------------
# Trajectories: continuous camera-to-world pose as a function of time (seconds)


def _rotation(yaw: float, pitch: float = 0.0, shake: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-world rotation: heading about world y (down), pitch down, then a small shake."""
    R = so3_exp([0.0, yaw, 0.0]) @ so3_exp([-pitch, 0.0, 0.0])
    return R if shake is None else R @ so3_exp(shake)


def _translation_path(rng: np.random.Generator, duration: float) -> Callable[[float], np.ndarray]:
    """Fast sideways sweeps (up to 4 m/s) back and forth, looking at one side of the room; the
    sweeps repeat, so any duration stays in the room."""
    yaw, pitch, phase = rng.uniform(0.0, 2 * math.pi), rng.uniform(0.03, 0.12), rng.uniform(0, 2 * math.pi)
    R = _rotation(yaw, pitch)
    right = np.array([math.cos(yaw), 0.0, -math.sin(yaw)])
    forward = np.array([math.sin(yaw), 0.0, math.cos(yaw)])
    amplitude, omega = 1.0, 4.0

    def pose(t: float) -> np.ndarray:
        return pose_from_rt(R, 0.5 * forward + amplitude * math.sin(omega * t + phase) * right)

    return pose


def _turn_path(rng: np.random.Generator, duration: float) -> Callable[[float], np.ndarray]:
    """One full turn in place over the sequence, standing near the room's centre."""
    centre = np.array([rng.uniform(-0.2, 0.2), 0.0, rng.uniform(-0.2, 0.2)])
    yaw0, pitch = rng.uniform(0.0, 2 * math.pi), rng.uniform(0.03, 0.12)

    def pose(t: float) -> np.ndarray:
        return pose_from_rt(_rotation(yaw0 + 2.0 * math.pi * t / duration, pitch), centre)

    return pose


def _handheld_path(rng: np.random.Generator, duration: float) -> Callable[[float], np.ndarray]:
    """A walk around an ellipse looking ahead and aside, with a step bob and hand shake."""
    axes, tilt = np.array([1.0, 0.8]), rng.uniform(0.0, math.pi)
    omega, phase = rng.choice([-1.0, 1.0]) * 1.5, rng.uniform(0.0, 2 * math.pi)
    look_phase = rng.uniform(0.0, 2 * math.pi)
    shake_amp = np.radians([1.0, 0.7, 0.4])[:, None] * rng.uniform(0.7, 1.3, (3, 3))
    shake_freq = rng.uniform([[1.8], [3.5], [6.0]], [[2.6], [5.0], [8.0]], (3, 3))
    shake_phase = rng.uniform(0.0, 2 * math.pi, (3, 3))
    c, s = math.cos(tilt), math.sin(tilt)

    def pose(t: float) -> np.ndarray:
        a = omega * t + phase
        ex, ez = axes[0] * math.cos(a), axes[1] * math.sin(a)
        vx, vz = -axes[0] * math.sin(a) * omega, axes[1] * math.cos(a) * omega
        position = np.array([c * ex - s * ez, 0.03 * math.sin(2 * math.pi * 1.8 * t), s * ex + c * ez])
        heading = math.atan2(c * vx - s * vz, s * vx + c * vz) + 0.45 * math.sin(0.8 * t + look_phase)
        shake = (shake_amp * np.sin(2 * math.pi * shake_freq * t + shake_phase)).sum(axis=0)
        pitch = 0.08 + 0.05 * math.sin(0.5 * t)
        return pose_from_rt(_rotation(heading, pitch, shake), position)

    return pose


_PATHS = {"translation": _translation_path, "turn": _turn_path, "handheld": _handheld_path}


def _camera_path(config: SynthConfig) -> Callable[[float], np.ndarray]:
    rng = np.random.default_rng([config.seed, 0x7A7])
    return _PATHS[config.trajectory](rng, config.frames / config.fps)


def _exposure_pair(path: Callable[[float], np.ndarray], t: float, half_span: float) -> np.ndarray:
    """Start and end poses ``mid @ exp(-+delta)``, delta the half-exposure twist of the path at t."""
    mid = path(t)
    if half_span == 0.0:
        return np.stack([mid, mid])
    ahead = se3_log(invert(mid) @ path(t + half_span))
    behind = se3_log(invert(mid) @ path(t - half_span))
    delta = 0.5 * (ahead - behind)
    return np.stack([mid @ se3_exp(-delta), mid @ se3_exp(delta)])


def _mean_frame_motion_px(config: SynthConfig, mid_poses: np.ndarray) -> float:
    """Mean image motion (full-resolution pixels) of scene points between consecutive frames."""
    factor = MOTION_PASS_DOWNSCALE
    K = camera_matrix(config)
    small = _downscaled(K, factor)
    w, h = max(config.width // factor, 8), max(config.height // factor, 8)
    motions = []
    for a, b in zip(mid_poses[:-1], mid_poses[1:]):
        _, depth = render_view(a, small, w, h, config.seed, config.scene)
        lengths, _ = path_lengths(point_tracks(depth, small, a, [a, b]))
        # No point in front of both cameras (a half turn between frames): count a full image width.
        motions.append(factor * lengths.mean() if lengths.size else float(config.width))
    return float(np.mean(motions))


def exposure_fraction(config: SynthConfig, mid_poses: np.ndarray) -> float:
    """Share of the frame interval the shutter is open, set so the mean smear meets the blur target."""
    target_px = BLUR_TARGET_WIDTH_FRACTION[config.blur] * config.width
    if target_px == 0.0:
        return 0.0
    return min(MAX_EXPOSURE_FRACTION, target_px / max(_mean_frame_motion_px(config, mid_poses), 1e-9))


def _sequence_poses(config: SynthConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Timestamps, mid poses, exposure start/end poses and the exposure fraction."""
    path = _camera_path(config)
    timestamps = np.arange(config.frames) / config.fps
    mids = np.stack([path(t) for t in timestamps])
    fraction = exposure_fraction(config, mids)
    half_span = 0.5 * fraction / config.fps
    exposure = np.stack([_exposure_pair(path, t, half_span) for t in timestamps])
    return timestamps, mids, exposure, fraction


def trajectory_poses(config: SynthConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Timestamps (N,), mid-exposure poses (N x 4 x 4) and exposure start/end poses (N x 2 x 4 x 4)."""
    timestamps, mids, exposure, _ = _sequence_poses(config)
    return timestamps, mids, exposure


# ---------------------------------------------------------------------------------------------
# Blur


def subframe_count(max_smear_px: float) -> int:
    """Sharp renders per exposure so that adjacent ones move points by < SUBFRAME_STEP_PX."""
    if max_smear_px <= 0.0:
        return 1
    return min(MAX_SUBFRAMES, max(2, math.ceil(max_smear_px / SUBFRAME_STEP_PX) + 1))


# ---------------------------------------------------------------------------------------------
# Depth sensor model


def _depth_edges(depth: np.ndarray) -> np.ndarray:
    """Pixels beside a depth step of more than EDGE_RELATIVE_STEP (both sides, grown by 1 px)."""
    edges = np.zeros(depth.shape, bool)
    for axis in (0, 1):
        a = np.swapaxes(depth, 0, axis)
        step = np.abs(np.diff(a, axis=0)) > EDGE_RELATIVE_STEP * np.minimum(a[1:], a[:-1])
        e = np.swapaxes(edges, 0, axis)
        e[1:] |= step
        e[:-1] |= step
    return cv2.dilate(edges.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def _hole_mask(depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Invalid pixels: beyond range, random blobs and single pixels, and many depth-edge pixels."""
    h, w = depth.shape
    coarse = rng.random((h // 12 + 2, w // 12 + 2)).astype(np.float32)
    smooth = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    blobs = smooth > np.quantile(smooth, 1.0 - DROPOUT_BLOB_FRACTION)
    pixels = rng.random((h, w)) < DROPOUT_PIXEL_FRACTION
    edges = _depth_edges(depth) & (rng.random((h, w)) < EDGE_DROP_PROBABILITY)
    return (depth > MAX_RANGE_M) | blobs | pixels | edges


def sensor_depth(depth: np.ndarray, config: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    """Exact depth turned sensor-like: Gaussian noise sigma = 0.0015 z^2 and holes (0), as configured."""
    out = depth.astype(np.float64)
    if config.depth_noise:
        out += rng.standard_normal(out.shape) * DEPTH_NOISE_QUADRATIC * out**2
    if config.holes:
        out[_hole_mask(depth, rng)] = 0.0
    return out


# ---------------------------------------------------------------------------------------------
# Output


@dataclass(frozen=True)
class FrameStats:
    """How a frame's blur was made: sharp renders averaged and the streak lengths measured."""

    subframes: int
    smear_mean_px: float
    smear_max_px: float


@dataclass(frozen=True)
class FrameImages:
    """One generated frame before it is written: colours in [0, 1] and the 16-bit depth."""

    blurred: np.ndarray
    sharp: np.ndarray
    depth_raw: np.ndarray


def render_frame(
    config: SynthConfig, index: int, mid: np.ndarray, exposure: np.ndarray, exposure_s: float = 0.0
) -> tuple[FrameImages, FrameStats]:
    """Sharp view and depth at mid-exposure, blurred colour over the exposure, sensor depth; with a rolling
    shutter (``config.readout_ms``) the rows' exposures of ``exposure_s`` seconds follow the camera path."""
    K = camera_matrix(config)
    sharp, depth = render_view(mid, K, config.width, config.height, config.seed, config.scene)
    smear_mean, smear_max = exposure_smear(depth, K, mid, exposure[0], exposure[1])
    count = subframe_count(smear_max)
    blurred = sharp
    if config.readout_ms > 0:
        blurred, depth, count = _rolling_shutter_frame(config, index / config.fps, exposure_s, depth, K)
    elif count > 1:
        poses = exposure_poses(exposure[0], exposure[1], count)
        blurred, _ = _render_mean(poses, K, config.width, config.height, config.seed, config.scene)
    rng = np.random.default_rng([config.seed, index, 0xDE97])
    raw = encode_depth(sensor_depth(depth, config, rng), config.depth_scale)
    return FrameImages(blurred, sharp, raw), FrameStats(count, smear_mean, smear_max)


def _rolling_shutter_frame(config: SynthConfig, t: float, exposure_s: float, depth: np.ndarray,
                           K: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(blurred colour, depth, sharp renders made) of the frame at time ``t`` through a rolling shutter (module
    docstring): renders spaced under SUBFRAME_STEP_PX over the readout and exposure, each standing for the
    time around it; a row averages them weighted by how much of that time lies in its exposure, and takes its
    depth from the render nearest its mid-exposure. An instant exposure renders each row at its own time."""
    path = _camera_path(config)
    h, w = config.height, config.width
    readout = config.readout_ms / 1000.0
    centres = t + readout * ((np.arange(h) + 0.5) / h - 0.5)
    times, weights = centres, np.eye(h)  # (renders,), (renders, rows)
    if exposure_s > 0:
        first, last = t - 0.5 * (readout + exposure_s), t + 0.5 * (readout + exposure_s)
        _, span_max = exposure_smear(depth, K, path(t), path(first), path(last))
        times = np.linspace(first, last, subframe_count(span_max))
        half = 0.5 * (times[1] - times[0])
        lo = np.maximum(times[:, None] - half, centres[None] - 0.5 * exposure_s)
        hi = np.minimum(times[:, None] + half, centres[None] + 0.5 * exposure_s)
        weights = np.maximum(hi - lo, 0.0)
    nearest = np.abs(times[:, None] - centres[None]).argmin(axis=0)
    total, rows_depth = np.zeros((h, w, 3)), np.zeros((h, w))
    for j, time in enumerate(times):
        if not (weights[j].any() or (nearest == j).any()):
            continue
        rgb, z = _render_mean([path(time)], K, w, h, config.seed, config.scene)
        total += weights[j][:, None, None] * rgb
        rows_depth[nearest == j] = z[nearest == j]
    blurred = total / weights.sum(axis=0)[:, None, None]
    return blurred.astype(np.float32), rows_depth.astype(np.float32), len(times)


def _write_frame(out_dir: Path, index: int, frame: FrameImages) -> None:
    name = f"{index:06d}.png"
    write_png(out_dir / "rgb" / name, to_uint8(frame.blurred))
    write_png(out_dir / "sharp" / name, to_uint8(frame.sharp))
    write_png(out_dir / "depth" / name, frame.depth_raw)


def _pose_fields(T: np.ndarray) -> str:
    """``tx ty tz qx qy qz qw`` of a pose, as in a TUM line."""
    return format_tum([0.0], [T]).split(maxsplit=1)[1].strip()


def _write_tables(
    out_dir: Path, config: SynthConfig, timestamps: np.ndarray, mids: np.ndarray, exposure: np.ndarray
) -> None:
    """intrinsics.json, frames.txt, groundtruth.txt and exposure.txt."""
    K = camera_matrix(config)
    intrinsics = Intrinsics(config.width, config.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2], config.depth_scale)
    # with a rolling shutter's readout (above 0), which the fast preset's camera_readout takes
    write_text(out_dir / "intrinsics.json", intrinsics.to_json(config.readout_ms))
    frames = ["# timestamp rgb depth"]
    frames += [f"{t:.6f} rgb/{i:06d}.png depth/{i:06d}.png" for i, t in enumerate(timestamps)]
    write_text(out_dir / "frames.txt", "\n".join(frames) + "\n")
    write_tum(out_dir / "groundtruth.txt", timestamps, mids, header="timestamp tx ty tz qx qy qz qw")
    lines = ["# timestamp start(tx ty tz qx qy qz qw) end(tx ty tz qx qy qz qw)"]
    lines += [f"{t:.6f} {_pose_fields(s)} {_pose_fields(e)}" for t, (s, e) in zip(timestamps, exposure)]
    write_text(out_dir / "exposure.txt", "\n".join(lines) + "\n")


def _write_summary(out_dir: Path, config: SynthConfig, fraction: float, frames: list[FrameStats]) -> None:
    """synth.json: the config, generator version, sub-frame counts and measured smear."""
    summary = {
        "generator": "taichi_gs.synth",
        "generator_version": GENERATOR_VERSION,
        "package_version": __version__,
        "config": dataclasses.asdict(config),
        "exposure_fraction": fraction,
        "subframes": [f.subframes for f in frames],
        "smear_px": {
            "mean": float(np.mean([f.smear_mean_px for f in frames])),
            "max": float(np.max([f.smear_max_px for f in frames])),
            "per_frame_mean": [round(f.smear_mean_px, 3) for f in frames],
        },
        "depth_model": {
            "noise_sigma_m": f"{DEPTH_NOISE_QUADRATIC} * z^2" if config.depth_noise else None,
            "max_range_m": MAX_RANGE_M if config.holes else None,
        },
    }
    write_text(out_dir / "synth.json", jsonout.dumps(summary, indent=2) + "\n")


def generate(config: SynthConfig, out_dir: Path, progress: Callable[[int, int], None] | None = None) -> Path:
    """Render a sequence into ``out_dir`` (layout in :mod:`taichi_gs.io.sequence`) and return it."""
    out_dir = Path(out_dir)
    timestamps, mids, exposure, fraction = _sequence_poses(config)
    stats = []
    for i in range(config.frames):
        images, frame_stats = render_frame(config, i, mids[i], exposure[i], fraction / config.fps)
        _write_frame(out_dir, i, images)
        stats.append(frame_stats)
        if progress is not None:
            progress(i + 1, config.frames)
    _write_tables(out_dir, config, timestamps, mids, exposure)
    _write_summary(out_dir, config, fraction, stats)
    return out_dir
