"""Depth point clouds and coarse-to-fine point-to-plane ICP with Open3D.

Open3D is imported on first use (:func:`open3d`): only stage 1 needs it, so stages 2 and 3 (and
everything that imports this module for :func:`reliable_depth_mask`) run where it is not installed.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np

from . import profiling
from .geometry import backproject

if TYPE_CHECKING:
    import open3d as o3d


@functools.cache
def open3d():
    """The open3d module, imported once and told to print errors only."""
    try:
        import open3d as o3d
    except ImportError as error:
        raise ImportError(f"stage 1 (pose) needs open3d, which did not import ({error}): pip install open3d; "
                          "stages 2 and 3 run without it") from error
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d


@dataclass(frozen=True)
class ICPResult:
    """Transform source -> target, fraction of source points matched (fitness) and their RMSE (m)."""

    transform: np.ndarray
    fitness: float
    inlier_rmse: float


def reliable_depth_mask(depth: np.ndarray, min_depth: float, max_depth: float, edge_ratio: float) -> np.ndarray:
    """Depth inside [min_depth, max_depth] whose 3x3 neighbourhood is valid and spans < edge_ratio x depth.

    Removes the flying pixels that depth sensors leave on object boundaries.
    """
    valid = (depth > min_depth) & (depth < max_depth)
    kernel = np.ones((3, 3), np.uint8)
    masked = np.where(valid, depth, 0).astype(np.float32)
    lowest = cv2.erode(masked, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    highest = cv2.dilate(masked, kernel)
    return valid & (lowest > 0) & (highest - lowest <= edge_ratio * depth)


@profiling.timed("point clouds (Open3D; import on first use)")
def depth_cloud(depth: np.ndarray, K: np.ndarray, mask: np.ndarray, colors: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """Camera-space point cloud of the masked depth pixels (coloured if colours are given)."""
    o3d = open3d()
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(backproject(depth, K)[mask])
    if colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(colors[mask].astype(np.float64))
    return cloud


MIN_ICP_POINTS = 3  # fewer points than this in either cloud: no alignment is possible


@dataclass(frozen=True)
class ICPLevels:
    """Two clouds prepared for coarse-to-fine point-to-plane ICP, reusable from any start: per level
    (in the order given) the voxel size, the downsampled source, the downsampled target with normals
    and the iteration count; None when a cloud has too few points to align."""

    levels: tuple[tuple[float, o3d.geometry.PointCloud, o3d.geometry.PointCloud, int], ...] | None
    distance_factor: float


@profiling.timed("ICP")
def prepare_icp(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    voxel_sizes: tuple[float, ...],
    iterations: tuple[int, ...],
    distance_factor: float,
    normal_radius_factor: float,
    normal_max_nn: int,
    max_points: int = 0,
) -> ICPLevels:
    """The clouds downsampled to every voxel size, target normals with radius normal_radius_factor v.
    With ``max_points`` > 0 every voxel size grows by steps of 25% (``VOXEL_GROWTH``) until the finest
    level leaves at most that many source points (ICP time grows faster than linearly with density)."""
    if len(voxel_sizes) != len(iterations):
        raise ValueError(f"{len(voxel_sizes)} ICP voxel sizes but {len(iterations)} iteration counts")
    if len(source.points) < MIN_ICP_POINTS or len(target.points) < MIN_ICP_POINTS:
        return ICPLevels(None, distance_factor)  # nothing to align (a frame without depth)
    source, scale = capped_voxel_down_sample(source, min(voxel_sizes), max_points)
    voxel_sizes = tuple(scale * v for v in voxel_sizes)
    finest = min(voxel_sizes)
    target = target.voxel_down_sample(finest)
    levels = []
    for voxel, steps in zip(voxel_sizes, iterations):
        src = source if voxel == finest else source.voxel_down_sample(voxel)
        tgt = target if voxel == finest else target.voxel_down_sample(voxel)
        tgt.estimate_normals(open3d().geometry.KDTreeSearchParamHybrid(radius=normal_radius_factor * voxel, max_nn=normal_max_nn))
        levels.append((voxel, src, tgt, int(steps)))
    return ICPLevels(tuple(levels), distance_factor)


@profiling.timed("ICP")
def align(prepared: ICPLevels, init: np.ndarray) -> ICPResult:
    """Point-to-plane ICP through the prepared levels, each starting from the previous one's result;
    correspondences farther than distance_factor x voxel are ignored. Fitness and RMSE are the last
    level's (fitness 0 when there was nothing to align)."""
    registration = open3d().pipelines.registration
    transform = np.asarray(init, dtype=np.float64)
    fitness, rmse = 0.0, float("inf")
    for voxel, src, tgt, steps in prepared.levels or ():
        result = registration.registration_icp(
            src, tgt, prepared.distance_factor * voxel, transform,
            registration.TransformationEstimationPointToPlane(),
            registration.ICPConvergenceCriteria(max_iteration=steps),
        )
        transform = np.asarray(result.transformation).copy()
        fitness, rmse = float(result.fitness), float(result.inlier_rmse)
    return ICPResult(transform, fitness, rmse)


