"""Stage 2: global refinement of poses and geometry, a package of its parts.

``run`` trains fixed-scale Gaussians and the poses against each frame's depth (:func:`run_refine`, the stage's
declaration ``STAGE``); ``config`` holds its settings and presets; ``accept`` [ours] keeps the refined trajectory
only where stage 1's verification scores it no worse; ``model`` (:class:`DepthRefiner`) is the trainable scene
only stage 2 trains. The public names are importable from the package.
"""

from .accept import accept_refined_poses
from .config import FAST_TRAINING_PER_FRAME, PRESETS, RefineConfig
from .run import (
    STAGE,
    RefineResult,
    deskewed_for_training,
    gaussian_footprint_px,
    load_stage1,
    resolve_config,
    run_refine,
)

__all__ = [
    "FAST_TRAINING_PER_FRAME", "PRESETS", "STAGE", "RefineConfig", "RefineResult", "accept_refined_poses",
    "deskewed_for_training", "gaussian_footprint_px", "load_stage1", "resolve_config", "run_refine",
]
