"""Stage 1's window of frames: each frame and what pairs and graph edges derive from it, computed once."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

import numpy as np

from .config import PoseConfig
from .flow import to_gray_u8
from .icp import capped_voxel_down_sample, depth_cloud
from .pair import joint_normals
from .verify import frame_view

if TYPE_CHECKING:
    import open3d as o3d


class FrameCache:
    """A sequence's frames and what pairs and the pose graph derive from them (grey frames for optical flow,
    verification views, information clouds, the joint solve's normals), each read or computed once while among
    the ``keep`` frames used last: pairs and graph edges visit frames in windows. Safe to share between threads."""

    def __init__(self, sequence, K: np.ndarray, config: PoseConfig, keep: int = 16):
        settings = config.verify_settings()
        self.color = _Recent(lambda i: _read_only(sequence.color(i)), keep)
        self.depth = _Recent(lambda i: _read_only(sequence.depth(i)), keep)
        self.gray = _Recent(lambda i: _read_only(to_gray_u8(self.color(i))), keep)
        self.view = _Recent(lambda i: frame_view(self.color(i), self.depth(i), K, settings), keep)
        self.info_cloud = _Recent(lambda i: _information_cloud(self.depth(i), K, config), keep)
        self.normals = _Recent(lambda i: joint_normals(self.depth(i), K, config), keep)


class _Recent:
    """``compute(key)`` for the ``keep`` keys used last, each computed once even when several threads ask for
    it at the same time (the later ones wait for the first)."""

    def __init__(self, compute: Callable[[int], Any], keep: int):
        self.compute, self.keep = compute, keep
        self.results: OrderedDict[int, Future] = OrderedDict()
        self.lock = threading.Lock()

    def __call__(self, key: int) -> Any:
        with self.lock:
            result = self.results.get(key)
            mine = result is None
            if mine:
                result = self.results[key] = Future()
            self.results.move_to_end(key)
            while len(self.results) > self.keep:
                self.results.popitem(last=False)
        if mine:
            try:
                result.set_result(self.compute(key))
            except BaseException as error:
                result.set_exception(error)
                with self.lock:
                    if self.results.get(key) is result:
                        del self.results[key]  # not cached: the next call tries again
        return result.result()


def _read_only(image: np.ndarray) -> np.ndarray:
    """A read-only view of ``image`` (the sequence's own array keeps its flags): a cached frame is shared
    by every pair and edge that uses it."""
    view = image.view()
    view.flags.writeable = False
    return view


def _information_cloud(depth: np.ndarray, K: np.ndarray, config: PoseConfig) -> o3d.geometry.PointCloud:
    """A frame's reliable depth as a cloud at the information matrices' voxel size (grown to keep at most
    ``graph_info_max_points`` points)."""
    cloud = depth_cloud(depth, K, config.reliable_depth(depth))
    return capped_voxel_down_sample(cloud, config.graph_info_voxel_m, config.graph_info_max_points)[0]
