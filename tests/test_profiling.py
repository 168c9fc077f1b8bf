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

    profiler = profiling.Profiler()
    profiling.install(profiler)
    try:
        rng = np.random.default_rng(0)
        n = 200
        with profiler.stage_scope("deblur"):
            result = rasterize(rng.normal(0, 0.3, (n, 3)) + [0, 0, 3], np.tile([1.0, 0, 0, 0], (n, 1)),
                               np.full((n, 3), -3.0), np.zeros(n), rng.uniform(size=(n, 3)),
                               np.array([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]]), np.eye(4), 64, 48)
            result.backward(d_rgb=np.ones((48, 64, 3)))
    finally:
        profiling.uninstall()
    from taichi_gs.kernels import splat

    assert not getattr(splat.Rasterizer.forward, "_profiled", False)
    sections = profiler.report()["deblur"]["sections"]
    for name in ("render forward: project", "render forward: sort", "render forward: blend", "render backward"):
        assert sections[name]["calls"] == 1, name
    json_path, md_path = profiling.write(profiler, tmp_path)
    assert "render backward" in json.loads(json_path.read_text())["deblur"]["sections"]
    assert "| render forward: blend | 1 |" in md_path.read_text()
