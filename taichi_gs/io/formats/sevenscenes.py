"""Microsoft 7-Scenes as distributed: ``frame-NNNNNN.color.png|jpg``, ``.depth.png`` (uint16 mm;
0 and 65535 invalid) and ``.pose.txt`` (camera-to-world 4x4), either flat in the folder or in one
``seq-NN/`` subfolder. Frames are 1/30 s apart. Without pose files the sequence runs without ground truth.

The colour and depth images come from the Kinect's two cameras and are not registered; the dataset
gives one K, ``camera-intrinsics.txt`` (else the published fx = fy = 585, cx = 320, cy = 240), the
depth camera's, and its poses (KinectFusion's) are the depth camera's. ``--camera`` chooses:

- ``registered`` (default): the colour camera as fitted here (0.9 x the depth camera's focal length,
  526.5 px for 585, the same principal point, 2.5 cm from the depth camera along x: depth edges
  reprojected onto colour edges over RedKitchen frames 0, 25, ..., 225 on grids of 5.9 px and 6 mm,
  edge correlation 0.17 -> 0.28;
  docs/notebook/benchmarks-2026-11.md, "Depth-colour registration"); depth is moved into it as it is read
  (``io.registration``) and the poses to it. intrinsics.json and the flags set the colour camera;
  intrinsics.json's ``depth_camera`` replaces the depth camera and its offset.
- ``shipped``: as distributed, colour and depth taken as one camera with the dataset's K (colour
  then sits up to 16 px off its depth at the image edges, and the colour focal length reads 11% long).

The published K is for 640x480 frames: without camera-intrinsics.txt, frames of another size are refused
wherever it would be read (as the colour camera, or as the depth camera registered without depth_camera).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ...errors import InputError
from ...geometry import intrinsics_matrix, pose_from_rt
from ..registration import DepthCamera, RegisterDepth, depth_camera_in
from ..sequence import Intrinsics, Sequence
from ..transforms import DropDepthAbove, then
from .common import (NOMINAL_FPS, ReadOptions, check_published_size, intrinsics_with_defaults, json_keys, numbered,
                     pose_files, read_matrix)

NAME = "7scenes"
COLOR = r"frame-(\d+)\.color\.(?:png|jpg)"
DEFAULTS = {"fx": 585.0, "fy": 585.0, "cx": 320.0, "cy": 240.0, "depth_scale": 1000.0}  # the depth camera's
PUBLISHED_SIZE = (640, 480)  # the frames DEFAULTS are for
PINHOLE = ("fx", "fy", "cx", "cy")
COLOUR_FOCAL_RATIO = 526.5 / 585.0  # the colour camera's focal length over the depth camera's, fitted (module docstring)
COLOUR_FROM_DEPTH = np.array([-0.025, 0.0, 0.0])  # metres: X_colour = X_depth + this
CAMERAS = ("registered", "shipped")
NO_READING = 65535  # depth code for "no reading", besides 0


def _sequence_folders(root: Path) -> list[Path]:
    if not root.is_dir():
        return []
    return sorted(p for p in root.iterdir() if p.is_dir() and re.fullmatch(r"seq-\d+", p.name) and numbered(p, COLOR))


def detect(root: Path) -> bool:
    return bool(numbered(root, COLOR)) or bool(_sequence_folders(root))


def open_sequence(root: Path, options: ReadOptions) -> Sequence:
    folder = root
    if not numbered(root, COLOR):
        folders = _sequence_folders(root)
        if len(folders) != 1:
            names = ", ".join(p.name for p in folders) or "none"
            raise InputError(root, f"holds {len(folders)} 7-Scenes sequences ({names}) and no frames of its own",
                             "give one seq-NN folder (sequences are separate recordings)")
        folder = folders[0]
    colors = numbered(folder, COLOR)
    stems = [p.name.split(".color.")[0] for p in colors.values()]
    depth_paths = [folder / f"{s}.depth.png" for s in stems]
    missing = next((p for p in depth_paths if not p.is_file()), None)
    if missing is not None:
        raise InputError(missing, "depth image missing for its colour frame", "restore it or remove that frame's files")
    camera = options.camera or CAMERAS[0]
    if camera not in CAMERAS:
        raise InputError(root, f"unknown --camera {camera!r} for 7-Scenes", f"use one of {', '.join(CAMERAS)}")
    calibration = _camera_file(folder, root)
    depth_K = {**DEFAULTS, **(calibration or {})}
    rgb_paths = list(colors.values())
    colour_K = {**depth_K, "fx": COLOUR_FOCAL_RATIO * depth_K["fx"], "fy": COLOUR_FOCAL_RATIO * depth_K["fy"]}
    defaults = depth_K if camera == "shipped" else colour_K
    intrinsics = intrinsics_with_defaults(root, options.override, rgb_paths[0], defaults)
    json_depth_camera = depth_camera_in(root / "intrinsics.json") if camera == "registered" else None
    if calibration is None:
        _check_published_camera(root, options, rgb_paths[0], intrinsics, camera == "registered" and json_depth_camera is None)
    timestamps = np.array(list(colors), dtype=float) / NOMINAL_FPS
    gt = pose_files([folder / f"{s}.pose.txt" for s in stems],
                    "restore it, or remove every .pose.txt file to run without ground truth")
    transform = DropDepthAbove((NO_READING - 0.5) / intrinsics.depth_scale)
    if camera == "registered":
        fitted = DepthCamera(intrinsics_matrix(depth_K["fx"], depth_K["fy"], depth_K["cx"], depth_K["cy"]),
                             pose_from_rt(np.eye(3), COLOUR_FROM_DEPTH))
        depth_camera = json_depth_camera or fitted
        transform = then(transform, RegisterDepth(depth_camera, intrinsics.K(), intrinsics.width, intrinsics.height))
        gt = depth_camera.moved_to_colour(gt)
    sequence = Sequence(root, NAME, intrinsics, timestamps, rgb_paths, depth_paths, gt_poses=gt, names=stems,
                        transform=transform)
    sequence.source = {**sequence.source, "camera": camera}
    return sequence


def _camera_file(folder: Path, root: Path) -> dict[str, float] | None:
    """fx, fy, cx, cy of the first camera-intrinsics.txt in the sequence folder or ROOT (None without one)."""
    for place in (folder, root):
        if (place / "camera-intrinsics.txt").is_file():
            K = read_matrix(place / "camera-intrinsics.txt", (3, 3), "camera matrix", "write a 3x3 matrix, one row per line")
            return {"fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2]}
    return None


def _check_published_camera(root: Path, options: ReadOptions, first_rgb: Path, intrinsics: Intrinsics,
                            published_depth: bool) -> None:
    """Without camera-intrinsics.txt, refuse frames of another size than 640x480 where the published camera would be
    read: as the colour camera (intrinsics.json and the flags do not give all of it) or, registering depth, as the
    depth camera (``published_depth``: intrinsics.json has no depth_camera)."""
    published_colour = not all(k in json_keys(root / "intrinsics.json") | set(options.override.values()) for k in PINHOLE)
    if not (published_colour or published_depth):
        return
    fix = "give camera-intrinsics.txt (the camera matrix at this size)"
    if published_depth:
        fix += (", or the colour camera (intrinsics.json or --fx --fy --cx --cy) with --camera shipped "
                "or with intrinsics.json's depth_camera")
    else:
        fix += ", or the colour camera in intrinsics.json or with --fx --fy --cx --cy"
    check_published_size(first_rgb, intrinsics, "the 7-Scenes camera (fx = fy = 585, cx = 320, cy = 240)",
                         PUBLISHED_SIZE, fix)
