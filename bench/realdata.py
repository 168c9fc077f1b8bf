"""Real benchmark data: a slice of the 7-Scenes folder in ../shared/data, converted to our own layout.

    python bench/realdata.py OUT [--first 0 --count 60 --every 1 --scale 0.5]

7-Scenes (Kinect v1) ships ``frame-NNNNNN.color.jpg|png``, ``.depth.png`` (uint16 millimetres, 0 and
65535 invalid) and ``.pose.txt`` (camera-to-world 4x4) with ``camera-intrinsics.txt``; frames are 1/30 s
apart. The slice is written as ``frames.txt`` + ``rgb/`` + ``depth/`` + ``groundtruth.txt`` +
``intrinsics.json`` (the data is non-commercial: write it outside the repository, never commit it).
Colour is resampled by area, depth by nearest neighbour (invalid stays 0), and the intrinsics with the
pixel-centre convention (c' = (c + 0.5) s - 0.5).

Depth-colour registration (``--register``). 7-Scenes' colour and depth come from the Kinect's two
cameras and are not registered; the dataset gives one K (585, 320, 240), which is the depth camera's.
Fitting the colour camera by the agreement of depth edges (after reprojection) with colour edges over
10 frames (0, 25, ..., 225) gives a colour focal length of 526.5 px (grid step 5.9 px; the Kinect v1
colour camera's usual 525), the principal point (320, 240) (+-1 px) and the colour camera 2.5 cm from
the depth camera along x (grid step 6 mm): u_colour = 526.5 (X_depth - 0.025) / Z + 320; the edge
correlation rises from 0.17 (as shipped) to 0.28. With ``register`` each depth map is forward-projected
into the colour camera (nearest depth wins), the intrinsics written are the colour camera's, and the
ground-truth poses (KinectFusion's, of the depth camera) are moved to the colour camera. Without it the
slice is as shipped (depth and colour treated as one camera with K = 585).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from taichi_gs.geometry import rotmat_to_quat

SEVEN_SCENES = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes_redkitchen_000-249"
FPS = 30.0
COLOUR_FOCAL = 526.5  # px at 640x480, fitted as the module docstring says
COLOUR_FROM_DEPTH = np.array([-0.025, 0.0, 0.0])  # X_colour = X_depth + this (metres)


def register_depth(depth: np.ndarray, K_depth: np.ndarray, K_colour: np.ndarray, colour_from_depth: np.ndarray,
                   size: tuple[int, int]) -> np.ndarray:
    """Depth (metres, 0 = invalid) seen by the colour camera of image ``size`` (width, height):
    every valid depth pixel is back-projected, moved by ``colour_from_depth`` and splatted to its
    nearest colour pixel; the nearest surface wins, pixels nothing lands on are 0."""
    v, u = np.nonzero(depth > 0)
    z = depth[v, u].astype(np.float64)
    points = np.stack([(u - K_depth[0, 2]) / K_depth[0, 0] * z, (v - K_depth[1, 2]) / K_depth[1, 1] * z, z], axis=1)
    points = points + colour_from_depth
    zc = points[:, 2]
    front = zc > 1e-6
    points, zc = points[front], zc[front]
    uc = np.round(K_colour[0, 0] * points[:, 0] / zc + K_colour[0, 2]).astype(np.int64)
    vc = np.round(K_colour[1, 1] * points[:, 1] / zc + K_colour[1, 2]).astype(np.int64)
    width, height = size
    inside = (uc >= 0) & (uc < width) & (vc >= 0) & (vc < height)
    out = np.full((height, width), np.inf)
    np.minimum.at(out, (vc[inside], uc[inside]), zc[inside])
    out[np.isinf(out)] = 0.0
    return out


def convert_7scenes(out: Path, src: Path = SEVEN_SCENES, first: int = 0, count: int = 60, every: int = 1,
                    scale: float = 1.0, register: bool = False) -> Path:
    """Write frames first, first+every, ... (count of them) of a 7-Scenes folder to OUT in our layout;
    ``register``: depth reprojected into the colour camera (see the module docstring)."""
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    K = np.loadtxt(src / "camera-intrinsics.txt")
    K_colour = K.copy()
    if register:
        K_colour[0, 0] = K_colour[1, 1] = COLOUR_FOCAL
    colour_to_depth = np.eye(4)
    colour_to_depth[:3, 3] = -COLOUR_FROM_DEPTH if register else 0.0
    frames, gt = ["# timestamp rgb depth"], []
    size = None
    for n in range(count):
        index = first + n * every
        stem = src / f"frame-{index:06d}"
        color_path = next((p for p in (stem.with_suffix(".color.jpg"), stem.with_suffix(".color.png")) if p.is_file()), None)
        if color_path is None:
            break
        color = cv2.imread(str(color_path), cv2.IMREAD_COLOR)
        depth = cv2.imread(str(stem.with_suffix(".depth.png")), cv2.IMREAD_UNCHANGED)
        depth[depth == 65535] = 0
        size = (round(color.shape[1] * scale), round(color.shape[0] * scale))
        if register:
            K_out = K_colour.copy()
            K_out[:2] *= scale
            K_out[:2, 2] = (K_colour[:2, 2] + 0.5) * scale - 0.5
            metres = register_depth(depth / 1000.0, K, K_out, COLOUR_FROM_DEPTH, size)
            depth = np.round(metres * 1000.0).astype(np.uint16)
        if scale != 1.0:
            color = cv2.resize(color, size, interpolation=cv2.INTER_AREA)
            if not register:
                depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        name = f"{index:06d}.png"
        cv2.imwrite(str(out / "rgb" / name), color)
        cv2.imwrite(str(out / "depth" / name), depth.astype(np.uint16))
        t = index / FPS
        frames.append(f"{t:.6f} rgb/{name} depth/{name}")
        pose = np.loadtxt(stem.with_suffix(".pose.txt")) @ colour_to_depth
        w, x, y, z = rotmat_to_quat(pose[:3, :3])
        gt.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], x, y, z, w)))
    height, width = color.shape[:2]
    intrinsics = {"width": width, "height": height, "fx": K_colour[0, 0] * scale, "fy": K_colour[1, 1] * scale,
                  "cx": (K_colour[0, 2] + 0.5) * scale - 0.5, "cy": (K_colour[1, 2] + 0.5) * scale - 0.5,
                  "depth_scale": 1000.0}
    (out / "frames.txt").write_text("\n".join(frames) + "\n")
    (out / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    (out / "intrinsics.json").write_text(json.dumps(intrinsics, indent=2) + "\n")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--src", type=Path, default=SEVEN_SCENES)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--count", type=int, default=60)
    parser.add_argument("--every", type=int, default=1)
    parser.add_argument("--scale", type=float, default=1.0)
    parser.add_argument("--register", action="store_true", help="reproject depth into the colour camera")
    args = parser.parse_args()
    out = convert_7scenes(args.out, args.src, args.first, args.count, args.every, args.scale, args.register)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
