"""TUM RGB-D (rgb.txt, depth.txt, groundtruth.txt) with the published Freiburg 1/2/3 calibrations.

The camera comes from ``--camera fr1|fr2|fr3``, else from intrinsics.json or the --fx/--fy/--cx/--cy
flags (then no undistortion), else from the folder name (``rgbd_dataset_freiburg1_...``). A built-in
camera's lens distortion is removed as frames are read: colour bilinearly, depth by nearest
neighbour (TUM's depth is registered to the colour camera). Depth PNGs hold 5000 units per metre.
A built-in camera's numbers are for 640x480 frames: frames of another size are refused unless the
flags give all four.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from ..sequence import IntrinsicsOverride, Sequence, _open_tum_layout
from ..transforms import Undistort, then
from .common import ReadOptions, check_published_size, json_keys

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
