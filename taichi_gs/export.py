"""Hand a finished run to other tools: nerfstudio ``transforms.json``, a COLMAP text model, PLYs,
a reference-3DGS model folder, or sharp renders along a camera path.

The newest finished stage provides the poses (deblur, else refine, else pose); images are the
deblurred sharp renders when stage 3 ran, else the input frames. Everything is written under a
destination folder; the run folder and the input are only read.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .camera_paths import orbit_path, trajectory_path
from .choices import RENDER_PATHS
from .errors import InputError
from .geometry import intrinsics_matrix, invert, rotmat_to_quat
from .io import jsonout
from .io.atomic import atomic_path, write_text
from .io.images import encode_depth, to_uint8, write_png
from .io.ply import read_point_cloud, read_splats, write_splats
from .io.sequence import Sequence
from .io.trajectory import read_tum
from .pipeline import STAGES, read_done

DEPTH_PNG_UNITS_PER_METRE = 1000.0  # exported depth: uint16 millimetres
REFERENCE_SH_DEGREE = 3  # what the reference 3DGS loader asserts
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


def _frame_images(run_dir: Path, sequence: Sequence, dest: Path, depth: bool = True) -> list[tuple[str, str | None]]:
    """Copy the frames' images (deblurred if available) into dest/images and, with ``depth``, write
    their depth maps as 16-bit PNGs in millimetres into dest/depth; return paths relative to dest."""
    sharp_dir = run_dir / "deblur" / "renders" / "sharp"
    (dest / "images").mkdir(parents=True, exist_ok=True)
    names: list[tuple[str, str | None]] = []
    for i, stem in enumerate(sequence.names):
        source = sharp_dir / f"{stem}.png"
        if source.is_file():
            image = f"images/{stem}.png"
            _copy(source, dest / image)
        elif sequence.transform is not None:  # read through a resampling: write the frame as read
            image = f"images/{stem}.png"
            write_png(dest / image, to_uint8(sequence.color(i)))
        else:
            image = f"images/{stem}{sequence.rgb_paths[i].suffix}"
            _copy(sequence.rgb_paths[i], dest / image)
        depth_name = None
        if depth:
            depth_name = f"depth/{stem}.png"
            write_png(dest / depth_name, encode_depth(sequence.depth(i), DEPTH_PNG_UNITS_PER_METRE))
        names.append((image, depth_name))
    return names


def _copy(source: Path, target: Path) -> None:
    with atomic_path(target) as tmp:
        shutil.copyfile(source, tmp)


def centre_principal_point(cx: float, cy: float) -> tuple[float, float]:
    """OpenCV's principal point (pixel u samples image coordinate u) in the convention of COLMAP,
    nerfstudio and 3DGS, whose pixel u covers [u, u + 1) with its centre at u + 0.5."""
    return cx + 0.5, cy + 0.5


def export_nerfstudio(run_dir: Path, sequence: Sequence, dest: Path) -> Path:
    """nerfstudio ``transforms.json`` (OpenGL camera-to-world), images, depth and points.ply.

    Depth PNGs are uint16 millimetres, which nerfstudio's dataparser reads right with its default
    ``--depth-unit-scale-factor 1e-3`` (it never reads that factor from transforms.json)."""
    poses = final_poses(run_dir, sequence)
    intr = sequence.intrinsics
    cx, cy = centre_principal_point(intr.cx, intr.cy)
    frames = []
    for (image, depth), pose in zip(_frame_images(run_dir, sequence, dest), poses):
        frames.append({"file_path": image, "transform_matrix": (pose @ OPENCV_TO_OPENGL).tolist(),
                       "depth_file_path": depth})
    transforms = {
        "camera_model": "OPENCV", "w": intr.width, "h": intr.height,
        "fl_x": intr.fx, "fl_y": intr.fy, "cx": cx, "cy": cy,
        "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0,
        "depth_unit_scale_factor": 1.0 / DEPTH_PNG_UNITS_PER_METRE,  # informative: nerfstudio's default
        "frames": frames,
    }
    cloud = _points_path(run_dir)
    if cloud is not None:
        _copy(cloud, dest / "points.ply")
        transforms["ply_file_path"] = "points.ply"
    path = dest / "transforms.json"
    write_text(path, jsonout.dumps(transforms, indent=2) + "\n")
    return path


def export_colmap(run_dir: Path, sequence: Sequence, dest: Path, max_points: int = 200_000) -> Path:
    """COLMAP text model (``sparse/0/{cameras,images,points3D}.txt``, PINHOLE camera) and images/."""
    poses = final_poses(run_dir, sequence)
    intr = sequence.intrinsics
    names = _frame_images(run_dir, sequence, dest, depth=False)
    model = dest / "sparse" / "0"
    cx, cy = centre_principal_point(intr.cx, intr.cy)
    write_text(model / "cameras.txt",
               "# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]\n"
               f"1 PINHOLE {intr.width} {intr.height} {intr.fx:.12g} {intr.fy:.12g} {cx:.12g} {cy:.12g}\n")
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
    """The newest splats.ply (3DGS layout, SH padded to degree 3 so that the reference loader and
    SIBR viewer open it; SuperSplat and gsplat read it too) and points.ply, into ``dest``."""
    splats = newest_splats_path(run_dir)
    cloud = _points_path(run_dir)
    if splats is None and cloud is None:
        raise InputError(run_dir, "no splats.ply or points.ply in any stage folder", "run 'taichi-gs reconstruct' first")
    if splats is not None:
        write_splats(dest / "splats.ply", read_splats(splats), sh_degree=REFERENCE_SH_DEGREE)
    if cloud is not None:
        _copy(cloud, dest / "points.ply")
    return dest


def export_3dgs(run_dir: Path, sequence: Sequence, dest: Path) -> Path:
    """A model folder as the reference 3DGS code writes it, for its SIBR viewer and tools:
    ``point_cloud/iteration_N/point_cloud.ply`` (SH degree 3), ``cameras.json``, ``cfg_args``,
    with the COLMAP dataset it names as source in ``dest/source``."""
    splats = newest_splats_path(run_dir)
    if splats is None:
        raise InputError(run_dir, "no splats.ply in deblur/ or refine/", "run 'taichi-gs reconstruct' first")
    stage = splats.parent.name
    iteration = int(((read_done(run_dir, stage) or {}).get("config") or {}).get("iterations", 0)) or 1
    poses = final_poses(run_dir, sequence)
    source = dest / "source"
    export_colmap(run_dir, sequence, source)
    write_splats(dest / "point_cloud" / f"iteration_{iteration}" / "point_cloud.ply", read_splats(splats),
                 sh_degree=REFERENCE_SH_DEGREE)
    intr = sequence.intrinsics
    cameras = [{"id": i, "img_name": name, "width": intr.width, "height": intr.height,
                "position": pose[:3, 3].tolist(), "rotation": pose[:3, :3].tolist(), "fy": intr.fy, "fx": intr.fx}
               for i, (name, pose) in enumerate(zip(sequence.names, poses))]
    write_text(dest / "cameras.json", jsonout.dumps(cameras))
    write_text(dest / "cfg_args", f"Namespace(sh_degree={REFERENCE_SH_DEGREE}, source_path={str(source.resolve())!r}, "
                                  f"model_path={str(dest.resolve())!r}, images='images', resolution=-1, "
                                  "white_background=False, data_device='cuda', eval=False)")
    return dest


def newest_splats_path(run_dir: Path) -> Path | None:
    """The newest stage's splats.ply (deblur/, else refine/), or None."""
    paths = (run_dir / stage / "splats.ply" for stage in ("deblur", "refine"))
    return next((path for path in paths if path.is_file()), None)


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

    if path not in RENDER_PATHS:
        raise ValueError(f"unknown camera path {path!r}: choose one of {', '.join(RENDER_PATHS)}")
    splat_path = newest_splats_path(run_dir)
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
