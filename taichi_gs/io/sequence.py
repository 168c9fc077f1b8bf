"""RGB-D sequences read lazily, frame by frame, from the TUM layout or taichi-gs's own layout.

Own layout (written by ``taichi-gs synth``)::

    SEQ/intrinsics.json   {"width", "height", "fx", "fy", "cx", "cy", "depth_scale"}, and "depth_camera" for
                          depth from its own camera, registered as it is read (``io.registration``), and
                          "readout_ms" for a colour camera with a rolling shutter (``rolling_shutter``;
                          ``Sequence.source["readout_ms"]``, what ``camera_readout`` takes)
    SEQ/frames.txt        "timestamp rgb/NAME.png depth/NAME.png" per frame
    SEQ/groundtruth.txt   optional TUM trajectory (camera-to-world), matched to frames by time
    SEQ/exposure.txt      optional "timestamp" + start and end pose (tx ty tz qx qy qz qw each)
    SEQ/sharp/NAME.png    optional sharp mid-exposure colour, same stem as the rgb file
    SEQ/sourced.png       optional 8-bit mask, 255 where a colour pixel came from camera pixels (what
                          ``import`` writes for frames that had an unsourced border, e.g. undistorted ones)

TUM layout: ``rgb.txt`` and ``depth.txt`` ("timestamp filename"), optional ``groundtruth.txt``;
colour and depth associated by nearest timestamp as TUM's associate.py does.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..errors import InputError
from ..geometry import intrinsics_matrix, pose_from_rt, quat_to_rotmat, rotmat_to_quat
from .registration import RegisterDepth, depth_camera_in, intrinsics_entry
from .trajectory import read_tum_rows, tum_rows_to_poses
from . import jsonout
from .transforms import FrameTransform

MAX_TIME_DIFFERENCE = 0.02  # seconds, TUM associate.py's default
MEDIAN_DEPTH_RANGE = (0.1, 100.0)  # metres: outside it the depth scale is surely wrong
INDOOR_MEDIAN_DEPTH = (0.25, 6.0)  # metres: indoor RGB-D sensors; outside it the scale is likely wrong
COMMON_DEPTH_SCALES = (1000.0, 5000.0, 6553.5, 4000.0, 10000.0, 1.0)  # mm, TUM, Replica, RealSense, ...
READOUT_KEY = "readout_ms"  # intrinsics.json: the colour camera's rolling-shutter readout (ms; 0: a global shutter)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics (OpenCV pixel convention) and the depth PNG scale (units per metre)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    depth_scale: float = 5000.0

    def K(self) -> np.ndarray:
        """3x3 intrinsics matrix."""
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)

    def to_json(self, readout_ms: float = 0.0) -> str:
        """intrinsics.json's text; a rolling shutter's ``readout_ms`` (above 0) as :data:`READOUT_KEY`."""
        values = {**asdict(self), READOUT_KEY: readout_ms} if readout_ms > 0 else asdict(self)
        return jsonout.dumps(values, indent=2) + "\n"


@dataclass(frozen=True)
class IntrinsicsOverride:
    """Values given on the command line; each one set wins over intrinsics.json."""

    fx: float | None = None
    fy: float | None = None
    cx: float | None = None
    cy: float | None = None
    depth_scale: float | None = None

    def values(self) -> dict[str, float]:
        return {k: v for k, v in asdict(self).items() if v is not None}


SOURCED = 0.999  # share of a pixel that must come from camera pixels for it to count as seen


class Sequence:
    """An RGB-D sequence whose frames are read on demand.

    Attributes: ``root``, ``layout`` ("tum" or "taichi-gs"), ``intrinsics``, ``timestamps`` (N,),
    ``rgb_paths``, ``depth_paths``, ``names`` (colour file stems), ``gt_poses`` (N x 4 x 4
    camera-to-world, NaN where ground truth does not cover a frame, or None), ``exposure_poses``
    (N x 2 x 4 x 4 start/end, or None), ``sharp_paths`` (or None), ``sourced_path`` (the own layout's
    ``sourced.png``, or None), ``transform`` (applied to each
    frame as it is read: resampling, undistortion, masking; see ``io.transforms``), ``source``
    (how it was read: format, every, scale, camera) and ``load_options`` (the arguments of
    :func:`load_sequence`, recorded in a run's run.json so later commands reopen it the same way).
    """

    def __init__(
        self,
        root: Path,
        layout: str,
        intrinsics: Intrinsics,
        timestamps: np.ndarray,
        rgb_paths: list[Path],
        depth_paths: list[Path],
        gt_poses: np.ndarray | None = None,
        exposure_poses: np.ndarray | None = None,
        sharp_paths: list[Path] | None = None,
        names: list[str] | None = None,
        transform: FrameTransform | None = None,
        sourced_path: Path | None = None,
    ):
        self.root = root
        self.layout = layout
        self.intrinsics = intrinsics
        self.timestamps = timestamps
        self.rgb_paths = rgb_paths
        self.depth_paths = depth_paths
        self.names = names if names is not None else [p.stem for p in rgb_paths]
        self.gt_poses = gt_poses
        self.exposure_poses = exposure_poses
        self.sharp_paths = sharp_paths
        self.transform = transform
        self.sourced_path = sourced_path
        self.source: dict[str, object] = {"format": layout, "every": 1, "scale": 1.0}
        self.load_options: dict[str, Any] = {}

    def __len__(self) -> int:
        return len(self.rgb_paths)

    def K(self) -> np.ndarray:
        return self.intrinsics.K()

    def color(self, i: int) -> np.ndarray:
        """Blurred colour of frame i, float32 H x W x 3 in [0, 1]."""
        return self._checked_color(self.rgb_paths[i])

    def sharp(self, i: int) -> np.ndarray:
        """Sharp ground-truth colour of frame i (synthetic sequences only)."""
        if self.sharp_paths is None:
            raise InputError(self.root, "sequence has no sharp ground-truth images", "use a sequence made by 'taichi-gs synth'")
        return self._checked_color(self.sharp_paths[i])

    def depth(self, i: int) -> np.ndarray:
        """Depth of frame i in metres, float32 H x W, 0 where invalid."""
        path = self.depth_paths[i]
        depth = read_depth(path, self.intrinsics.depth_scale)
        if self.transform is not None:
            depth = self.transform.depth(path, depth)
        self._check_size(path, depth.shape[:2], "depth")
        return depth

    def sourced_pixels(self) -> np.ndarray:
        """Boolean H x W: the colour pixels made wholly from camera pixels. False only where a transform
        had no source (e.g. the border of an undistorted frame, which OpenCV fills by replicating the
        edge), or where the own layout's ``sourced.png`` says so. [ours] eval's real-data figures count
        these pixels only, and so do stage 3's photometric losses with ``[deblur] sourced_pixels_only``."""
        h, w = self.intrinsics.height, self.intrinsics.width
        if not self.rgb_paths or (self.transform is None and self.sourced_path is None):
            return np.ones((h, w), bool)
        raw = read_color(self.rgb_paths[0]).shape[:2]
        share = np.ones(raw, np.float32) if self.sourced_path is None else self._stored_sourced(raw)
        if self.transform is not None:
            share = self.transform.sourced(share)
        self._check_size(self.rgb_paths[0], share.shape[:2], "colour")
        return share >= SOURCED

    def _stored_sourced(self, raw: tuple[int, int]) -> np.ndarray:
        """The own layout's ``sourced.png`` as a 0/1 float32 share on the frames' grid."""
        path = self.sourced_path
        mask = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if mask is None or mask.ndim != 2:
            raise InputError(path, "unreadable or not a single-channel mask",
                             "restore it (255 where a pixel came from the camera), or delete it to count every pixel")
        if mask.shape != raw:
            raise InputError(path, f"mask is {mask.shape[1]}x{mask.shape[0]}, the colour frames {raw[1]}x{raw[0]}",
                             "give a mask at the colour frames' size, or delete it to count every pixel")
        return (mask >= 128).astype(np.float32)

    def check_all(self) -> None:
        """Read every frame once, so corrupt files fail now rather than mid-stage."""
        for i in range(len(self)):
            self.color(i)
            self.depth(i)

    def _checked_color(self, path: Path) -> np.ndarray:
        color = read_color(path)
        if self.transform is not None:
            color = self.transform.color(path, color)
        self._check_size(path, color.shape[:2], "colour")
        return color

    def _check_size(self, path: Path, shape: tuple[int, int], what: str) -> None:
        h, w = shape
        if (w, h) != (self.intrinsics.width, self.intrinsics.height):
            raise InputError(
                path,
                f"{what} image is {w}x{h} but the intrinsics say {self.intrinsics.width}x{self.intrinsics.height}",
                "give colour and depth at the same resolution as intrinsics.json (align depth to colour first)",
            )


def read_color(path: Path) -> np.ndarray:
    """Colour image as float32 H x W x 3 RGB in [0, 1] (8- or 16-bit, grey, RGB or RGBA)."""
    image = _imread(path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=2)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    scale = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(image.dtype)
    if scale is None:
        raise InputError(path, f"colour image has unsupported type {image.dtype}", "save colour as 8- or 16-bit PNG or JPEG")
    return image.astype(np.float32) / np.float32(scale)


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """Depth in metres from a 16-bit PNG (value / depth_scale), or a float ``.npy`` or 32-bit float
    TIFF in metres (NaN or inf in a float TIFF count as invalid, 0)."""
    if path.suffix == ".npy":
        depth = _load_npy(path)
    else:
        raw = _imread(path)
        if raw.ndim == 2 and raw.dtype in (np.float32, np.float64):
            depth = np.nan_to_num(raw.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
        elif raw.dtype != np.uint16 or raw.ndim != 2:
            kind = f"{raw.dtype}, {raw.shape[2] if raw.ndim == 3 else 1} channel(s)"
            raise InputError(path, f"depth must be a 16-bit single-channel PNG, got {kind}",
                             "save depth as uint16 PNG (value = metres x depth_scale)")
        else:
            depth = raw.astype(np.float32) / np.float32(depth_scale)
    if not np.all(np.isfinite(depth)):
        raise InputError(path, "depth contains NaN or inf", "write 0 for invalid depth")
    if np.any(depth < 0):
        raise InputError(path, "depth contains negative values", "write 0 for invalid depth")
    return depth


def _load_npy(path: Path) -> np.ndarray:
    try:
        depth = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise InputError(path, f"cannot read depth array ({err})", "write depth as a float32 .npy in metres") from None
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise InputError(path, f"depth array has shape {depth.shape} and type {depth.dtype}",
                         "write an H x W float array in metres")
    return depth.astype(np.float32)


def _imread(path: Path) -> np.ndarray:
    if not path.is_file():
        raise InputError(path, "image file not found", "restore the file or remove its line from the frame list")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None or image.size == 0:
        raise InputError(path, "image is unreadable or corrupt", "re-export the image as PNG or JPEG")
    return image


def load_sequence(
    folder: str | Path,
    override: IntrinsicsOverride | None = None,
    max_time_difference: float | None = None,
    trust_depth_scale: bool = False,
    *,
    format: str | None = None,
    camera: str | None = None,
    every: int = 1,
    scale: float = 1.0,
    first: int = 0,
    count: int = 0,
    depth_latency: float | None = None,
) -> Sequence:
    """Open a sequence folder in any known layout (detected, or ``format``; see ``io.formats``),
    keep every ``every``-th frame from frame ``first`` on (``count`` of them; 0: all), read at
    ``scale`` times the size; checks lists, files, intrinsics and depth scale. ``depth_latency``: TUM layout,
    seconds by which depth stamps trail what they show (None: the named camera's; see ``io.formats.tum``).

    The median valid depth must look like an indoor RGB-D capture (0.25-6 m), which catches the usual
    depth-scale mix-ups (1000 for 5000); ``trust_depth_scale`` relaxes that to 0.1-100 m for scenes
    that really are that close or far. The call's arguments are kept in ``sequence.load_options``.
    """
    from .formats import ReadOptions, open_format
    from .transforms import rescale, subsample

    root = Path(folder)
    max_time_difference = MAX_TIME_DIFFERENCE if max_time_difference is None else max_time_difference
    if not root.is_dir():
        raise InputError(root, "sequence folder not found", "give the folder holding the sequence (see README 'Input formats')")
    if every < 1:
        raise InputError(None, f"--every {every} is not a positive integer", "e.g. --every 2 keeps every second frame")
    if not (math.isfinite(scale) and 0.0 < scale <= 4.0):
        raise InputError(None, f"--scale {scale} is not in (0, 4]", "e.g. --scale 0.5 for half width and height")
    if first < 0 or count < 0:
        raise InputError(None, f"--first {first} / --count {count} is negative", "e.g. --first 100 --count 40")
    options = ReadOptions(override or IntrinsicsOverride(), camera, max_time_difference, depth_latency)
    listed = open_format(root, options, format)
    if first >= len(listed):
        raise InputError(listed.root, f"--first {first} is past the last of the sequence's {len(listed)} frames",
                         f"give --first below {len(listed)} (frames count from 0)")
    sequence = rescale(subsample(listed, every, first, count), scale)
    if options.override.values():
        sequence.source = {**sequence.source, "intrinsics": options.override.values()}
    if len(sequence) < 2:
        raise InputError(sequence.root, f"sequence has {len(sequence)} frame(s)", "give at least 2 frames")
    _check_depth_scale(sequence, trust_depth_scale)
    sequence.load_options = {"override": options.override.values(), "max_time_difference": max_time_difference,
                             "trust_depth_scale": trust_depth_scale, "format": sequence.source["format"],
                             "camera": sequence.source.get("camera"), "every": every, "scale": scale,
                             "first": first, "count": count}
    if sequence.source.get("depth_latency_s"):  # only then: older records, without it, keep their fingerprints
        sequence.load_options["depth_latency"] = sequence.source["depth_latency_s"]
    return sequence


def _open_own_layout(root: Path, override: IntrinsicsOverride) -> Sequence:
    list_path = root / "frames.txt"
    rows = _read_list(list_path, columns=3)
    timestamps = np.array([float(r[0]) for r in rows])
    _check_increasing(list_path, timestamps)
    rgb_paths = [_listed_file(root, r[1], list_path) for r in rows]
    depth_paths = [_listed_file(root, r[2], list_path) for r in rows]
    intrinsics = _resolve_intrinsics(root, override, rgb_paths[0])
    sharp_dir = root / "sharp"
    sharp_paths = None
    if sharp_dir.is_dir():
        sharp_paths = [sharp_dir / p.name for p in rgb_paths]
        missing = [p for p in sharp_paths if not p.is_file()]
        if missing:
            raise InputError(missing[0], "sharp image missing", "restore it or remove the sharp/ folder")
    sourced = root / "sourced.png"
    depth_camera = depth_camera_in(root / "intrinsics.json")
    sequence = Sequence(
        root, "taichi-gs", intrinsics, timestamps, rgb_paths, depth_paths,
        gt_poses=_ground_truth(root / "groundtruth.txt", timestamps),
        exposure_poses=read_exposure(root / "exposure.txt", timestamps),
        sharp_paths=sharp_paths, sourced_path=sourced if sourced.is_file() else None,
        transform=None if depth_camera is None else RegisterDepth(depth_camera, intrinsics.K(), intrinsics.width,
                                                                   intrinsics.height),
    )
    readout_ms = readout_in(root / "intrinsics.json")
    if readout_ms is not None:
        sequence.source = {**sequence.source, READOUT_KEY: readout_ms}
    return sequence


def readout_in(json_path: Path) -> float | None:
    """The ``readout_ms`` entry of an own layout's intrinsics.json (None without the file or the entry)."""
    entry = intrinsics_entry(json_path, READOUT_KEY)
    if entry is None:
        return None
    try:
        readout_ms = float(entry)
    except (TypeError, ValueError):
        readout_ms = math.nan
    if not (math.isfinite(readout_ms) and 0.0 <= readout_ms < 1000.0):
        raise InputError(json_path, f"{READOUT_KEY} {entry!r} is not a readout in milliseconds",
                         f'write "{READOUT_KEY}": the ms the camera takes to read its rows top to bottom '
                         "(0: a global shutter), or leave it out")
    return readout_ms


# Closest-first matches around a frame whose median offset says which side its depth frame should be on.
OFFSET_WINDOW = 31


def _open_tum_layout(root: Path, override: IntrinsicsOverride, max_difference: float,
                     depth_latency: float = 0.0) -> Sequence:
    """A TUM folder's colour frames, each with a depth frame (see :func:`associate` and :func:`typical_offsets`).
    ``depth_latency``: seconds by which a depth frame's stamp trails the moment its depth shows; colour stamps are
    matched with depth stamps minus it."""
    rgb_list, depth_list = root / "rgb.txt", root / "depth.txt"
    for path in (rgb_list, depth_list):
        if not path.is_file():
            raise InputError(path, "file list missing", "a TUM folder needs both rgb.txt and depth.txt")
    rgb_rows = _read_list(rgb_list, columns=2)
    depth_rows = _read_list(depth_list, columns=2)
    rgb_times = np.array([float(r[0]) for r in rgb_rows])
    depth_times = np.array([float(r[0]) for r in depth_rows])
    _check_increasing(rgb_list, rgb_times)
    _check_increasing(depth_list, depth_times)
    depth_times = depth_times - depth_latency
    matches = associate(rgb_times, depth_times, max_difference)
    if matches:
        matches = associate(rgb_times, depth_times, max_difference, typical_offsets(rgb_times, depth_times, matches))
    if not matches:
        raise InputError(rgb_list, f"no colour frame has a depth frame within {max_difference} s",
                         "check that rgb.txt and depth.txt share a clock, or raise --time-tolerance (seconds)")
    timestamps = np.array([rgb_times[i] for i, _ in matches])
    rgb_paths = [_listed_file(root, rgb_rows[i][1], rgb_list) for i, _ in matches]
    depth_paths = [_listed_file(root, depth_rows[j][1], depth_list) for _, j in matches]
    intrinsics = _resolve_intrinsics(root, override, rgb_paths[0])
    return Sequence(root, "tum", intrinsics, timestamps, rgb_paths, depth_paths,
                    gt_poses=_ground_truth(root / "groundtruth.txt", timestamps))


def associate(first: np.ndarray, second: np.ndarray, max_difference: float,
              offsets: np.ndarray | None = None) -> list[tuple[int, int]]:
    """Pair timestamps as TUM's associate.py does: closest pairs first, each stamp used once, at most
    ``max_difference`` apart. With ``offsets`` (one per first stamp), "closest" means closest to
    ``first + offsets``.

    Returns (index in first, index in second) pairs sorted by the first stamp.
    """
    shifted = first if offsets is None else first + offsets
    candidates = []
    for i, a in enumerate(first):
        lo = np.searchsorted(second, a - max_difference, side="left")
        hi = np.searchsorted(second, a + max_difference, side="right")
        candidates.extend((abs(shifted[i] - second[j]), i, j) for j in range(lo, hi))
    candidates.sort()
    used_first, used_second, matches = set(), set(), []
    for _, i, j in candidates:
        if i not in used_first and j not in used_second:
            used_first.add(i)
            used_second.add(j)
            matches.append((i, j))
    return sorted(matches)


def typical_offsets(first: np.ndarray, second: np.ndarray, matches: list[tuple[int, int]],
                    window: int = OFFSET_WINDOW) -> np.ndarray:
    """[ours] Per first stamp, the median of ``second - first`` over the ``window`` closest-first ``matches``
    around it: the two streams' local phase offset (it drifts along a recording).

    Pairing again closest to it keeps each depth frame on one side of its colour frame. Kinect v1 streams in
    TUM fr1 run at one rate about half a frame apart (depth ~15 ms before and ~15 ms after each colour frame),
    so closest-first pairing flips between the frame before and the frame after; consecutive depth frames are
    then 0.5-2x the colour frames' interval apart, and motion measured on depth is off by as much.
    Synchronised streams have offsets near 0 and keep their pairs.
    """
    offsets = np.array([second[j] - first[i] for i, j in matches])
    at = np.minimum(np.searchsorted([i for i, _ in matches], np.arange(len(first))), len(matches) - 1)
    half = window // 2
    return np.array([np.median(offsets[max(0, k - half): k + half + 1]) for k in at])


def _read_text(path: Path) -> str:
    """A list file's text (UTF-8), or a one-line error."""
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError as err:
        raise InputError(path, f"not UTF-8 text (byte {err.start})", "save the list as plain UTF-8 text") from None
    except OSError as err:
        raise InputError(path, f"cannot read ({err.strerror})", "check the file's permissions") from None


def _read_list(path: Path, columns: int) -> list[list[str]]:
    rows = []
    for n, line in enumerate(_read_text(path).splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) < columns:
            raise InputError(path, f"line {n} has {len(parts)} fields, expected {columns}",
                             "write 'timestamp file' per line (frames.txt: 'timestamp rgb depth')")
        try:
            stamp = float(parts[0])
        except ValueError:
            raise InputError(path, f"line {n}: timestamp {parts[0]!r} is not a number", "fix the timestamp") from None
        if not math.isfinite(stamp):
            raise InputError(path, f"line {n}: timestamp is NaN or inf", "fix the timestamp")
        rows.append(parts[:columns])
    if not rows:
        raise InputError(path, "lists no frames", "add one line per frame")
    return rows


def _check_increasing(path: Path, timestamps: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(timestamps) <= 0)
    if bad.size:
        k = int(bad[0])
        raise InputError(path, f"timestamps not increasing at entry {k + 2} ({timestamps[k]:.6f} then {timestamps[k + 1]:.6f})",
                         "sort the list by time and remove duplicate frames")


def _listed_file(root: Path, name: str, list_path: Path) -> Path:
    path = root / name
    if not path.is_file():
        raise InputError(path, f"listed in {list_path.name} but missing",
                         f"restore the frame or remove its line from {list_path.name}")
    return path


def _resolve_intrinsics(root: Path, override: IntrinsicsOverride, first_rgb: Path) -> Intrinsics:
    json_path = root / "intrinsics.json"
    values: dict[str, float] = {}
    if json_path.is_file():
        try:
            values = json.loads(_read_text(json_path))
        except json.JSONDecodeError as err:
            raise InputError(json_path, f"not valid JSON ({err.msg} at line {err.lineno})", "fix the JSON syntax") from None
        if not isinstance(values, dict):
            raise InputError(json_path, "must hold a JSON object", 'write {"width", "height", "fx", "fy", "cx", "cy", "depth_scale"}')
    values = {**values, **override.values()}
    missing = [k for k in ("fx", "fy", "cx", "cy") if k not in values]
    if missing:
        raise InputError(json_path, f"intrinsics {', '.join(missing)} not given",
                         "write intrinsics.json beside the data or pass --fx --fy --cx --cy")
    height, width = _imread(first_rgb).shape[:2]
    values.setdefault("width", width)
    values.setdefault("height", height)
    values.setdefault("depth_scale", 5000.0)
    try:
        intrinsics = Intrinsics(
            width=int(values["width"]), height=int(values["height"]),
            fx=float(values["fx"]), fy=float(values["fy"]), cx=float(values["cx"]), cy=float(values["cy"]),
            depth_scale=float(values["depth_scale"]),
        )
    except (TypeError, ValueError) as err:
        raise InputError(json_path, f"intrinsics are not numbers ({err})", "write plain numbers") from None
    numbers = [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, intrinsics.depth_scale]
    if not all(math.isfinite(v) for v in numbers) or min(intrinsics.fx, intrinsics.fy, intrinsics.depth_scale) <= 0:
        raise InputError(json_path, "fx, fy and depth_scale must be finite and positive, cx and cy finite",
                         "fix intrinsics.json or the --fx/--fy/--cx/--cy/--depth-scale flags")
    if (intrinsics.width, intrinsics.height) != (width, height):
        raise InputError(first_rgb, f"image is {width}x{height} but intrinsics say {intrinsics.width}x{intrinsics.height}",
                         "fix width/height in intrinsics.json")
    return intrinsics


def _check_depth_scale(sequence: Sequence, trusted: bool) -> None:
    """Median valid depth over a few frames must be plausible, or the scale is wrong."""
    picks = np.unique(np.linspace(0, len(sequence) - 1, num=min(5, len(sequence))).astype(int))
    depths = [sequence.depth(int(i)) for i in picks]
    valid = np.concatenate([d[d > 0] for d in depths])
    where = sequence.depth_paths[int(picks[0])]
    if valid.size == 0:
        raise InputError(where, "no valid depth in the sampled frames", "check the depth files (0 means invalid)")
    median = float(np.median(valid))
    lo, hi = MEDIAN_DEPTH_RANGE if trusted else INDOOR_MEDIAN_DEPTH
    if lo <= median <= hi:
        return
    scale = sequence.intrinsics.depth_scale
    raw = median * scale
    likely = min(COMMON_DEPTH_SCALES, key=lambda s: abs(np.log(raw / s / 2.0)))
    fix = f"the data look like --depth-scale {likely:g} (median {raw / likely:.2f} m)"
    if not trusted:
        fix += f"; if {median:.3g} m is right, add --trust-depth-scale"
    raise InputError(where, f"median depth is {median:.4g} m with depth_scale {scale:g}, implausible for an RGB-D sensor"
                     f" ({lo}-{hi} m)", fix)


def _ground_truth(path: Path, timestamps: np.ndarray) -> np.ndarray | None:
    """Ground-truth poses interpolated to the frame times (NaN where not covered)."""
    if not path.is_file():
        return None
    rows = read_tum_rows(path)
    order = np.argsort(rows[:, 0])
    rows = rows[order]
    return interpolate_poses(rows[:, 0], tum_rows_to_poses(rows), timestamps, MAX_TIME_DIFFERENCE)


def interpolate_poses(times: np.ndarray, poses: np.ndarray, query: np.ndarray, tolerance: float) -> np.ndarray:
    """Poses at query times: linear in position, slerp in rotation; NaN beyond ``tolerance`` outside."""
    out = np.full((len(query), 4, 4), np.nan)
    for k, t in enumerate(query):
        j = int(np.searchsorted(times, t))
        if j < len(times) and abs(times[j] - t) < 1e-9:
            out[k] = poses[j]
        elif 0 < j < len(times):
            a = (t - times[j - 1]) / (times[j] - times[j - 1])
            out[k] = _blend(poses[j - 1], poses[j], a)
        elif j == 0 and times[0] - t <= tolerance:
            out[k] = poses[0]
        elif j == len(times) and t - times[-1] <= tolerance:
            out[k] = poses[-1]
    return out


def _blend(T0: np.ndarray, T1: np.ndarray, a: float) -> np.ndarray:
    q0, q1 = rotmat_to_quat(T0[:3, :3]), rotmat_to_quat(T1[:3, :3])
    if np.dot(q0, q1) < 0:
        q1 = -q1
    dot = np.clip(np.dot(q0, q1), -1.0, 1.0)
    theta = np.arccos(dot)
    if theta < 1e-8:
        q = q0
    else:
        q = (np.sin((1 - a) * theta) * q0 + np.sin(a * theta) * q1) / np.sin(theta)
    return pose_from_rt(quat_to_rotmat(q), (1 - a) * T0[:3, 3] + a * T1[:3, 3])


def read_exposure(path: Path, timestamps: np.ndarray) -> np.ndarray | None:
    """(N, 2, 4, 4) exposure start and end poses (camera-to-world) per frame from an exposure.txt (a timestamp and
    two TUM poses per line, one line per frame of ``timestamps``); None without the file."""
    if not path.is_file():
        return None
    rows = read_tum_rows(path, columns=15)
    if len(rows) != len(timestamps) or not np.allclose(rows[:, 0], timestamps, atol=1e-6):
        raise InputError(path, f"has {len(rows)} rows not matching the {len(timestamps)} frames' timestamps",
                         "write one 'timestamp start-pose end-pose' line per frame")
    start = tum_rows_to_poses(rows[:, :8])
    end = tum_rows_to_poses(np.concatenate([rows[:, :1], rows[:, 8:15]], axis=1))
    return np.stack([start, end], axis=1)

