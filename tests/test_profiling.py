"""--profile: exclusive section times, the forward split by phase, and the files it writes."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from taichi_gs import profiling


def test_nested_sections_are_counted_exclusively_and_the_rest_is_host_work():
    profiler = profiling.Profiler()
    with profiler.stage_scope("refine"):
        with profiler.section("outer"):
            time.sleep(0.05)
            with profiler.section("inner"):
                time.sleep(0.1)
        time.sleep(0.03)
    report = profiler.report()["refine"]
    sections = report["sections"]
    assert sections["inner"]["wall_s"] == pytest.approx(0.1, abs=0.03)
    assert sections["outer"]["wall_s"] == pytest.approx(0.05, abs=0.03)
    assert sections["other host work"]["wall_s"] == pytest.approx(0.03, abs=0.03)
    assert sum(s["wall_s"] for s in sections.values()) == pytest.approx(report["wall_s"], rel=1e-6)
    assert list(sections)[0] == "inner" and sections["inner"]["calls"] == 1
    # inclusive: a parent with its nested sections (how long a test-view fit took, renders included)
    assert sections["outer"]["inclusive_wall_s"] == pytest.approx(0.15, abs=0.04)
    assert sections["inner"]["inclusive_wall_s"] == pytest.approx(sections["inner"]["wall_s"], rel=1e-9)


def test_profiled_renders_split_the_forward_by_phase_and_are_written(tmp_path):
    from taichi_gs.render import rasterize

    rng = np.random.default_rng(0)
    n = 200
    scene = (rng.normal(0, 0.3, (n, 3)) + [0, 0, 3], np.tile([1.0, 0, 0, 0], (n, 1)), np.full((n, 3), -3.0),
             np.zeros(n), rng.uniform(size=(n, 3)), np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]), np.eye(4),
             64, 48)
    profiler = profiling.Profiler()
    profiling.install(profiler)
    try:
        with profiler.stage_scope("deblur"):
            rasterize(*scene).backward(d_rgb=np.ones((48, 64, 3)))
    finally:
        profiling.uninstall()
    with profiler.stage_scope("deblur"):
        rasterize(*scene).backward(d_rgb=np.ones((48, 64, 3)))  # uninstalled: not timed
    sections = profiler.report()["deblur"]["sections"]
    for name in ("render forward: project", "render forward: sort", "render forward: blend", "render backward"):
        assert sections[name]["calls"] == 1, name
    json_path, md_path = profiling.write(profiler, tmp_path)
    assert "render backward" in json.loads(json_path.read_text())["deblur"]["sections"]
    assert "| render forward: blend | 1 |" in md_path.read_text()


def test_timed_functions_pass_through_without_a_profiler_and_book_to_the_stage_in_scope():
    @profiling.timed("work")
    def work(x: int) -> int:
        return x + 1

    @profiling.stage_scope
    def run(stage: str, x: int) -> int:
        return work(x)

    assert run("pose", 1) == 2  # nothing installed: nothing recorded anywhere
    profiler = profiling.Profiler()
    profiling.install(profiler)
    try:
        assert run("pose", 2) == 3 and work(3) == 4
    finally:
        profiling.uninstall()
    assert run("pose", 4) == 5
    report = profiler.report()
    assert report["pose"]["sections"]["work"]["calls"] == 1
    assert report["outside stages"]["sections"]["work"]["calls"] == 1
    assert work.__name__ == "work" and run.__name__ == "run"
