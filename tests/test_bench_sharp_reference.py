"""bench/sharp_reference.py: the merged sequence puts the references on the test views of ``--holdout h`` and keeps
every frame with its own pose, and a reference whose reference pose is off by a degree is placed by depth ICP."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from sharp_reference import merge, place_references, rotation_deg, held_out_positions  # noqa: E402

from taichi_gs.io.load import load_sequence  # noqa: E402
from taichi_gs.synth import SynthConfig, generate  # noqa: E402


def _clip(folder: Path, frames: int, seed: int, size: tuple[int, int] = (64, 48)) -> Path:
    generate(SynthConfig(width=size[0], height=size[1], frames=frames, trajectory="handheld", blur="none", seed=seed),
             folder)
    return folder


def test_the_merged_sequence_puts_the_references_on_the_test_views(tmp_path):
    stretch, references = _clip(tmp_path / "stretch", 6, 1), _clip(tmp_path / "references", 2, 2)
    test = merge(load_sequence(stretch), load_sequence(references), tmp_path / "merged", every=4)
    assert test == held_out_positions(8, 4) == [1, 5]
    merged, a, b = (load_sequence(tmp_path / name) for name in ("merged", "stretch", "references"))
    assert len(merged) == 8 and np.all(np.diff(merged.timestamps) > 0)
    sources = [(a, 0), (b, 0), (a, 1), (a, 2), (a, 3), (b, 1), (a, 4), (a, 5)]
    for position, (source, i) in enumerate(sources):
        assert np.array_equal(merged.color(position), source.color(i))
        assert np.array_equal(merged.depth(position), source.depth(i))
        assert np.allclose(merged.gt_poses[position], source.gt_poses[i], atol=1e-6)


def test_references_that_do_not_fill_the_test_views_are_refused(tmp_path):
    stretch, references = _clip(tmp_path / "stretch", 6, 1), _clip(tmp_path / "references", 2, 2)
    try:
        merge(load_sequence(stretch), load_sequence(references), tmp_path / "merged", every=3)  # views 1, 4, 7
    except SystemExit as error:
        assert "do not fill the 3 test views" in str(error)
    else:
        raise AssertionError("merge accepted 2 references for 3 test views")


def test_a_reference_is_placed_by_depth_icp_in_stage_1s_frame(tmp_path):
    clip = _clip(tmp_path / "clip", 8, 3, size=(160, 120))  # 64x48 leaves ICP too few points
    stretch, references = load_sequence(clip, count=6), load_sequence(clip, first=6, count=2)
    world = np.eye(4)
    world[:3, :3] = cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0]
    world[:3, 3] = [0.3, -0.1, 0.2]
    stretch_poses = np.array([world @ pose for pose in stretch.gt_poses])  # stage 1's frame: another world
    truth = np.array([world @ pose for pose in references.gt_poses])
    lagged = references.gt_poses.copy()
    for pose in lagged:  # the references' own poses off by 1 degree (a pan)
        pose[:3, :3] = pose[:3, :3] @ cv2.Rodrigues(np.array([0.0, np.radians(1.0), 0.0]))[0]
    references.gt_poses = lagged
    placed, lines = place_references(stretch, references, stretch_poses)
    assert len(lines) == 2
    for found, expected in zip(placed, truth):
        assert rotation_deg(found, expected) < 0.3
        assert np.linalg.norm(found[:3, 3] - expected[:3, 3]) < 0.01
    assert rotation_deg(world @ lagged[0], truth[0]) > 0.9  # the start was a degree off


def test_the_merged_sequence_keeps_no_rolling_shutter_readout(tmp_path):
    """An imported Kinect v1 stretch gives ``readout_ms`` in its intrinsics.json; the merged sequence's made-up
    stamps would give its frames wrong velocities, so it keeps the intrinsics without it."""
    stretch, references = _clip(tmp_path / "stretch", 6, 1), _clip(tmp_path / "references", 2, 2)
    intrinsics = json.loads((stretch / "intrinsics.json").read_text())
    (stretch / "intrinsics.json").write_text(json.dumps({**intrinsics, "readout_ms": 25.0}))
    assert load_sequence(stretch).source["readout_ms"] == 25.0
    merge(load_sequence(stretch), load_sequence(references), tmp_path / "merged", every=4)
    assert json.loads((tmp_path / "merged" / "intrinsics.json").read_text()) == intrinsics
    assert "readout_ms" not in load_sequence(tmp_path / "merged").source
