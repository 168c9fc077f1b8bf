"""Writers and readers: TUM trajectories, point-cloud PLY, 3DGS PLY, atomic writes."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from taichi_gs import geometry as g
from taichi_gs.errors import InputError
from taichi_gs.io.atomic import atomic_path
from taichi_gs.io.ply import read_ply, read_point_cloud, read_splats, write_point_cloud, write_splats
from taichi_gs.io.trajectory import check_frame_times, read_tum, write_tum
from taichi_gs.splats import Splats, splats_from_points
from taichi_gs.stages.deblur import load_stage2


def random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return np.stack([g.se3_exp(rng.normal(size=6)) for _ in range(n)])


def test_tum_round_trip(tmp_path):
    poses = random_poses(7)
    stamps = np.arange(7) / 30.0 + 1e9
    write_tum(tmp_path / "t.txt", stamps, poses, header="test")
    t, p = read_tum(tmp_path / "t.txt")
    assert np.allclose(t, stamps, atol=1e-6) and np.allclose(p, poses, atol=1e-8)
    # TUM order is tx ty tz qx qy qz qw, with w last.
    row = (tmp_path / "t.txt").read_text().splitlines()[1].split()
    assert np.allclose([float(row[7]), *map(float, row[4:7])], g.rotmat_to_quat(poses[0][:3, :3]), atol=1e-8)


def test_tum_reader_rejects_short_lines(tmp_path):
    (tmp_path / "t.txt").write_text("0 1 2 3\n")
    with pytest.raises(InputError, match="line 1 has 4 values"):
        read_tum(tmp_path / "t.txt")


def test_point_cloud_round_trip_and_open3d_reads_it(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(100, 3)).astype(np.float32)
    cols = rng.uniform(size=(100, 3)).astype(np.float32)
    write_point_cloud(tmp_path / "p.ply", pts, cols)
    p, c = read_point_cloud(tmp_path / "p.ply")
    assert np.array_equal(p, pts) and np.allclose(c, cols, atol=0.5 / 255 + 1e-7)
    cloud = o3d.io.read_point_cloud(str(tmp_path / "p.ply"))
    assert np.allclose(np.asarray(cloud.points), pts, atol=1e-6) and len(cloud.colors) == 100


def test_point_clouds_that_open3d_writes_in_ascii_are_read(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(20, 3))
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    cloud.colors = o3d.utility.Vector3dVector(rng.uniform(size=(20, 3)))
    assert o3d.io.write_point_cloud(str(tmp_path / "a.ply"), cloud, write_ascii=True)
    assert b"format ascii" in (tmp_path / "a.ply").read_bytes()[:200]
    p, c = read_point_cloud(tmp_path / "a.ply")
    np.testing.assert_allclose(p, pts, atol=1e-5)
    np.testing.assert_allclose(c, np.asarray(cloud.colors), atol=0.5 / 255 + 1e-6)


def test_big_endian_and_vertex_after_another_element_are_read(tmp_path):
    from plyfile import PlyData, PlyElement

    vertex = np.array([(1.0, 2.0, 3.0), (4.0, 5.0, 6.0)], dtype=[("x", ">f4"), ("y", ">f4"), ("z", ">f4")])
    camera = np.array([(1.5,)], dtype=[("focal", ">f4")])
    PlyData([PlyElement.describe(camera, "camera"), PlyElement.describe(vertex, "vertex")],
            byte_order=">").write(str(tmp_path / "b.ply"))
    p, c = read_point_cloud(tmp_path / "b.ply")
    np.testing.assert_array_equal(p, [[1, 2, 3], [4, 5, 6]])
    assert np.all(c == 0.5)  # no colours: grey


def test_unreadable_ply_is_an_input_error(tmp_path):
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nend_header\n\x00")
    with pytest.raises(InputError, match="bad.ply"):
        read_point_cloud(tmp_path / "bad.ply")
    (tmp_path / "text.ply").write_text("hello")
    with pytest.raises(InputError, match="PLY"):
        read_ply(tmp_path / "text.ply")


def test_splats_padded_to_degree_3_keep_their_low_bands(tmp_path):
    splats = splats_from_points(np.zeros((3, 3)), np.full((3, 3), 0.25), scale=0.01)
    write_splats(tmp_path / "s.ply", splats, sh_degree=3)
    back = read_splats(tmp_path / "s.ply")
    assert back.sh.shape == (3, 16, 3)
    np.testing.assert_array_equal(back.sh[:, 0], splats.sh[:, 0])
    assert not back.sh[:, 1:].any()


@pytest.mark.parametrize("m", [1, 4, 16])
def test_splat_ply_round_trip(tmp_path, m):
    rng = np.random.default_rng(m)
    n = 50
    splats = Splats(
        means=rng.normal(size=(n, 3)).astype(np.float32), quats=rng.normal(size=(n, 4)).astype(np.float32),
        log_scales=rng.normal(size=(n, 3)).astype(np.float32), opacity_logits=rng.normal(size=n).astype(np.float32),
        sh=rng.normal(size=(n, m, 3)).astype(np.float32),
    )
    write_splats(tmp_path / "s.ply", splats)
    back = read_splats(tmp_path / "s.ply")
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert np.array_equal(getattr(back, name), getattr(splats, name)), name


def test_splat_ply_uses_3dgs_property_order(tmp_path):
    splats = splats_from_points(np.zeros((2, 3)), np.full((2, 3), 0.5), scale=0.01)
    splats.sh = np.concatenate([splats.sh, np.arange(2 * 3 * 3, dtype=np.float32).reshape(2, 3, 3)], axis=1)
    write_splats(tmp_path / "s.ply", splats)
    names = read_ply(tmp_path / "s.ply").dtype.names
    assert names[:9] == ("x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2")
    assert names[-8:] == ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")
    header = (tmp_path / "s.ply").read_bytes().split(b"end_header")[0]
    assert b"binary_little_endian" in header and header.count(b"f_rest_") == 9
    # Channel-major: f_rest_0..2 are the red channel of bands 1..3.
    v = read_ply(tmp_path / "s.ply")
    assert [v[f"f_rest_{k}"][0] for k in range(3)] == [0.0, 3.0, 6.0]


def test_splats_validate_shapes():
    with pytest.raises(ValueError, match="quats"):
        Splats(np.zeros((2, 3)), np.zeros((3, 4)), np.zeros((2, 3)), np.zeros(2), np.zeros((2, 1, 3)))


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old" and list(tmp_path.iterdir()) == [target]


def test_a_trajectory_for_other_frames_is_a_one_line_error(tmp_path):
    """[ours] A stage's trajectory must be stamped like the frames it is read for: a run folder reopened on other
    frames (another pairing, another --first) fails with the file's name instead of using the poses by index."""
    frames = 1000.0 + np.arange(4) / 30
    path = tmp_path / "trajectory.txt"
    check_frame_times(path, frames + 1e-4, frames, "rerun")  # within the 6 written decimals' reach: fine
    with pytest.raises(InputError, match="other frames") as info:
        check_frame_times(path, frames + 5 / 30, frames, "rerun stage 1")
    assert info.value.path == path and "\n" not in str(info.value)
    with pytest.raises(InputError, match="3 poses for 4 frames"):
        check_frame_times(path, frames[:3], frames, "rerun stage 1")


def test_stage_3_refuses_stage_2_poses_of_other_frames(tmp_path):
    frames = 1000.0 + np.arange(3) / 30
    (tmp_path / "refine").mkdir()
    write_tum(tmp_path / "refine" / "trajectory.txt", frames + 1 / 30, np.stack([np.eye(4)] * 3))
    (tmp_path / "refine" / "splats.ply").write_bytes(b"")
    with pytest.raises(InputError, match="stamped for other frames"):
        load_stage2(tmp_path, frames)
