"""The pipeline's bookkeeping: which stages a rerun skips, resumes, or starts again, and why."""

from __future__ import annotations

import dataclasses
import json
import shutil
from contextlib import contextmanager

import cv2
import numpy as np
import pytest

from taichi_gs import pipeline
from taichi_gs.errors import InputError
from taichi_gs.io.load import load_sequence
from taichi_gs.io.sequence import IntrinsicsOverride
from taichi_gs.stages.declaration import StageRun, declared
from taichi_gs.pipeline import (
    STAGES, open_run_sequence, reconstruct, resolve_sections, resolve_stage, run_stage, stage_done,
    stage_inputs,
)


@contextmanager
def _no_progress(description, total):
    yield lambda *args, **kwargs: None


@pytest.fixture
def fake_stages(monkeypatch):
    """Stages that only write their output files (content depends on config and input); records which ran."""
    calls: list[str] = []

    def execute(stage, context):
        calls.append(stage)
        out, sequence = context.out, context.sequence
        (out / stage).mkdir(parents=True, exist_ok=True)
        content = json.dumps([dataclasses.asdict(context.config), str(sequence.root), sequence.intrinsics.depth_scale],
                             default=str)
        for name in declared(stage).outputs:
            (out / stage / name).write_text(content)
        return StageRun("fake")

    monkeypatch.setattr(pipeline, "_execute", execute)
    return calls


