"""Real benchmark data: a slice of the 7-Scenes folder in ../shared/data, converted to our own layout.

    python bench/realdata.py OUT [--first 0 --count 60 --every 1 --scale 0.5]

7-Scenes (Kinect v1) ships ``frame-NNNNNN.color.jpg|png``, ``.depth.png`` (uint16 millimetres, 0 and
65535 invalid) and ``.pose.txt`` (camera-to-world 4x4) with ``camera-intrinsics.txt``; frames are 1/30 s
apart. The slice is written as ``frames.txt`` + ``rgb/`` + ``depth/`` + ``groundtruth.txt`` +
``intrinsics.json`` (the data is non-commercial: write it outside the repository, never commit it).
Colour is resampled by area, depth by nearest neighbour (invalid stays 0), and the intrinsics with the
pixel-centre convention (c' = (c + 0.5) s - 0.5).
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


def convert_7scenes(out: Path, src: Path = SEVEN_SCENES, first: int = 0, count: int = 60, every: int = 1,
                    scale: float = 1.0) -> Path:
    """Write frames first, first+every, ... (count of them) of a 7-Scenes folder to OUT in our layout."""
    out = Path(out)
    (out / "rgb").mkdir(parents=True, exist_ok=True)
    (out / "depth").mkdir(parents=True, exist_ok=True)
    K = np.loadtxt(src / "camera-intrinsics.txt")
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
        if scale != 1.0:
            size = (round(color.shape[1] * scale), round(color.shape[0] * scale))
            color = cv2.resize(color, size, interpolation=cv2.INTER_AREA)
            depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        name = f"{index:06d}.png"
        cv2.imwrite(str(out / "rgb" / name), color)
        cv2.imwrite(str(out / "depth" / name), depth.astype(np.uint16))
        t = index / FPS
        frames.append(f"{t:.6f} rgb/{name} depth/{name}")
        pose = np.loadtxt(stem.with_suffix(".pose.txt"))
        w, x, y, z = rotmat_to_quat(pose[:3, :3])
        gt.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*pose[:3, 3], x, y, z, w)))
    height, width = color.shape[:2]
    intrinsics = {"width": width, "height": height, "fx": K[0, 0] * scale, "fy": K[1, 1] * scale,
                  "cx": (K[0, 2] + 0.5) * scale - 0.5, "cy": (K[1, 2] + 0.5) * scale - 0.5, "depth_scale": 1000.0}
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
    args = parser.parse_args()
    out = convert_7scenes(args.out, args.src, args.first, args.count, args.every, args.scale)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
