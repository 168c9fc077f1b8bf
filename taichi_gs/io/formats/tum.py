"""TUM RGB-D (rgb.txt, depth.txt, groundtruth.txt) with the published Freiburg 1/2/3 calibrations.

The camera comes from ``--camera fr1|fr2|fr3``, else from intrinsics.json or the --fx/--fy/--cx/--cy
flags (then no undistortion), else from the folder name (``rgbd_dataset_freiburg1_...``). A built-in
camera's lens distortion is removed as frames are read: colour bilinearly, depth by nearest
neighbour (TUM's depth is registered to the colour camera). Depth PNGs hold 5000 units per metre.
``rgb.txt`` and ``depth.txt`` list "timestamp filename" per frame; colour and depth are associated by nearest
timestamp as TUM's associate.py does (:func:`associate`), kept on one side of each other (:func:`typical_offsets`).
A built-in camera's numbers are for 640x480 frames: frames of another size are refused unless the
flags give all four.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import IntrinsicsOverride, Sequence
from ..transforms import Undistort, then
from .common import (
    ReadOptions,
    check_increasing,
    check_published_size,
    ground_truth,
    json_keys,
    listed_file,
    read_list,
    resolve_intrinsics,
)

NAME = "tum"
# [ours] Seconds by which a Freiburg 1 depth frame's stamp trails the moment its depth shows, measured on fr1_rpy:
# depth edges sit where the colour frame saw them about 15 ms before the depth stamp
# (docs/notebook/benchmarks-2026-11.md, "TUM's depth frames show an earlier moment than their stamps"). Colour frames
# are paired with depth stamps minus it, so where the two streams run half a frame apart a colour frame takes the
# depth frame after it, not the one before.
# fr2 and fr3 are not measured and keep 0.
FR1_DEPTH_LATENCY_S = 0.015
# https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats#intrinsic_camera_calibration_of_the_kinect
CAMERAS: dict[str, dict[str, object]] = {
    "fr1": {"fx": 517.3, "fy": 516.5, "cx": 318.6, "cy": 255.3, "distortion": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
            "depth_latency_s": FR1_DEPTH_LATENCY_S},
    "fr2": {"fx": 520.9, "fy": 521.0, "cx": 325.1, "cy": 249.7, "distortion": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)},
    "fr3": {"fx": 535.4, "fy": 539.2, "cx": 320.1, "cy": 247.6, "distortion": (0.0, 0.0, 0.0, 0.0, 0.0)},
}
PUBLISHED_SIZE = (640, 480)  # the frames the Freiburg calibrations are for
PINHOLE = ("fx", "fy", "cx", "cy")
# Closest-first matches around a frame whose median offset says which side its depth frame should be on.
OFFSET_WINDOW = 31


def detect(root: Path) -> bool:
    return (root / "rgb.txt").is_file() or (root / "depth.txt").is_file()


def camera_from_name(root: Path) -> str | None:
    """fr1/fr2/fr3 from a folder name such as rgbd_dataset_freiburg2_desk or fr3_office."""
    match = re.search(r"(?:freiburg|fr)([123])(?![0-9])", root.resolve().name.lower())
    return f"fr{match.group(1)}" if match else None


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    flags = options.override.values()
    camera = options.camera
    if camera is not None and camera not in CAMERAS:
        raise InputError(root, f"unknown --camera {camera!r}", f"use one of {', '.join(CAMERAS)}")
    given = json_keys(root / "intrinsics.json") | set(flags)
    if camera is None and not all(k in given for k in PINHOLE):
        camera = camera_from_name(root)
        if camera is None and not any(k in given for k in PINHOLE):
            raise InputError(root / "intrinsics.json", "no intrinsics: not in the folder, no flags, and the folder name "
                             "names no Freiburg camera", "pass --camera fr1|fr2|fr3, write intrinsics.json, or pass --fx --fy --cx --cy")
    override = options.override
    if camera is not None:
        values = {k: float(v) for k, v in CAMERAS[camera].items() if k in PINHOLE}
        override = IntrinsicsOverride(**{**values, **flags})
    latency = options.depth_latency
    if latency is None:
        latency = float(CAMERAS[camera].get("depth_latency_s", 0.0)) if camera is not None else 0.0
    sequence = _open_tum_layout(root, override, options.max_time_difference, latency)
    if camera is not None and not all(k in flags for k in PINHOLE):
        check_published_size(sequence.rgb_paths[0], sequence.intrinsics, f"the {camera} camera", PUBLISHED_SIZE,
                             "give this size's camera in intrinsics.json (without --camera) or with --fx --fy --cx --cy")
    if camera is not None:
        distortion = np.array(CAMERAS[camera]["distortion"], dtype=float)
        intr = sequence.intrinsics
        if np.any(distortion != 0):
            sequence.transform = then(sequence.transform, Undistort(intr.K(), distortion, intr.width, intr.height))
        sequence.source = {**sequence.source, "camera": camera}
    if latency:
        sequence.source = {**sequence.source, "depth_latency_s": latency}
    return sequence


def _open_tum_layout(root: Path, override: IntrinsicsOverride, max_difference: float,
                     depth_latency: float = 0.0) -> Sequence:
    """A TUM folder's colour frames, each with a depth frame (see :func:`associate` and :func:`typical_offsets`).
    ``depth_latency``: seconds by which a depth frame's stamp trails the moment its depth shows; colour stamps are
    matched with depth stamps minus it."""
    rgb_list, depth_list = root / "rgb.txt", root / "depth.txt"
    for path in (rgb_list, depth_list):
        if not path.is_file():
            raise InputError(path, "file list missing", "a TUM folder needs both rgb.txt and depth.txt")
    rgb_rows = read_list(rgb_list, columns=2)
    depth_rows = read_list(depth_list, columns=2)
    rgb_times = np.array([float(r[0]) for r in rgb_rows])
    depth_times = np.array([float(r[0]) for r in depth_rows])
    check_increasing(rgb_list, rgb_times)
    check_increasing(depth_list, depth_times)
    depth_times = depth_times - depth_latency
    matches = associate(rgb_times, depth_times, max_difference)
    if matches:
        matches = associate(rgb_times, depth_times, max_difference, typical_offsets(rgb_times, depth_times, matches))
    if not matches:
        raise InputError(rgb_list, f"no colour frame has a depth frame within {max_difference} s",
                         "check that rgb.txt and depth.txt share a clock, or raise --time-tolerance (seconds)")
    timestamps = np.array([rgb_times[i] for i, _ in matches])
    rgb_paths = [listed_file(root, rgb_rows[i][1], rgb_list) for i, _ in matches]
    depth_paths = [listed_file(root, depth_rows[j][1], depth_list) for _, j in matches]
    intrinsics = resolve_intrinsics(root, override, rgb_paths[0])
    return Sequence(root, NAME, intrinsics, timestamps, rgb_paths, depth_paths,
                    gt_poses=ground_truth(root / "groundtruth.txt", timestamps),
                    depth_timestamps=np.array([depth_times[j] for _, j in matches]))


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
