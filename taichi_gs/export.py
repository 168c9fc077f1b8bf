"""Hand a finished run to other tools: nerfstudio ``transforms.json``, a COLMAP text model, PLYs,
or sharp renders along a camera path.

The newest finished stage provides the poses (deblur, else refine, else pose); images are the
deblurred sharp renders when stage 3 ran, else the input frames. Everything is written under a
destination folder; the run folder and the input are only read.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .camera_paths import orbit_path, trajectory_path
from .errors import InputError
from .geometry import intrinsics_matrix, invert, rotmat_to_quat
from .io.atomic import atomic_path, write_text
from .io.images import encode_depth, to_uint8, write_png
from .io.ply import read_point_cloud, read_splats
from .io.sequence import Sequence
from .io.trajectory import read_tum
from .pipeline import STAGES

FORMATS = ("nerfstudio", "colmap", "ply")
# OpenCV camera axes (x right, y down, z forward) -> OpenGL/nerfstudio axes (x right, y up, z back).
OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


def final_stage(run_dir: Path) -> str:
    """The newest stage of a run that wrote a trajectory."""
    for stage in reversed(STAGES):
        if (run_dir / stage / "trajectory.txt").is_file():
            return stage
    raise InputError(run_dir, "no finished stage (pose/, refine/ or deblur/ with trajectory.txt)",
                     "run 'taichi-gs reconstruct' first")


def final_poses(run_dir: Path, sequence: Sequence) -> np.ndarray:
    """Camera-to-world poses of every frame from the newest stage, in sequence order."""
    stage = final_stage(run_dir)
    path = run_dir / stage / "trajectory.txt"
    timestamps, poses = read_tum(path)
    if len(poses) != len(sequence) or not np.allclose(timestamps, sequence.timestamps, atol=1e-6):
        raise InputError(path, f"{len(poses)} poses do not match the {len(sequence)} frames of {sequence.root}",
                         "export a run made from this sequence")
    return poses


def _frame_images(run_dir: Path, sequence: Sequence, dest: Path) -> list[tuple[str, str | None]]:
    """Copy the frames' images (deblurred if available) and depth maps into dest/images, dest/depth;
    return their paths relative to dest."""
    sharp_dir = run_dir / "deblur" / "renders" / "sharp"
    (dest / "images").mkdir(parents=True, exist_ok=True)
    (dest / "depth").mkdir(parents=True, exist_ok=True)
    names: list[tuple[str, str | None]] = []
    for i, stem in enumerate(sequence.names):
        source = sharp_dir / f"{stem}.png"
        if not source.is_file():
            source = sequence.rgb_paths[i]
        depth_source = sequence.depth_paths[i]
        if sequence.transform is not None:  # read through a resampling: write the frames as read
            image, depth = f"images/{stem}.png", f"depth/{stem}.png"
            if source.parent == sharp_dir:
                _copy(source, dest / image)
            else:
                write_png(dest / image, to_uint8(sequence.color(i)))
            write_png(dest / depth, encode_depth(sequence.depth(i), sequence.intrinsics.depth_scale))
            names.append((image, depth))
            continue
        image = f"images/{stem}{source.suffix}"
        _copy(source, dest / image)
        depth = f"depth/{stem}{depth_source.suffix}" if depth_source.suffix == ".png" else None
        if depth is not None:
            _copy(depth_source, dest / depth)
        names.append((image, depth))
    return names


def _copy(source: Path, target: Path) -> None:
    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)


def export_nerfstudio(run_dir: Path, sequence: Sequence, dest: Path) -> Path:
    """nerfstudio ``transforms.json`` (OpenGL camera-to-world), images, depth and points.ply."""
    poses = final_poses(run_dir, sequence)
    intr = sequence.intrinsics
    frames = []
    for (image, depth), pose in zip(_frame_images(run_dir, sequence, dest), poses):
        frame = {"file_path": image, "transform_matrix": (pose @ OPENCV_TO_OPENGL).tolist()}
        if depth is not None:
            frame["depth_file_path"] = depth
        frames.append(frame)
    transforms = {
        "camera_model": "OPENCV", "w": intr.width, "h": intr.height,
        "fl_x": intr.fx, "fl_y": intr.fy, "cx": intr.cx, "cy": intr.cy,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "depth_unit_scale_factor": 1.0 / intr.depth_scale,
        "frames": frames,
    }
    cloud = _points_path(run_dir)
    if cloud is not None:
        _copy(cloud, dest / "points.ply")
        transforms["ply_file_path"] = "points.ply"
    path = dest / "transforms.json"
    write_text(path, json.dumps(transforms, indent=2) + "\n")
    return path


def export_colmap(run_dir: Path, sequence: Sequence, dest: Path, max_points: int = 200_000) -> Path:
    """COLMAP text model (``sparse/0/{cameras,images,points3D}.txt``, PINHOLE camera) and images/."""
    poses = final_poses(run_dir, sequence)
    intr = sequence.intrinsics
    names = _frame_images(run_dir, sequence, dest)
    model = dest / "sparse" / "0"
    write_text(model / "cameras.txt",
               "# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n"
               f"1 PINHOLE {intr.width} {intr.height} {intr.fx:.12g} {intr.fy:.12g} {intr.cx:.12g} {intr.cy:.12g}\n")
    lines = ["# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", "# (world-to-camera; second line: no 2D points)"]
    for i, ((image, _), pose) in enumerate(zip(names, poses), start=1):
        world_to_camera = invert(pose)
        qw, qx, qy, qz = rotmat_to_quat(world_to_camera[:3, :3])
        tx, ty, tz = world_to_camera[:3, 3]
        values = " ".join(f"{float(v):.12g}" for v in (qw, qx, qy, qz, tx, ty, tz))
        lines += [f"{i} {values} 1 {Path(image).name}", ""]
    write_text(model / "images.txt", "\n".join(lines) + "\n")
    point_lines = ["# POINT3D_ID X Y Z R G B ERROR TRACK[]"]
    cloud = _points_path(run_dir)
    if cloud is not None:
        points, colors = read_point_cloud(cloud)
        step = max(1, -(-len(points) // max_points))
        rgb = np.clip(np.round(colors[::step] * 255), 0, 255).astype(int)
        point_lines += [f"{k} {x:.6f} {y:.6f} {z:.6f} {r} {g} {b} 0"
                        for k, ((x, y, z), (r, g, b)) in enumerate(zip(points[::step], rgb), start=1)]
    write_text(model / "points3D.txt", "\n".join(point_lines) + "\n")
    return model


def export_ply(run_dir: Path, dest: Path) -> Path:
    """Copy the newest splats.ply (3DGS layout, for splat viewers) and points.ply into ``dest``."""
    copied = False
    for name in ("splats.ply", "points.ply"):
        for stage in reversed(STAGES):
            source = run_dir / stage / name
            if source.is_file():
                _copy(source, dest / name)
                copied = True
                break
    if not copied:
        raise InputError(run_dir, "no splats.ply or points.ply in any stage folder", "run 'taichi-gs reconstruct' first")
    return dest


def _points_path(run_dir: Path) -> Path | None:
    for stage in reversed(STAGES):
        path = run_dir / stage / "points.ply"
        if path.is_file():
            return path
    return None


def render_path(run_dir: Path, sequence: Sequence, path: str, count: int, scale: float = 1.0,
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Render the newest splats along an ``orbit`` or the ``trajectory`` into
    RUN_DIR/render/PATH/NNNNNN.png and RUN_DIR/render/PATH.gif; returns the PNG folder."""
    from .render import render_views

    splat_path = next((run_dir / s / "splats.ply" for s in ("deblur", "refine") if (run_dir / s / "splats.ply").is_file()), None)
    if splat_path is None:
        raise InputError(run_dir, "no splats.ply in deblur/ or refine/", "run 'taichi-gs reconstruct' first")
    splats = read_splats(splat_path)
    poses = final_poses(run_dir, sequence)
    cameras = orbit_path(poses, splats.means, count) if path == "orbit" else trajectory_path(poses, count)
    intr = sequence.intrinsics
    width, height = max(8, round(intr.width * scale)), max(8, round(intr.height * scale))
    sx, sy = width / intr.width, height / intr.height
    K = intrinsics_matrix(intr.fx * sx, intr.fy * sy, (intr.cx + 0.5) * sx - 0.5, (intr.cy + 0.5) * sy - 0.5)
    target = run_dir / "render" / path
    images = []
    for i, (rgb, _, _) in enumerate(render_views(splats, K, width, height, cameras)):
        images.append(to_uint8(rgb))
        write_png(target / f"{i:06d}.png", images[-1])
        if progress is not None:
            progress(i + 1, count)
    with atomic_path(run_dir / "render" / f"{path}.gif") as tmp:
        iio.imwrite(tmp, np.stack(images), extension=".gif", duration=40, loop=0)
    return target
