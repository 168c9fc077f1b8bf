"""The command line's closed choices (taichi_gs/choices.py): each name it offers has an implementation behind it,
a name outside them is refused where it is acted on, and reading the choices costs the start-up no heavy import."""

from __future__ import annotations

import subprocess
import sys

import pytest

from taichi_gs import synth, synth_scenes
from taichi_gs.choices import BLUR_LEVELS, PRESET_NAMES, SCENES, TRAJECTORIES
from taichi_gs.stages.declaration import STAGE_NAMES, declared


def test_every_synth_choice_has_a_generator():
    assert tuple(synth._PATHS) == TRAJECTORIES
    assert tuple(synth.BLUR_TARGET_WIDTH_FRACTION) == BLUR_LEVELS
    assert tuple(synth_scenes._BUILDERS) == SCENES


@pytest.mark.parametrize("stage", STAGE_NAMES)
def test_every_stage_declares_the_presets_the_cli_offers(stage):
    assert sorted(declared(stage).presets) == sorted(PRESET_NAMES)


def test_render_path_refuses_an_unknown_camera_path(tmp_path):
    from taichi_gs.export import render_path

    with pytest.raises(ValueError, match="'spiral'.*orbit, trajectory"):
        render_path(tmp_path, None, "spiral", 2)  # type: ignore[arg-type]
    assert not (tmp_path / "render").exists()


def test_the_cli_imports_no_numpy_opencv_taichi_or_pipeline_at_start_up():
    heavy = ("numpy", "cv2", "taichi", "open3d", "taichi_gs.pipeline", "taichi_gs.export", "taichi_gs.synth")
    probe = f"import sys, taichi_gs.cli; print(' '.join(m for m in {heavy!r} if m in sys.modules))"
    loaded = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert loaded == []
