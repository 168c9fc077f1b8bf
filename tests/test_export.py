"""Export (nerfstudio, COLMAP, PLY), camera paths and novel-view renders of a finished run."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from taichi_gs import geometry as g
from taichi_gs.camera_paths import orbit_path, trajectory_path
from taichi_gs.errors import InputError
from taichi_gs.export import OPENCV_TO_OPENGL, export_colmap, export_nerfstudio, export_ply, final_stage
from taichi_gs.io.ply import read_splats, write_point_cloud, write_splats
from taichi_gs.io.sequence import load_sequence
from taichi_gs.io.trajectory import read_tum, write_tum
from taichi_gs.pipeline import write_run_info
from taichi_gs.splats import splats_from_points
from taichi_gs.synth import SynthConfig, generate


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory) -> tuple[Path, Path]:
    """A run folder with refine/ outputs made from ground truth (no optimisation needed)."""
    root = tmp_path_factory.mktemp("export")
    seq_dir = generate(SynthConfig(width=64, height=48, frames=4, trajectory="handheld", blur="moderate", seed=2),
                       root / "seq")
    sequence = load_sequence(seq_dir)
    run = root / "run"
    write_run_info(run, sequence)
    write_tum(run / "refine" / "trajectory.txt", sequence.timestamps, sequence.gt_poses)
    rng = np.random.default_rng(0)
    points = g.transform(sequence.gt_poses[0], rng.uniform(-1, 1, (500, 3)) + [0, 0, 2.5])  # in view of frame 0
    colors = rng.uniform(0, 1, (500, 3))
    write_point_cloud(run / "refine" / "points.ply", points, colors)
    write_splats(run / "refine" / "splats.ply", splats_from_points(points, colors, scale=0.05))
    return run, seq_dir


def test_nerfstudio_transforms_hold_opengl_poses_and_existing_files(finished_run, tmp_path):
    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    path = export_nerfstudio(run, sequence, tmp_path / "ns")
    data = json.loads(path.read_text())
    assert (data["w"], data["h"], data["fl_x"]) == (64, 48, sequence.intrinsics.fx)
    assert data["depth_unit_scale_factor"] == pytest.approx(1 / sequence.intrinsics.depth_scale)
    assert len(data["frames"]) == len(sequence)
    for frame, pose in zip(data["frames"], sequence.gt_poses):
        np.testing.assert_allclose(np.array(frame["transform_matrix"]) @ OPENCV_TO_OPENGL, pose, atol=1e-9)
        assert (tmp_path / "ns" / frame["file_path"]).is_file()
        assert (tmp_path / "ns" / frame["depth_file_path"]).is_file()
    assert (tmp_path / "ns" / data["ply_file_path"]).is_file()


def test_colmap_images_are_world_to_camera_and_points_listed(finished_run, tmp_path):
    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    model = export_colmap(run, sequence, tmp_path / "colmap")
    assert (model / "cameras.txt").read_text().splitlines()[1].startswith("1 PINHOLE 64 48 ")
    rows = [line.split() for line in (model / "images.txt").read_text().splitlines() if line and not line.startswith("#")]
    assert len(rows) == len(sequence)
    for row, pose in zip(rows, sequence.gt_poses):
        qw, qx, qy, qz, tx, ty, tz = map(float, row[1:8])
        world_to_camera = g.pose_from_rt(g.quat_to_rotmat(np.array([qw, qx, qy, qz])), np.array([tx, ty, tz]))
        np.testing.assert_allclose(g.invert(world_to_camera), pose, atol=1e-9)
        assert (tmp_path / "colmap" / "images" / row[9]).is_file()
    points = [line for line in (model / "points3D.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(points) == 500


def test_ply_export_copies_splats_readably(finished_run, tmp_path):
    run, _ = finished_run
    export_ply(run, tmp_path / "ply")
    assert len(read_splats(tmp_path / "ply" / "splats.ply")) == 500


def test_export_of_an_unfinished_run_is_a_clear_error(tmp_path):
    with pytest.raises(InputError, match="no finished stage"):
        final_stage(tmp_path)


def test_export_refuses_poses_of_another_sequence(finished_run, tmp_path):
    run, seq_dir = finished_run
    other = tmp_path / "run"
    shutil.copytree(run, other)
    t, poses = read_tum(run / "refine" / "trajectory.txt")
    write_tum(other / "refine" / "trajectory.txt", t[:-1], poses[:-1])
    with pytest.raises(InputError, match="do not match"):
        export_nerfstudio(other, load_sequence(seq_dir), tmp_path / "ns")


def test_trajectory_path_runs_from_first_to_last_pose():
    poses = np.stack([g.se3_exp(np.array([0.1 * i, 0, 0, 0, 0.05 * i, 0])) for i in range(5)])
    path = trajectory_path(poses, 9)
    np.testing.assert_allclose(path[0], poses[0], atol=1e-12)
    np.testing.assert_allclose(path[-1], poses[-1], atol=1e-9)
    np.testing.assert_allclose(path[2], poses[1], atol=1e-9)


def test_orbit_cameras_circle_the_mean_camera_and_look_at_one_point():
    poses = np.stack([g.se3_exp(np.array([0.05 * i, 0, 0, 0, 0, 0])) for i in range(5)])
    points = np.array([[0.0, 0.0, 3.0], [0.1, 0.0, 3.0], [0.0, 0.1, 3.0]])
    path = orbit_path(poses, points, 8, radius_fraction=0.1)
    centre = poses[:, :3, 3].mean(axis=0)
    target = centre + np.array([0, 0, 3.0])
    for T in path:
        assert np.linalg.norm(T[:3, 3] - centre) == pytest.approx(0.3)
        np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
        to_target = (target - T[:3, 3]) / np.linalg.norm(target - T[:3, 3])
        np.testing.assert_allclose(T[:3, 2], to_target, atol=1e-12)


def test_render_command_writes_a_png_per_view_and_a_gif(finished_run, tmp_path):
    from typer.testing import CliRunner

    from taichi_gs.cli import app

    run, _ = finished_run
    local = tmp_path / "run"
    shutil.copytree(run, local)
    result = CliRunner().invoke(app, ["--arch", "cpu", "render", str(local), "--frames", "5", "--path", "trajectory"])
    assert result.exit_code == 0, result.output
    frames = sorted((local / "render" / "trajectory").glob("*.png"))
    assert len(frames) == 5 and (local / "render" / "trajectory.gif").is_file()
    import imageio.v3 as iio

    image = iio.imread(frames[0])
    assert image.shape == (48, 64, 3) and image.std() > 5  # the splats are visible, not a blank frame
