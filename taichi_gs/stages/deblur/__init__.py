"""Stage 3: deblurring, a package of its parts.

``run`` trains the scene and every training frame's exposure (:func:`run_deblur`, the stage's declaration
``STAGE``); ``config`` holds its settings and presets; ``frames`` the split and the frames at each scale,
``exposures`` the exposure offsets and colour transforms, ``density`` the density schedule and the fill of
uncovered pixels, ``gauge`` the way back to stage 2's frame, ``rprop`` the held-out fits' optimiser, ``outputs``
what the stage writes. ``model`` (the trainable scene, :class:`BlurScene`) and ``density_control`` (3DGS's
densification and pruning) are the model only stage 3 trains. The public names are importable from the package.
"""

from .config import PRESETS, DeblurConfig, scaled_schedule, with_headroom
from .density import fill_uncovered
from .exposures import shrink_mid
from .frames import choose_split, load_stage2, split_frames, training_frame
from .outputs import DeblurResult
from .run import STAGE, run_deblur

__all__ = [
    "PRESETS", "STAGE", "DeblurConfig", "DeblurResult", "choose_split", "fill_uncovered", "load_stage2",
    "run_deblur", "scaled_schedule", "shrink_mid", "split_frames", "training_frame", "with_headroom",
]
