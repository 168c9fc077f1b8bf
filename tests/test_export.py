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
from taichi_gs.export import export_3dgs, export_colmap, export_nerfstudio, export_ply, final_stage
from taichi_gs.io.ply import read_splats, write_point_cloud, write_splats
from taichi_gs.io.load import load_sequence
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


# Hand-written consumer conventions (not the exporter's constants):
# - nerfstudio: transform_matrix is camera-to-world with camera axes x right, y up, z backwards
#   (OpenGL); pixel i spans [i, i + 1), so a ray through image point (x, y) has direction
#   ((x - cx) / fx, -(y - cy) / fy, -1) in camera axes.
# - COLMAP: images.txt holds world-to-camera (qw qx qy qz tx ty tz), camera axes x right, y down,
#   z forward; PINHOLE params fx fy cx cy, pixel i spans [i, i + 1) (centre of pixel 0 at 0.5).
# - Ours (OpenCV): pixel index u samples image coordinate u exactly.


def _pixel_ray_points(sequence, frame: int, pixels: list[tuple[int, int]]) -> np.ndarray:
    """World points that ``frame`` sees at integer pixels (u, v) by our intrinsics, at depths 1-3 m."""
    intr, pose = sequence.intrinsics, sequence.gt_poses[frame]
    points = []
    for k, (u, v) in enumerate(pixels):
        z = 1.0 + 0.5 * k
        points.append(pose[:3, :3] @ np.array([(u - intr.cx) / intr.fx * z, (v - intr.cy) / intr.fy * z, z]) + pose[:3, 3])
    return np.array(points)


PIXELS = [(0, 0), (5, 40), (63, 47), (31, 20), (17, 33)]


def test_nerfstudio_camera_sees_our_pixels_at_the_same_pixels(finished_run, tmp_path):
    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    data = json.loads(export_nerfstudio(run, sequence, tmp_path / "ns").read_text())
    assert (data["w"], data["h"], data["camera_model"]) == (64, 48, "OPENCV")
    # synth puts OpenCV's principal point at ((w - 1) / 2, (h - 1) / 2) = (31.5, 23.5): the image centre is 32, 24.
    assert (data["cx"], data["cy"]) == (32.0, 24.0)
    for frame_index in (0, 2):
        c2w = np.array(data["frames"][frame_index]["transform_matrix"])
        for (u, v), X in zip(PIXELS, _pixel_ray_points(sequence, frame_index, PIXELS)):
            x, y, z = (np.linalg.inv(c2w) @ np.append(X, 1.0))[:3]  # OpenGL camera axes
            assert z < 0  # in front of an OpenGL camera
            image_x = data["fl_x"] * x / -z + data["cx"]
            image_y = -data["fl_y"] * y / -z + data["cy"]
            assert (int(np.floor(image_x)), int(np.floor(image_y))) == (u, v)
            np.testing.assert_allclose([image_x, image_y], [u + 0.5, v + 0.5], atol=1e-6)  # the pixel's centre


