"""A triangle mesh of a finished run: the input depth fused into a TSDF (Open3D's uniform TSDF volume
over the scene's bounds) at the run's final poses, coloured from the deblurred sharp renders rather
than the blurred input.

The voxel size defaults to the scene's scale (median valid depth / 200, clamped to 2 mm - 5 cm) and
is enlarged where the bounds would need more than ``MAX_RESOLUTION`` voxels a side (memory); the
truncation distance is 4 voxels; depth beyond the 99th percentile of the sampled frames is ignored.
(Open3D 0.20's ScalableTSDFVolume integrates nothing in this build, hence the uniform volume.)
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from .errors import InputError
from .export import final_poses
from .geometry import invert
from .io.atomic import atomic_path
from .io.images import to_uint8, write_png
from .io.ply import read_splats
from .io.sequence import Sequence, read_color

VOXEL_RANGE = (0.002, 0.05)  # metres
VOXELS_PER_MEDIAN_DEPTH = 200.0
MAX_RESOLUTION = 256  # voxels a side: 256^3 voxels of 20 bytes = 335 MB


def scene_voxel_size(sequence: Sequence) -> tuple[float, float]:
    """(voxel size, depth cut-off) in metres from the valid depth of a few frames."""
    picks = np.unique(np.linspace(0, len(sequence) - 1, num=min(5, len(sequence))).astype(int))
    valid = np.concatenate([d[d > 0] for d in (sequence.depth(int(i)) for i in picks)])
    if valid.size == 0:
        raise InputError(sequence.depth_paths[0], "no valid depth in the sampled frames", "check the depth files")
    voxel = float(np.clip(np.median(valid) / VOXELS_PER_MEDIAN_DEPTH, *VOXEL_RANGE))
    return voxel, float(np.percentile(valid, 99))


def scene_bounds(sequence: Sequence, poses: np.ndarray, depth_max: float, frames: int = 10,
                 stride: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """World-space bounding box (min, max corners) of the valid depth of up to ``frames`` frames."""
    K = sequence.K()
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    for i in np.unique(np.linspace(0, len(sequence) - 1, num=min(frames, len(sequence))).astype(int)):
        depth = sequence.depth(int(i))[::stride, ::stride]
        v, u = np.nonzero((depth > 0) & (depth <= depth_max))
        z = depth[v, u]
        cam = np.stack([(u * stride - K[0, 2]) / K[0, 0] * z, (v * stride - K[1, 2]) / K[1, 1] * z, z], axis=1)
        world = cam @ poses[i][:3, :3].T + poses[i][:3, 3]
        if len(world):
            low, high = np.minimum(low, world.min(axis=0)), np.maximum(high, world.max(axis=0))
    if not np.all(np.isfinite(low)):
        raise InputError(sequence.depth_paths[0], "no valid depth to bound the scene", "check the depth files")
    return low, high


def sharp_colors(run_dir: Path, sequence: Sequence, poses: np.ndarray) -> Iterator[np.ndarray]:
    """Each frame's deblurred colour (float RGB): stage 3's sharp render, else a render of the newest
    splats at the frame's final pose."""
    sharp_dir = run_dir / "deblur" / "renders" / "sharp"
    if all((sharp_dir / f"{name}.png").is_file() for name in sequence.names):
        for name in sequence.names:
            yield read_color(sharp_dir / f"{name}.png")
        return
    splat_path = next((run_dir / s / "splats.ply" for s in ("deblur", "refine") if (run_dir / s / "splats.ply").is_file()), None)
    if splat_path is None:
        raise InputError(run_dir, "no sharp renders and no splats.ply to render colours from", "run 'taichi-gs reconstruct' first")
    from .render import render_views

    intr = sequence.intrinsics
    for rgb, _, _ in render_views(read_splats(splat_path), intr.K(), intr.width, intr.height, poses):
        yield rgb


