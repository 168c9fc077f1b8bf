"""Stage 1: local pose, a package of its parts.

``run`` runs them over a sequence (:func:`run_pose`, the stage's declaration ``STAGE``); ``config`` holds its
settings and presets; ``pair`` one pair's estimate, ``frames`` the window of frames, ``edges`` the pose
graph's edges, ``losses`` and ``solver`` the method's terms and their Levenberg-Marquardt; ``flow`` (optical
flow), ``icp`` (multi-scale ICP, RGB-D odometry, clouds), ``verify`` (one score for any relative pose) and
``graph`` (the robust pose graph) are the helpers only stage 1 builds on (stage 2's acceptance test reuses
``verify``). The public names are importable from the package.
"""

from .config import METHOD_ONLY, PAPER, PRESETS, PoseConfig
from .run import (
    DEFAULT_MAX_THREADS,
    STAGE,
    PoseResult,
    chain_poses,
    fuse_points,
    pose_readout_ms,
    run_pose,
    stage_threads,
    weak_pair_warnings,
)

__all__ = [
    "DEFAULT_MAX_THREADS", "METHOD_ONLY", "PAPER", "PRESETS", "STAGE", "PoseConfig", "PoseResult", "chain_poses",
    "fuse_points", "pose_readout_ms", "run_pose", "stage_threads", "weak_pair_warnings",
]
