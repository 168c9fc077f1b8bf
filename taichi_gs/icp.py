"""Depth point clouds and coarse-to-fine point-to-plane ICP with Open3D."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from .geometry import backproject

o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)


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


def depth_cloud(depth: np.ndarray, K: np.ndarray, mask: np.ndarray, colors: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    """Camera-space point cloud of the masked depth pixels (coloured if colours are given)."""
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(backproject(depth, K)[mask])
    if colors is not None:
        cloud.colors = o3d.utility.Vector3dVector(colors[mask].astype(np.float64))
    return cloud


def multiscale_point_to_plane(
    source: o3d.geometry.PointCloud,
    target: o3d.geometry.PointCloud,
    init: np.ndarray,
    voxel_sizes: tuple[float, ...],
    iterations: tuple[int, ...],
    distance_factor: float,
    normal_radius_factor: float,
    normal_max_nn: int,
) -> ICPResult:
    """Point-to-plane ICP from coarse to fine voxel sizes; each level starts from the previous one.

    At voxel size v the clouds are downsampled to v, target normals use radius normal_radius_factor v,
    and correspondences farther than distance_factor v are ignored. Fitness and RMSE are the finest level's.
    """
    if len(voxel_sizes) != len(iterations):
        raise ValueError(f"{len(voxel_sizes)} ICP voxel sizes but {len(iterations)} iteration counts")
    registration = o3d.pipelines.registration
    transform = np.asarray(init, dtype=np.float64)
    fitness, rmse = 0.0, float("inf")
    finest = min(voxel_sizes)
    source, target = source.voxel_down_sample(finest), target.voxel_down_sample(finest)
    for voxel, steps in zip(voxel_sizes, iterations):
        src = source if voxel == finest else source.voxel_down_sample(voxel)
        tgt = target if voxel == finest else target.voxel_down_sample(voxel)
        tgt.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=normal_radius_factor * voxel, max_nn=normal_max_nn))
        result = registration.registration_icp(
            src, tgt, distance_factor * voxel, transform,
            registration.TransformationEstimationPointToPlane(),
            registration.ICPConvergenceCriteria(max_iteration=int(steps)),
        )
        transform = np.asarray(result.transformation).copy()
        fitness, rmse = float(result.fitness), float(result.inlier_rmse)
    return ICPResult(transform, fitness, rmse)