VOXEL_GROWTH = 1.25  # a point cap (ICP's, the pose graph's information clouds) grows voxels by this factor per step
_PROBE_STEP = 12  # the voxel search's first count, 1.25^12 ~ 15x coarser than the finest voxel (cheap)


def capped_voxel_down_sample(cloud: o3d.geometry.PointCloud, voxel: float,
                             max_points: int) -> tuple[o3d.geometry.PointCloud, float]:
    """``cloud`` downsampled on the smallest voxel ``voxel`` x 1.25^k that leaves at most ``max_points``
    points (k = 0 without a cap), and the factor 1.25^k.

    Voxel counts fall as voxels grow, and a fine voxel costs far more to count than a coarse one (173 ms
    at 1 cm for a 640x480 depth cloud, 8 ms at 15 cm). So the search counts a coarse voxel first,
    extrapolates by the surface law (count ~ voxel^-2) to a guess of k, and steps from the guess to the
    smallest k that fits: two or three counts instead of one per step from k = 0, with the same answer.
    The counted clouds are kept, so the chosen one is not downsampled a second time.
    """
    clouds: dict[int, o3d.geometry.PointCloud] = {}

    def down_sampled(k: int) -> o3d.geometry.PointCloud:
        if k not in clouds:
            clouds[k] = cloud.voxel_down_sample(voxel * VOXEL_GROWTH**k)
        return clouds[k]

    def fits(k: int) -> bool:
        return len(down_sampled(k).points) <= max_points

    if max_points <= 0:
        return down_sampled(0), 1.0
    probe = _PROBE_STEP
    while not fits(probe):
        probe *= 2
    growth_steps = math.log(max_points / max(len(clouds[probe].points), 1)) / (2 * math.log(VOXEL_GROWTH))
    k = min(probe, max(0, math.ceil(probe - growth_steps)))
    if fits(k):
        while k > 0 and fits(k - 1):
            k -= 1
    else:
        while not fits(k + 1):  # stops at probe at the latest
            k += 1
        k += 1
    return clouds[k], VOXEL_GROWTH**k


@profiling.timed("RGB-D odometry (Open3D)")
def rgbd_odometry(
    color_t: np.ndarray,
    depth_t: np.ndarray,
    color_t1: np.ndarray,
    depth_t1: np.ndarray,
    K: np.ndarray,
    init: np.ndarray,
    iterations: tuple[int, ...] = (20, 10, 5),
    depth_diff_max: float = 0.07,
    depth_range: tuple[float, float] = (0.1, 10.0),
) -> np.ndarray | None:
    """Open3D's dense RGB-D odometry (hybrid photometric + depth term, coarse to fine, one pyramid
    level per entry of ``iterations``) from ``init``: transform camera t -> t+1, or None if it fails.

    Colours are RGB floats in [0, 1], depths metres (0 = invalid).
    """
    o3d = open3d()
    h, w = depth_t.shape
    camera = o3d.camera.PinholeCameraIntrinsic(w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    option = o3d.pipelines.odometry.OdometryOption(
        iteration_number_per_pyramid_level=o3d.utility.IntVector([int(i) for i in iterations]),
        depth_diff_max=depth_diff_max, depth_min=depth_range[0], depth_max=depth_range[1])
    ok, transform, _ = o3d.pipelines.odometry.compute_rgbd_odometry(
        _rgbd(color_t, depth_t, depth_range[1]), _rgbd(color_t1, depth_t1, depth_range[1]), camera,
        np.asarray(init, dtype=np.float64), o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm(), option)
    return np.asarray(transform).copy() if ok else None


def _rgbd(color: np.ndarray, depth: np.ndarray, max_depth: float) -> o3d.geometry.RGBDImage:
    o3d = open3d()
    rgb = o3d.geometry.Image(np.ascontiguousarray(np.clip(color * 255.0, 0, 255).astype(np.uint8)))
    z = o3d.geometry.Image(np.ascontiguousarray(depth, dtype=np.float32))
    return o3d.geometry.RGBDImage.create_from_color_and_depth(rgb, z, depth_scale=1.0, depth_trunc=max_depth,
                                                              convert_rgb_to_intensity=True)