def fuse_mesh(run_dir: Path, sequence: Sequence, voxel_size: float | None = None,
              progress: Callable[[int, int], None] | None = None):
    """The TSDF mesh (an ``open3d.geometry.TriangleMesh`` with vertex colours and normals)."""
    import open3d as o3d

    poses = final_poses(run_dir, sequence)
    auto_voxel, depth_max = scene_voxel_size(sequence)
    voxel = voxel_size or auto_voxel
    low, high = scene_bounds(sequence, poses, depth_max)
    low, high = low - 4 * voxel, high + 4 * voxel
    length = float(np.max(high - low))
    resolution = int(min(MAX_RESOLUTION, np.ceil(length / voxel)))
    voxel = length / resolution
    volume = o3d.pipelines.integration.UniformTSDFVolume(
        length=length, resolution=resolution, sdf_trunc=4.0 * voxel,
        color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8, origin=low.reshape(3, 1))
    intr = sequence.intrinsics
    camera = o3d.camera.PinholeCameraIntrinsic(intr.width, intr.height, intr.fx, intr.fy, intr.cx, intr.cy)
    for i, color in enumerate(sharp_colors(run_dir, sequence, poses)):
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(to_uint8(color))), o3d.geometry.Image(sequence.depth(i)),
            depth_scale=1.0, depth_trunc=depth_max, convert_rgb_to_intensity=False)
        volume.integrate(rgbd, camera, invert(poses[i]))
        if progress is not None:
            progress(i + 1, len(sequence))
    mesh = volume.extract_triangle_mesh()
    if len(mesh.triangles) == 0:
        raise InputError(run_dir, "the fused volume holds no surface", "check the depth and poses, or pass a larger --voxel-size")
    mesh.compute_vertex_normals()
    return mesh


def mesh_view(mesh, K: np.ndarray, pose: np.ndarray, width: int, height: int) -> np.ndarray:
    """A quick picture of the mesh from camera ``pose``: its vertex colours splatted with a z-buffer
    (uint8 RGB, black where nothing is seen)."""
    points = np.asarray(mesh.vertices)
    colors = np.asarray(mesh.vertex_colors)
    world_to_camera = invert(pose)
    cam = points @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    front = cam[:, 2] > 1e-3
    cam, colors = cam[front], colors[front]
    u = np.round(K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2]).astype(int)
    v = np.round(K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]).astype(int)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z, colors = u[inside], v[inside], cam[inside, 2], colors[inside]
    image = np.zeros((height, width, 3))
    if len(z) == 0:
        return to_uint8(image)
    triangles = np.asarray(mesh.triangles)
    edge = float(np.median(np.linalg.norm(points[triangles[:, 0]] - points[triangles[:, 1]], axis=1)))
    radius = int(np.clip(np.ceil(0.5 * edge * K[0, 0] / np.median(z)), 0, 2))  # fill the gaps between vertices
    offsets = [(du, dv) for dv in range(-radius, radius + 1) for du in range(-radius, radius + 1)]
    uu = np.concatenate([np.clip(u + du, 0, width - 1) for du, _ in offsets])
    vv = np.concatenate([np.clip(v + dv, 0, height - 1) for _, dv in offsets])
    zz, cc = np.tile(z, len(offsets)), np.tile(colors, (len(offsets), 1))
    pixel = vv * width + uu
    nearest = np.full(height * width, np.inf)
    np.minimum.at(nearest, pixel, zz)
    hit = zz == nearest[pixel]  # the nearest vertex landing on each pixel
    image.reshape(-1, 3)[pixel[hit]] = cc[hit]
    return to_uint8(image)


def export_mesh(run_dir: Path, sequence: Sequence, dest: Path, voxel_size: float | None = None,
                progress: Callable[[int, int], None] | None = None) -> Path:
    """Write DEST/mesh.ply (binary PLY, vertex colours and normals) and RUN_DIR/report/mesh_view.png
    (the mesh seen from the first camera, pulled back); returns the PLY path."""
    import open3d as o3d

    mesh = fuse_mesh(run_dir, sequence, voxel_size, progress)
    path = Path(dest) / "mesh.ply"
    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
            raise OSError(f"could not write {path}")
    poses = final_poses(run_dir, sequence)
    back = poses[0].copy()
    back[:3, 3] -= back[:3, 2] * 0.5 * float(np.median(np.linalg.norm(np.asarray(mesh.vertices) - poses[0][:3, 3], axis=1)))
    intr = sequence.intrinsics
    write_png(Path(run_dir) / "report" / "mesh_view.png", mesh_view(mesh, intr.K(), back, intr.width, intr.height))
    return path
