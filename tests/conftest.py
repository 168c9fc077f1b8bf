"""Shared fixtures: small hand-made RGB-D folders for reader tests."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest


def write_frame_images(folder: Path, index: int, size=(40, 30), depth_m: float = 2.0) -> tuple[str, str]:
    """Write one colour PNG and one 16-bit depth PNG (scale 5000); return their relative names."""
    w, h = size
    rng = np.random.default_rng(index)
    (folder / "rgb").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(parents=True, exist_ok=True)
    rgb_name, depth_name = f"rgb/{index:06d}.png", f"depth/{index:06d}.png"
    cv2.imwrite(str(folder / rgb_name), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
    cv2.imwrite(str(folder / depth_name), np.full((h, w), depth_m * 5000, dtype=np.uint16))
    return rgb_name, depth_name


def write_intrinsics(folder: Path, size=(40, 30), **extra) -> None:
    w, h = size
    values = {"width": w, "height": h, "fx": 50.0, "fy": 50.0, "cx": w / 2, "cy": h / 2, "depth_scale": 5000.0, **extra}
    (folder / "intrinsics.json").write_text(json.dumps(values))


@pytest.fixture
def own_layout(tmp_path: Path) -> Path:
    """A 3-frame folder in taichi-gs's own layout with ground truth."""
    folder = tmp_path / "own"
    lines = ["# timestamp rgb depth"]
    gt = []
    for i in range(3):
        rgb, depth = write_frame_images(folder, i)
        lines.append(f"{i / 30:.6f} {rgb} {depth}")
        gt.append(f"{i / 30:.6f} {0.1 * i} 0 0 0 0 0 1")
    (folder / "frames.txt").write_text("\n".join(lines) + "\n")
    (folder / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    write_intrinsics(folder)
    return folder


@pytest.fixture
def tum_layout(tmp_path: Path) -> Path:
    """A 4-frame TUM folder whose depth clock is offset by 5 ms, with 100 Hz ground truth."""
    folder = tmp_path / "tum"
    rgb_lines, depth_lines = ["# color images"], ["# depth maps"]
    for i in range(4):
        rgb, depth = write_frame_images(folder, i)
        t = 1000.0 + i / 30
        rgb_lines.append(f"{t:.6f} {rgb}")
        depth_lines.append(f"{t + 0.005:.6f} {depth}")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    gt = [f"{1000.0 + k / 100:.6f} {k * 0.01} 0 0 0 0 0 1" for k in range(-2, 20)]
    (folder / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    write_intrinsics(folder)
    return folder
