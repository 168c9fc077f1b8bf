"""One analytic scene (a textured plane z = PLANE_Z in world coordinates) written in each public RGB-D
layout's published file layout, so the readers can be checked against exact ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from taichi_gs.geometry import pose_from_rt, rotmat_to_quat

PLANE_Z = 2.5
FRAMES = 3


def truth_poses(n: int = FRAMES) -> np.ndarray:
    """Camera-to-world poses (OpenCV axes) looking roughly down +z at the plane."""
    poses = []
    for i in range(n):
        rx, ry, rz = 0.05 * i, -0.04 * i + 0.02, 0.03 * i
        R = cv2.Rodrigues(np.array([rx, ry, rz]))[0]
        poses.append(pose_from_rt(R, np.array([0.1 * i, -0.05 * i, 0.2 + 0.03 * i])))
    return np.stack(poses)


def texture(X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Smooth RGB texture of the plane, in [0, 1]."""
    return np.stack([0.5 + 0.4 * np.sin(4.0 * X), 0.5 + 0.4 * np.cos(5.0 * Y), 0.5 + 0.3 * np.sin(3.0 * (X + Y))], axis=-1)


def render(K: np.ndarray, pose: np.ndarray, width: int, height: int,
           distortion: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(colour float RGB, depth metres) of the plane seen by a (possibly distorted) camera."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1)
    if distortion is None:
        x = (pixels[:, 0] - K[0, 2]) / K[0, 0]
        y = (pixels[:, 1] - K[1, 2]) / K[1, 1]
    else:
        x, y = _undistort_points(pixels, K, distortion)
    rays = np.stack([x, y, np.ones_like(x)], axis=1) @ pose[:3, :3].T
    depth = (PLANE_Z - pose[2, 3]) / rays[:, 2]
    points = pose[:3, 3] + rays * depth[:, None]
    color = texture(points[:, 0], points[:, 1])
    return color.reshape(height, width, 3), depth.reshape(height, width)


def _undistort_points(pixels: np.ndarray, K: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates whose image under OpenCV's distortion model (k1, k2, p1, p2, k3) is
    ``pixels``: fixed-point iteration, checked by distorting back."""
    k1, k2, p1, p2, k3 = d
    xd, yd = (pixels[:, 0] - K[0, 2]) / K[0, 0], (pixels[:, 1] - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(40):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    back = cv2.projectPoints(np.stack([x, y, np.ones_like(x)], axis=1), np.zeros(3), np.zeros(3), K, d)[0][:, 0]
    assert np.abs(back - pixels).max() < 1e-6, "distortion inversion did not converge"
    return x, y


def backproject(K: np.ndarray, pose: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """World points (M x 3) of the valid depth pixels."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return cam @ pose[:3, :3].T + pose[:3, 3]


def K_of(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])


def _bgr(color: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.round(np.clip(color, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)


def _mm(depth: np.ndarray, scale: float = 1000.0) -> np.ndarray:
    return np.round(depth * scale).astype(np.uint16)


def _matrix_text(M: np.ndarray) -> str:
    return "\n".join(" ".join(f"{v:.10g}" for v in row) for row in M) + "\n"


# Each writer: (folder) -> dict with the reader's expected K, size and depth step (metres).

SMALL_K = K_of(60.0, 62.0, 39.5, 29.5)  # 80 x 60


def write_own(folder: Path) -> dict:
    folder.mkdir(parents=True)
    lines, gt = ["# timestamp rgb depth"], []
    for i, pose in enumerate(truth_poses()):
        color, depth = render(SMALL_K, pose, 80, 60)
        (folder / "rgb").mkdir(exist_ok=True), (folder / "depth").mkdir(exist_ok=True)
        cv2.imwrite(str(folder / f"rgb/{i:06d}.png"), _bgr(color))
        cv2.imwrite(str(folder / f"depth/{i:06d}.png"), _mm(depth, 5000.0))
        lines.append(f"{i / 30:.6f} rgb/{i:06d}.png depth/{i:06d}.png")
        gt.append(_tum_line(i / 30, pose))
    (folder / "frames.txt").write_text("\n".join(lines) + "\n")
    (folder / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    (folder / "intrinsics.json").write_text(json.dumps({"fx": 60.0, "fy": 62.0, "cx": 39.5, "cy": 29.5, "depth_scale": 5000.0}))
    return {"K": SMALL_K, "size": (80, 60), "step": 1 / 5000}


def _tum_line(t: float, pose: np.ndarray) -> str:
    w, x, y, z = rotmat_to_quat(pose[:3, :3])
    return f"{t:.6f} " + " ".join(f"{v:.12f}" for v in (*pose[:3, 3], x, y, z, w))


TUM_FR1 = {"K": K_of(517.3, 516.5, 318.6, 255.3), "distortion": np.array([0.2624, -0.9531, -0.0054, 0.0026, 1.1633])}


def write_tum(folder: Path) -> dict:
    """A TUM folder named like the fr1 downloads (no intrinsics file: the camera comes from the name),
    images rendered through fr1's lens distortion."""
    folder = folder.parent / "rgbd_dataset_freiburg1_synthetic"
    folder.mkdir(parents=True)
    (folder / "rgb").mkdir(), (folder / "depth").mkdir()
    rgb, dep, gt = ["# color images"], ["# depth maps"], ["# timestamp tx ty tz qx qy qz qw"]
    for i, pose in enumerate(truth_poses()):
        color, depth = render(TUM_FR1["K"], pose, 640, 480, TUM_FR1["distortion"])
        t = 1305031102.0 + i / 30
        cv2.imwrite(str(folder / f"rgb/{t:.6f}.png"), _bgr(color))
        cv2.imwrite(str(folder / f"depth/{t + 0.004:.6f}.png"), _mm(depth, 5000.0))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        dep.append(f"{t + 0.004:.6f} depth/{t + 0.004:.6f}.png")
        gt.append(_tum_line(t, pose))
    for name, lines in (("rgb.txt", rgb), ("depth.txt", dep), ("groundtruth.txt", gt)):
        (folder / name).write_text("\n".join(lines) + "\n")
    return {"K": TUM_FR1["K"], "size": (640, 480), "step": 1 / 5000, "folder": folder}


SEVEN_SCENES_COLOUR_FROM_DEPTH = np.array([-0.025, 0.0, 0.0])  # X_colour = X_depth + this


def write_7scenes(folder: Path, seq: bool = False) -> dict:
    """Flat 7-Scenes folder with camera-intrinsics.txt (80x60), or seq-01/ at the published 640x480
    with no intrinsics file (the reader's defaults, fx = fy = 585, cx = 320, cy = 240). As the Kinect
    records it: depth from the depth camera with that K, colour from a camera with 0.9 x its focal
    length 2.5 cm along x, pose files the depth camera's."""
    K, size = (K_of(585.0, 585.0, 320.0, 240.0), (640, 480)) if seq else (SMALL_K, (80, 60))
    K_colour = K_of(0.9 * K[0, 0], 0.9 * K[1, 1], K[0, 2], K[1, 2])
    colour_from_depth = pose_from_rt(np.eye(3), SEVEN_SCENES_COLOUR_FROM_DEPTH)
    frames = folder / "seq-01" if seq else folder
    frames.mkdir(parents=True)
    if not seq:
        (folder / "camera-intrinsics.txt").write_text(_matrix_text(K))
    for i, pose in enumerate(truth_poses()):
        depth_pose = pose @ colour_from_depth
        color, _ = render(K_colour, pose, *size)
        raw = _mm(render(K, depth_pose, *size)[1])
        raw[:2, :5] = 65535  # "no reading"
        cv2.imwrite(str(frames / f"frame-{i:06d}.color.png"), _bgr(color))
        cv2.imwrite(str(frames / f"frame-{i:06d}.depth.png"), raw)
        (frames / f"frame-{i:06d}.pose.txt").write_text(_matrix_text(depth_pose))
    return {"K": K_colour, "size": size, "step": 1 / 1000, "resampled_depth": True}


SCANNET_COLOR_K = K_of(150.0, 152.0, 81.0, 59.0)  # 160 x 120 colour
SCANNET_DEPTH_K = K_of(74.0, 75.0, 38.5, 30.2)  # 80 x 60 depth, another principal point


def write_scannet(folder: Path) -> dict:
    for sub in ("color", "depth", "pose", "intrinsic"):
        (folder / sub).mkdir(parents=True)
    for kind, K in (("color", SCANNET_COLOR_K), ("depth", SCANNET_DEPTH_K)):
        M = np.eye(4)
        M[:3, :3] = K
        (folder / "intrinsic" / f"intrinsic_{kind}.txt").write_text(_matrix_text(M))
    for i, pose in enumerate(truth_poses()):
        color, _ = render(SCANNET_COLOR_K, pose, 160, 120)
        _, depth = render(SCANNET_DEPTH_K, pose, 80, 60)
        cv2.imwrite(str(folder / f"color/{i}.jpg"), _bgr(color), [cv2.IMWRITE_JPEG_QUALITY, 100])
        cv2.imwrite(str(folder / f"depth/{i}.png"), _mm(depth))
        (folder / f"pose/{i}.txt").write_text(_matrix_text(pose))
    return {"K": SCANNET_DEPTH_K, "size": (80, 60), "step": 1 / 1000}


def write_replica(folder: Path, intrinsics: bool = True) -> dict:
    (folder / "results").mkdir(parents=True)
    rows = []
    for i, pose in enumerate(truth_poses()):
        color, depth = render(SMALL_K, pose, 80, 60)
        cv2.imwrite(str(folder / f"results/frame{i:06d}.jpg"), _bgr(color), [cv2.IMWRITE_JPEG_QUALITY, 100])
        cv2.imwrite(str(folder / f"results/depth{i:06d}.png"), _mm(depth, 6553.5))
        rows.append(" ".join(f"{v:.12g}" for v in pose.ravel()))
    (folder / "traj.txt").write_text("\n".join(rows) + "\n")
    if intrinsics:
        (folder / "intrinsics.json").write_text(json.dumps({"fx": 60.0, "fy": 62.0, "cx": 39.5, "cy": 29.5}))
    return {"K": SMALL_K, "size": (80, 60), "step": 1 / 6553.5}


STRAY_COLOR_K = K_of(180.0, 180.0, 119.5, 89.5)  # 240 x 180 colour; depth 80 x 60 (same field of view)
ARKIT_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def write_stray(folder: Path, depth_kind: str = "png") -> dict:
    """Stray Scanner layout: colour 3x the depth size, confidence maps, ARKit odometry; depth as
    uint16 mm PNG, float .npy or float TIFF (metres)."""
    for sub in ("rgb", "depth", "confidence"):
        (folder / sub).mkdir(parents=True)
    (folder / "camera_matrix.csv").write_text("\n".join(",".join(f"{v:.10g}" for v in row) for row in STRAY_COLOR_K) + "\n")
    rows = ["timestamp, frame, x, y, z, qx, qy, qz, qw"]
    K_depth = K_of(60.0, 60.0, (119.5 + 0.5) / 3 - 0.5, (89.5 + 0.5) / 3 - 0.5)
    for i, pose in enumerate(truth_poses()):
        color, _ = render(STRAY_COLOR_K, pose, 240, 180)
        _, depth = render(K_depth, pose, 80, 60)
        cv2.imwrite(str(folder / f"rgb/{i:06d}.png"), _bgr(color))
        if depth_kind == "png":
            cv2.imwrite(str(folder / f"depth/{i:06d}.png"), _mm(depth))
        elif depth_kind == "npy":
            np.save(folder / f"depth/{i:06d}.npy", depth.astype(np.float32))
        else:
            cv2.imwrite(str(folder / f"depth/{i:06d}.tiff"), depth.astype(np.float32))
        confidence = np.full((60, 80), 2, np.uint8)
        confidence[:, :10] = 1  # medium confidence: dropped
        cv2.imwrite(str(folder / f"confidence/{i:06d}.png"), confidence)
        arkit = pose @ ARKIT_TO_OPENCV  # ARKit camera axes: y up, looking down -z
        w, x, y, z = rotmat_to_quat(arkit[:3, :3])
        rows.append(", ".join(f"{v:.12g}" for v in (100.0 + i / 60, i, *arkit[:3, 3], x, y, z, w)))
    (folder / "odometry.csv").write_text("\n".join(rows) + "\n")
    step = 1 / 1000 if depth_kind == "png" else 1e-6
    return {"K": K_depth, "size": (80, 60), "step": step, "masked_columns": 10}


WRITERS = {"taichi-gs": write_own, "tum": write_tum, "7scenes": write_7scenes, "scannet": write_scannet,
           "replica": write_replica, "stray": write_stray}