def test_nerfstudio_depth_at_its_default_scale_is_metres(finished_run, tmp_path):
    import cv2

    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    dest = tmp_path / "ns"
    data = json.loads(export_nerfstudio(run, sequence, dest).read_text())
    nerfstudio_default_depth_unit_scale_factor = 1e-3  # nerfstudio's dataparser option, never read from the JSON
    for i, frame in enumerate(data["frames"]):
        raw = cv2.imread(str(dest / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED)
        assert raw.dtype == np.uint16
        metres = raw.astype(np.float64) * nerfstudio_default_depth_unit_scale_factor
        ours = sequence.depth(i)
        valid = ours > 0
        assert valid.mean() > 0.5 and np.array_equal(raw > 0, valid)
        np.testing.assert_allclose(metres[valid], ours[valid], atol=0.5e-3)  # rounded to millimetres
    assert (dest / data["ply_file_path"]).is_file()


def test_colmap_camera_sees_our_pixels_at_the_same_pixels(finished_run, tmp_path):
    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    model = export_colmap(run, sequence, tmp_path / "colmap")
    camera = (model / "cameras.txt").read_text().splitlines()[1].split()
    assert camera[:4] == ["1", "PINHOLE", "64", "48"]
    fx, fy, cx, cy = map(float, camera[4:8])
    assert (cx, cy) == (32.0, 24.0)
    rows = [line.split() for line in (model / "images.txt").read_text().splitlines() if line and not line.startswith("#")]
    assert len(rows) == len(sequence)
    for frame_index in (0, 3):
        qw, qx, qy, qz, tx, ty, tz = map(float, rows[frame_index][1:8])
        R = g.quat_to_rotmat(np.array([qw, qx, qy, qz]))  # Hamilton, as COLMAP
        for (u, v), X in zip(PIXELS, _pixel_ray_points(sequence, frame_index, PIXELS)):
            x, y, z = R @ X + np.array([tx, ty, tz])
            image = np.array([fx * x / z + cx, fy * y / z + cy])
            np.testing.assert_allclose(image, [u + 0.5, v + 0.5], atol=1e-6)
    for row in rows:
        assert (tmp_path / "colmap" / "images" / row[9]).is_file()
    points = [line for line in (model / "points3D.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(points) == 500


def test_pycolmap_reads_the_model_and_projects_like_us(finished_run, tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    model = export_colmap(run, sequence, tmp_path / "colmap")
    reconstruction = pycolmap.Reconstruction()
    reconstruction.read_text(str(model))
    assert reconstruction.num_images() == len(sequence) and reconstruction.num_points3D() == 500
    by_name = {image.name: image for image in reconstruction.images.values()}
    for frame_index in (0, 3):
        image = by_name[sequence.names[frame_index] + sequence.rgb_paths[frame_index].suffix]
        camera = reconstruction.cameras[image.camera_id]
        cam_from_world = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        for (u, v), X in zip(PIXELS, _pixel_ray_points(sequence, frame_index, PIXELS)):
            xy = camera.img_from_cam(cam_from_world * X)
            np.testing.assert_allclose(np.asarray(xy).ravel()[:2], [u + 0.5, v + 0.5], atol=1e-5)


def reference_3dgs_load_ply(path: Path, max_sh_degree: int = 3) -> dict[str, np.ndarray]:
    """The checks of the reference 3DGS ``GaussianModel.load_ply`` (plyfile, degree-3 assert), and
    the fixed binary record layout its SIBR viewer reads."""
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    vertex = ply.elements[0]
    assert vertex.name == "vertex" and ply.byte_order == "<" and not ply.text
    names = [p.name for p in vertex.properties]
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n.split("_")[-1]))
    assert len(rest) == 3 * (max_sh_degree + 1) ** 2 - 3
    sibr_layout = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(45)]
                   + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    assert names == sibr_layout and all(p.val_dtype in ("f4", "float32", "<f4") or np.dtype(p.val_dtype) == np.float32
                                        for p in vertex.properties)
    n = len(vertex.data)
    extra = np.stack([np.asarray(vertex[name]) for name in rest], axis=1).reshape(n, 3, (max_sh_degree + 1) ** 2 - 1)
    return {"xyz": np.stack([np.asarray(vertex[k]) for k in "xyz"], axis=1),
            "dc": np.stack([np.asarray(vertex[f"f_dc_{i}"]) for i in range(3)], axis=1), "rest": extra}


def test_ply_export_pads_sh_to_degree_3_for_the_reference_loader(finished_run, tmp_path):
    run, _ = finished_run
    export_ply(run, tmp_path / "ply")
    loaded = reference_3dgs_load_ply(tmp_path / "ply" / "splats.ply")
    original = read_splats(run / "refine" / "splats.ply")
    assert original.sh.shape[1] == 1  # degree 0 in the run
    np.testing.assert_array_equal(loaded["xyz"], original.means)
    np.testing.assert_array_equal(loaded["dc"], original.sh[:, 0])
    assert not loaded["rest"].any()
    assert len(read_splats(tmp_path / "ply" / "splats.ply")) == 500
    assert (tmp_path / "ply" / "points.ply").is_file()


def test_3dgs_model_folder_has_ply_cameras_and_cfg_args(finished_run, tmp_path):
    import ast

    run, seq_dir = finished_run
    sequence = load_sequence(seq_dir)
    dest = export_3dgs(run, sequence, tmp_path / "model")
    (ply,) = (dest / "point_cloud").glob("iteration_*/point_cloud.ply")
    reference_3dgs_load_ply(ply)
    cfg = (dest / "cfg_args").read_text()
    assert cfg.startswith("Namespace(") and cfg.endswith(")")
    args = {kw.arg: ast.literal_eval(kw.value) for kw in ast.parse(cfg).body[0].value.keywords}  # how viewers eval it
    assert args["sh_degree"] == 3 and Path(args["source_path"]) == (dest / "source").resolve()
    assert (Path(args["source_path"]) / "sparse" / "0" / "images.txt").is_file()
    cameras = json.loads((dest / "cameras.json").read_text())
    assert len(cameras) == len(sequence)
    for camera, pose in zip(cameras, sequence.gt_poses):  # 3DGS's camera_to_JSON: centre and camera-to-world rotation
        np.testing.assert_allclose(camera["position"], pose[:3, 3], atol=1e-9)
        np.testing.assert_allclose(camera["rotation"], pose[:3, :3], atol=1e-9)


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
