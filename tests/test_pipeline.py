"""The pipeline's bookkeeping: which stages a rerun skips, resumes, or starts again."""

from __future__ import annotations

import dataclasses
from contextlib import contextmanager
from pathlib import Path

import pytest

from taichi_gs import pipeline
from taichi_gs.errors import InputError
from taichi_gs.pipeline import STAGE_OUTPUTS, STAGES, reconstruct, resolve_sections, resolve_stage, stage_done


@contextmanager
def _no_progress(description, total):
    yield lambda *args, **kwargs: None


class _FakeSequence:
    root = Path("/nonexistent/sequence")


@pytest.fixture
def fake_stages(monkeypatch):
    """Stages that only write their output files; records which ran."""
    calls: list[str] = []

    def run_stage(stage, sequence, out, section, progress, poses=None, points=None):
        calls.append(stage)
        for name in STAGE_OUTPUTS[stage]:
            (out / stage).mkdir(parents=True, exist_ok=True)
            (out / stage / name).write_text("x")
        pipeline._mark_done(out, stage, section, 0.1, "cpu", "fake")
        return section, "fake"

    monkeypatch.setattr(pipeline, "run_stage", run_stage)
    return calls


def test_rerun_skips_done_stages_and_a_config_change_reruns_from_there(tmp_path, fake_stages):
    sections = resolve_sections("fast")
    reports = reconstruct(_FakeSequence(), tmp_path, sections, _no_progress)
    assert fake_stages == list(STAGES) and all(r.ran for r in reports)
    assert (tmp_path / "config.toml").is_file() and (tmp_path / "run.json").is_file()

    fake_stages.clear()
    reports = reconstruct(_FakeSequence(), tmp_path, sections, _no_progress)
    assert fake_stages == [] and not any(r.ran for r in reports)

    changed = dict(sections, refine=dataclasses.replace(sections["refine"], seed=7))
    reconstruct(_FakeSequence(), tmp_path, changed, _no_progress)
    assert fake_stages == ["refine", "deblur"]


def test_force_reruns_from_the_named_stage(tmp_path, fake_stages):
    sections = resolve_sections("fast")
    reconstruct(_FakeSequence(), tmp_path, sections, _no_progress)
    fake_stages.clear()
    reconstruct(_FakeSequence(), tmp_path, sections, _no_progress, force="deblur")
    assert fake_stages == ["deblur"]
    with pytest.raises(InputError, match="unknown stage"):
        reconstruct(_FakeSequence(), tmp_path, sections, _no_progress, force="sharpen")


def test_a_stage_with_a_missing_output_or_no_marker_is_not_done(tmp_path, fake_stages):
    sections = resolve_sections("fast")
    reconstruct(_FakeSequence(), tmp_path, sections, _no_progress)
    refine = resolve_stage("refine", sections)
    assert refine.voxel_size == sections["pose"].voxel_size_m  # filled in from stage 1's config
    assert stage_done(tmp_path, "refine", refine)
    (tmp_path / "refine" / "splats.ply").unlink()
    assert not stage_done(tmp_path, "refine", refine)
    (tmp_path / "deblur" / "done.json").write_text("{not json")
    assert not stage_done(tmp_path, "deblur", sections["deblur"])
    fake_stages.clear()
    reconstruct(_FakeSequence(), tmp_path, sections, _no_progress)
    assert fake_stages == ["refine", "deblur"]


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


def test_one_config_file_serves_every_stage_command(tmp_path):
    both = tmp_path / "all.toml"
    both.write_text("[refine]\nseed = 3\n\n[deblur]\nk = 5\n")
    assert set(resolve_sections("fast", both, only=("refine",))) == {"refine"}
    assert resolve_sections("fast", both, only=("deblur",))["deblur"].k == 5
