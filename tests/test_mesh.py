"""Mesh export: TSDF fusion of the input depth at the run's poses, coloured from the sharp renders."""

from __future__ import annotations

import numpy as np
import open3d as o3d

from format_fixtures import PLANE_Z, texture, truth_poses, write_own
from taichi_gs.io.images import to_uint8, write_png
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import write_tum
from taichi_gs.mesh import export_mesh, mesh_view
from taichi_gs.pipeline import write_run_info


def test_mesh_lies_on_the_surface_and_takes_the_sharp_colours(tmp_path):
    folder = tmp_path / "seq"
    write_own(folder)
    seq = load_sequence(folder)
    run = tmp_path / "run"
    write_run_info(run, seq)
    write_tum(run / "pose" / "trajectory.txt", seq.timestamps, truth_poses())
    for i, name in enumerate(seq.names):  # "sharp renders": the input inverted, so using them is visible
        write_png(run / "deblur" / "renders" / "sharp" / f"{name}.png", to_uint8(1.0 - seq.color(i)))
    path = export_mesh(run, seq, run / "export" / "mesh", voxel_size=0.025)
    mesh = o3d.io.read_triangle_mesh(str(path))
    vertices, colors = np.asarray(mesh.vertices), np.asarray(mesh.vertex_colors)
    assert len(mesh.triangles) > 100 and mesh.has_vertex_normals()
    assert np.abs(vertices[:, 2] - PLANE_Z).max() < 0.01  # 2.5 cm voxels: the zero crossing is interpolated
    expected = 1.0 - texture(vertices[:, 0], vertices[:, 1])
    assert np.abs(colors - expected).mean() < 0.04
    assert (run / "report" / "mesh_view.png").is_file()
    view = mesh_view(mesh, seq.K(), truth_poses()[1], 80, 60) / 255.0  # seen from a frame's own camera
    seen = view.sum(axis=2) > 0
    assert seen.mean() > 0.6
    assert np.abs(view - (1.0 - seq.color(1)))[seen].mean() < 0.06