def test_rerun_skips_done_stages_and_a_config_change_reruns_from_there(own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    sections = resolve_sections("fast")
    reports = reconstruct(sequence, tmp_path, sections, _no_progress)
    assert fake_stages == list(STAGES) and all(r.ran for r in reports)
    assert (tmp_path / "config.toml").is_file() and (tmp_path / "run.json").is_file()

    fake_stages.clear()
    reports = reconstruct(sequence, tmp_path, sections, _no_progress)
    assert fake_stages == [] and not any(r.ran for r in reports)

    changed = dict(sections, refine=dataclasses.replace(sections["refine"], seed=7))
    reconstruct(sequence, tmp_path, changed, _no_progress)
    assert fake_stages == ["refine", "deblur"]


def test_force_reruns_from_the_named_stage(own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    sections = resolve_sections("fast")
    reconstruct(sequence, tmp_path, sections, _no_progress)
    fake_stages.clear()
    reconstruct(sequence, tmp_path, sections, _no_progress, force="deblur")
    assert fake_stages == ["deblur"]
    with pytest.raises(InputError, match="unknown stage"):
        reconstruct(sequence, tmp_path, sections, _no_progress, force="sharpen")


def test_a_stage_with_a_missing_output_or_a_corrupt_marker_is_not_done(own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    sections = resolve_sections("fast")
    reconstruct(sequence, tmp_path, sections, _no_progress)
    refine = resolve_stage("refine", sections)
    assert refine.voxel_size == sections["pose"].voxel_size_m  # filled in from stage 1's config
    fingerprint = stage_inputs("refine", sequence, tmp_path, refine)
    assert stage_done(tmp_path, "refine", fingerprint)
    (tmp_path / "refine" / "splats.ply").unlink()
    assert not stage_done(tmp_path, "refine", fingerprint)
    (tmp_path / "deblur" / "done.json").write_text("{not json")
    assert not stage_done(tmp_path, "deblur", stage_inputs("deblur", sequence, tmp_path, sections["deblur"]))
    fake_stages.clear()
    reconstruct(sequence, tmp_path, sections, _no_progress)
    assert fake_stages == ["refine", "deblur"]


def test_changed_input_files_rerun_every_stage(own_layout, tmp_path, fake_stages):
    sections = resolve_sections("fast")
    reconstruct(load_sequence(own_layout), tmp_path, sections, _no_progress)
    depth = own_layout / "depth" / "000001.png"
    cv2.imwrite(str(depth), np.full((30, 40), 2.5 * 5000, dtype=np.uint16))  # the user fixed a frame
    fake_stages.clear()
    reconstruct(load_sequence(own_layout), tmp_path, sections, _no_progress)
    assert fake_stages == list(STAGES)


def test_a_corrected_depth_scale_reruns_every_stage(own_layout, tmp_path, fake_stages):
    sections = resolve_sections("fast")
    reconstruct(load_sequence(own_layout), tmp_path, sections, _no_progress)
    fake_stages.clear()
    reconstruct(load_sequence(own_layout, IntrinsicsOverride(depth_scale=4000.0)), tmp_path, sections, _no_progress)
    assert fake_stages == list(STAGES)
    assert open_run_sequence(tmp_path).intrinsics.depth_scale == 4000.0  # later commands reopen it the same way


def test_a_rolling_shutter_readout_written_into_intrinsics_json_reruns_every_stage(own_layout, tmp_path, fake_stages):
    """[ours] The own layout's ``readout_ms`` changes what the fast preset computes, so a run made before the user
    wrote it is not current; a run without one keeps its fingerprint (the key is recorded only when given)."""
    sections = resolve_sections("fast")
    reconstruct(load_sequence(own_layout), tmp_path, sections, _no_progress)
    fake_stages.clear()
    reconstruct(load_sequence(own_layout), tmp_path, sections, _no_progress)
    assert fake_stages == []
    intrinsics = own_layout / "intrinsics.json"
    intrinsics.write_text(json.dumps({**json.loads(intrinsics.read_text()), "readout_ms": 20.0}))
    reconstruct(load_sequence(own_layout), tmp_path, sections, _no_progress)
    assert fake_stages == list(STAGES)


def test_another_input_into_a_finished_run_folder_is_refused(own_layout, tmp_path, fake_stages):
    sections = resolve_sections("fast")
    out = tmp_path / "run"
    reconstruct(load_sequence(own_layout), out, sections, _no_progress)
    other = tmp_path / "other"
    shutil.copytree(own_layout, other)
    before = (out / "run.json").read_text()
    with pytest.raises(InputError, match="holds the results of another input sequence"):
        reconstruct(load_sequence(other), out, sections, _no_progress)
    assert (out / "run.json").read_text() == before


def test_a_rerun_stage_1_invalidates_stages_2_and_3(own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    sections = resolve_sections("fast")
    reconstruct(sequence, tmp_path, sections, _no_progress)
    pose = dataclasses.replace(sections["pose"], max_points=1234)
    run_stage("pose", sequence, tmp_path, pose, _no_progress)  # as `taichi-gs pose` with other settings
    assert not (tmp_path / "refine").exists() and not (tmp_path / "deblur").exists()
    fake_stages.clear()
    reconstruct(sequence, tmp_path, dict(sections, pose=pose), _no_progress)
    assert fake_stages == ["refine", "deblur"]


def test_replaced_stage_1_outputs_invalidate_stage_2(own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    sections = resolve_sections("fast")
    reconstruct(sequence, tmp_path, sections, _no_progress)
    (tmp_path / "pose" / "trajectory.txt").write_text("# edited by hand\n")
    fake_stages.clear()
    reconstruct(sequence, tmp_path, sections, _no_progress)
    assert fake_stages == ["refine", "deblur"]


def test_caches_made_from_other_inputs_are_not_resumed(own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    section = resolve_sections("fast")["pose"]
    cache = tmp_path / "pose" / "pairs" / "000000.json"
    cache.parent.mkdir(parents=True)
    cache.write_text("{}")  # left by a run on other input (no inputs.json records what it belongs to)
    run_stage("pose", sequence, tmp_path, section, _no_progress)
    assert not cache.exists()
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text("{}")  # a cache of this very run, interrupted: kept for the resume
    (tmp_path / "pose" / "done.json").unlink()
    run_stage("pose", sequence, tmp_path, section, _no_progress)
    assert cache.exists()


def test_config_file_overrides_presets_and_rejects_unknown_keys(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("[refine]\niterations_per_frame = 3\n")
    assert resolve_sections("paper", good)["refine"].iterations_per_frame == 3
    bad = tmp_path / "bad.toml"
    bad.write_text("[refine]\niterations = 3\n")
    with pytest.raises(InputError, match="unknown key 'iterations'"):
        resolve_sections("fast", bad)
    with pytest.raises(InputError, match="unknown preset"):
        resolve_sections("turbo")


@pytest.mark.parametrize("table, line, message", [
    ("pose", 'flow_preset = "nonsense"', "flow_preset"),
    ("pose", "voxel_size_m = 0.0", "voxel_size_m"),
    ("refine", "lr_means = 1e12", "learning rate"),
    ("refine", "lr_means = nan", "not a finite number"),
    ("deblur", "k = 0", "k = 0"),
    ("deblur", "holdout_every = 1", "holdout_every"),
    ("pose", "min_depth_m = 20.0", "min_depth_m must be below max_depth_m"),
    ("pose", "graph_info_max_points = -5", "graph_info_max_points = -5 must be at least 0"),
    ("pose", "threads = -1", "threads = -1 must be at least 0"),
    ("pose", "graph_long_spans = [1]", "graph_long_spans"),
    ("pose", "graph_long_every = 0", "graph_long_every"),
])
def test_bad_config_values_are_refused_before_any_work(tmp_path, table, line, message):
    path = tmp_path / "bad.toml"
    path.write_text(f"[{table}]\n{line}\n")
    for only in (STAGES, ("pose",)):  # every table is checked, whichever stage command reads the file
        with pytest.raises(InputError, match=message):
            resolve_sections("fast", path, only=only)


def test_presets_pass_their_own_checks():
    for preset in ("fast", "paper"):
        assert set(resolve_sections(preset)) == set(STAGES)


def test_one_config_file_serves_every_stage_command(tmp_path):
    both = tmp_path / "all.toml"
    both.write_text("[refine]\nseed = 3\n\n[deblur]\nk = 5\n")
    assert set(resolve_sections("fast", both, only=("refine",))) == {"refine"}
    assert resolve_sections("fast", both, only=("deblur",))["deblur"].k == 5


def test_a_corrupt_run_record_is_a_clear_error(tmp_path):
    (tmp_path / "run.json").write_text("\x00garbage")
    with pytest.raises(InputError, match="corrupt run record"):
        open_run_sequence(tmp_path)
    with pytest.raises(InputError, match="run folder not found"):
        open_run_sequence(tmp_path / "missing")


def test_every_stage_is_declared_once_with_both_presets():
    for name in STAGES:
        stage = declared(name)
        assert stage.name == name and stage.title.startswith("stage ")
        assert set(stage.presets) == {"fast", "paper"}
        assert all(type(config) is stage.config_type for config in stage.presets.values())
        assert stage.outputs and "trajectory.txt" in stage.outputs
    with pytest.raises(ValueError, match="unknown stage"):
        declared("sharpen")


def test_the_pipeline_writes_every_stage_config_and_refine_takes_the_voxel_stage_1_ran_with(
        own_layout, tmp_path, fake_stages):
    sequence = load_sequence(own_layout)
    sections = resolve_sections("fast")
    pose = dataclasses.replace(sections["pose"], voxel_size_m=0.031)
    run_stage("pose", sequence, tmp_path, pose, _no_progress)  # as `taichi-gs pose --config` with its own voxel
    assert "voxel_size_m = 0.031" in (tmp_path / "pose" / "config.toml").read_text()
    assert resolve_stage("refine", sections).voxel_size == sections["pose"].voxel_size_m  # no run folder yet
    refine = resolve_stage("refine", sections, tmp_path)  # as `taichi-gs refine` without that config
    assert refine.voxel_size == 0.031
    run_stage("refine", sequence, tmp_path, refine, _no_progress)
    assert "voxel_size = 0.031" in (tmp_path / "refine" / "config.toml").read_text()
    run_stage("deblur", sequence, tmp_path, sections["deblur"], _no_progress)
    assert (tmp_path / "deblur" / "config.toml").is_file()
