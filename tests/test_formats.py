"""Readers of the public layouts, --every/--scale, import, and bad or mixed folders, on one analytic
scene (a textured plane) written by the tests in each layout's published file layout."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from format_fixtures import (FRAMES, PLANE_Z, SCANNET_COLOR_K, SCANNET_DEPTH_K, SMALL_K, TUM_FR1, WRITERS, backproject, render,
                             truth_poses, write_7scenes, write_own, write_replica, write_scannet, write_stray)
from taichi_gs.cli import app
from taichi_gs.errors import InputError
from taichi_gs.io.convert import import_sequence
from taichi_gs.io.formats import detect_format
from taichi_gs.io.load import load_sequence
from taichi_gs.io.sequence import IntrinsicsOverride
from taichi_gs.io.transforms import resize_depth
from taichi_gs.pipeline import open_run_sequence, write_run_info


def _write(name: str, tmp_path: Path) -> tuple[Path, dict]:
    folder = tmp_path / name
    info = WRITERS[name](folder)
    return info.get("folder", folder), info


@pytest.mark.parametrize("name", sorted(WRITERS))
def test_every_layout_reads_the_same_scene(name, tmp_path):
    """Detected layout, ground-truth poses, intrinsics and depth units: back-projected depth lands on
    the plane within the layout's depth step, and colour matches the texture at the read pose."""
    folder, info = _write(name, tmp_path)
    assert detect_format(folder) == name
    seq = load_sequence(folder)
    assert len(seq) == 3 and seq.source["format"] == name
    assert (seq.intrinsics.width, seq.intrinsics.height) == info["size"]
    assert np.allclose(seq.K(), info["K"], atol=1e-6)
    assert np.allclose(seq.gt_poses, truth_poses(), atol=1e-6)
    for i in range(len(seq)):
        depth = seq.depth(i)
        points = backproject(seq.K(), seq.gt_poses[i], depth)
        assert len(points) > 0.8 * depth.size * (1 - info.get("masked_columns", 0) / depth.shape[1])
        expected, expected_depth = render(seq.K(), seq.gt_poses[i], *info["size"])
        # a depth step dz moves a point on a ray by dz / cos <= 1.2 dz along z here; a nearest-neighbour
        # remap (TUM's undistortion, 7-Scenes' registration) may take the depth of a pixel up to 0.71 px away
        tolerance = 0.6 * info["step"] * 1.2 + 1e-6
        if name == "tum" or info.get("resampled_depth"):
            tolerance += 0.71 * 1.2 * max(np.abs(np.diff(expected_depth, axis=a)).max() for a in (0, 1))
        assert np.abs(points[:, 2] - PLANE_Z).max() <= tolerance
        error = np.abs(seq.color(i) - expected)[3:-3, 3:-3]  # borders: resampling / undistortion edges
        assert error.mean() < 0.01, f"{name} frame {i}: mean colour error {error.mean():.4f}"


def test_7scenes_seq_folder_defaults_and_no_reading_code(tmp_path):
    write_7scenes(tmp_path / "scene", seq=True)
    seq = load_sequence(tmp_path / "scene")
    assert seq.source["format"] == "7scenes" and seq.names[0] == "frame-000000"
    assert seq.source["camera"] == "registered"
    assert (seq.intrinsics.fx, seq.intrinsics.cx, seq.intrinsics.cy, seq.intrinsics.depth_scale) == (526.5, 320, 240, 1000)
    assert np.allclose(seq.timestamps, [0, 1 / 30, 2 / 30])
    assert 0 < seq.depth(0).max() < PLANE_Z + 1  # 65535 = no reading, not a far surface
    raw = load_sequence(tmp_path / "scene", camera="shipped")
    assert (raw.intrinsics.fx, raw.intrinsics.cx, raw.intrinsics.cy) == (585, 320, 240)
    assert np.all(raw.depth(0)[:2, :5] == 0)
    assert np.allclose(raw.gt_poses[:, :3, 3] - seq.gt_poses[:, :3, 3],
                       -truth_poses()[:, :3, 0] * 0.025, atol=1e-6)  # the depth camera, 2.5 cm along -x


def test_a_tum_fr1_run_recorded_before_the_depth_latency_reopens_without_it(tmp_path):
    """fr1 pairs colour with depth stamps minus 15 ms; a run folder whose record has no latency (made before it
    existed) reopens with the old pairing, so its stage outputs keep their frames (and fingerprints)."""
    folder, _ = _write("tum", tmp_path)
    stamps = [line.split() for line in (folder / "depth.txt").read_text().splitlines() if not line.startswith("#")]
    # depth stamped 15.5 ms before each colour frame (and 17.8 ms after the one before), as in fr1_rpy 400-439
    shifted = [f"{float(t) - 0.004 - 0.0155:.6f} {name}" for t, name in stamps]
    shifted.append(f"{float(stamps[-1][0]) - 0.004 - 0.0155 + 1 / 30:.6f} {stamps[-1][1]}")
    (folder / "depth.txt").write_text("\n".join(shifted) + "\n")
    new = load_sequence(folder)
    assert new.load_options["depth_latency"] == 0.015
    assert [p.name for p in new.depth_paths] == [name.split("/")[1] for _, name in stamps[1:]] + [stamps[-1][1].split("/")[1]]
    write_run_info(tmp_path / "new", new)
    assert open_run_sequence(tmp_path / "new").depth_paths == new.depth_paths
    record = json.loads((tmp_path / "new" / "run.json").read_text())
    del record["load_options"]["depth_latency"]
    (tmp_path / "old" ).mkdir()
    (tmp_path / "old" / "run.json").write_text(json.dumps(record))
    old = open_run_sequence(tmp_path / "old")
    assert [p.name for p in old.depth_paths] == [name.split("/")[1] for _, name in stamps]
    assert "depth_latency" not in old.load_options


def test_a_7scenes_run_recorded_before_registration_reopens_as_shipped(tmp_path):
    """Run folders made when 7-Scenes was read as one camera recorded no camera: they reopen that way."""
    write_7scenes(tmp_path / "s")
    write_run_info(tmp_path / "new", load_sequence(tmp_path / "s"))
    assert open_run_sequence(tmp_path / "new").source["camera"] == "registered"
    write_run_info(tmp_path / "old", load_sequence(tmp_path / "s", camera="shipped"))
    record = json.loads((tmp_path / "old" / "run.json").read_text())
    record["load_options"]["camera"] = None
    (tmp_path / "old" / "run.json").write_text(json.dumps(record))
    assert open_run_sequence(tmp_path / "old").source["camera"] == "shipped"


def test_7scenes_camera_names_are_checked(tmp_path):
    write_7scenes(tmp_path / "s")
    with pytest.raises(InputError, match="unknown --camera 'fr1' for 7-Scenes"):
        load_sequence(tmp_path / "s", camera="fr1")


def test_rounded_pose_matrices_are_read_as_rigid_motions(tmp_path):
    """7-Scenes stores rotations with determinants off by ~1e-4; the reader returns the nearest
    rotation, so a perfect estimate has ~0 rotation error rather than ~1 degree."""
    write_7scenes(tmp_path / "s")
    pose = truth_poses()[1]
    skewed = pose.copy()
    skewed[:3, :3] *= 1.0 - 1.5e-4
    (tmp_path / "s" / "frame-000001.pose.txt").write_text("\n".join(" ".join(f"{v:.9g}" for v in r) for r in skewed))
    read = load_sequence(tmp_path / "s", camera="shipped").gt_poses[1]  # the file's pose, not moved to colour
    assert np.allclose(read[:3, :3].T @ read[:3, :3], np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(read[:3, :3]), 1.0)
    assert np.allclose(read, pose, atol=1e-8)


def test_7scenes_without_pose_files_runs_without_ground_truth(tmp_path):
    write_7scenes(tmp_path / "s")
    for p in (tmp_path / "s").glob("*.pose.txt"):
        p.unlink()
    assert load_sequence(tmp_path / "s").gt_poses is None


def test_scannet_colour_lands_on_the_depth_grid(tmp_path):
    """A point drawn as a small blob in the 160x120 colour image appears in the read (80x60, depth
    grid) colour at its projection with the depth intrinsics."""
    folder = tmp_path / "scannet"
    write_scannet(folder)
    point = np.array([0.31, -0.22, PLANE_Z])
    pose = truth_poses()[0]
    for K, size, path in ((SCANNET_COLOR_K, (160, 120), folder / "color/0.jpg"),):
        image = _blob_image(K, pose, point, size)
        cv2.imwrite(str(path), image, [cv2.IMWRITE_JPEG_QUALITY, 100])
    seq = load_sequence(folder)
    u, v = _project(SCANNET_DEPTH_K, pose, point)
    cu, cv_ = _centroid(seq.color(0)[..., 0])
    assert abs(cu - u) < 0.1 and abs(cv_ - v) < 0.1


def test_tum_undistortion_matches_opencv(tmp_path):
    folder, _ = _write("tum", tmp_path)
    seq = load_sequence(folder)
    assert seq.source.get("camera") == "fr1"
    assert seq.source.get("depth_latency_s") == 0.015  # the fr1 preset pairs by depth stamps minus its latency
    raw = cv2.imread(str(seq.rgb_paths[0]), cv2.IMREAD_COLOR)
    expected = cv2.cvtColor(cv2.undistort(raw, TUM_FR1["K"], TUM_FR1["distortion"]), cv2.COLOR_BGR2RGB) / 255.0
    mx, my = cv2.initUndistortRectifyMap(TUM_FR1["K"], TUM_FR1["distortion"], None, TUM_FR1["K"], (640, 480), cv2.CV_32FC1)
    inside = (mx >= 1) & (mx <= 638) & (my >= 1) & (my <= 478)  # where cv2.undistort has source pixels
    assert inside.mean() > 0.8
    assert np.abs(seq.color(0) - expected)[inside].max() < 2.5 / 255
    # depth is remapped by nearest neighbour: every read value is one of the raw values
    raw_depth = cv2.imread(str(seq.depth_paths[0]), cv2.IMREAD_UNCHANGED)
    read = np.round(seq.depth(0) * 5000.0)
    assert np.isin(read[read > 0], raw_depth).all()


def test_tum_sourced_pixels_are_those_undistortion_reads_from_the_raw_frame(tmp_path):
    folder, _ = _write("tum", tmp_path)
    seq = load_sequence(folder)
    mx, my = cv2.initUndistortRectifyMap(TUM_FR1["K"], TUM_FR1["distortion"], None, TUM_FR1["K"], (640, 480), cv2.CV_32FC1)
    margin = 0.05  # OpenCV interpolates on a 1/32-pixel grid: samples nearer the edge than that may round
    inside = (mx >= margin) & (mx <= 639 - margin) & (my >= margin) & (my <= 479 - margin)
    outside = (mx < -margin) | (mx > 639 + margin) | (my < -margin) | (my > 479 + margin)
    sourced = seq.sourced_pixels()
    assert sourced.shape == (480, 640) and 0.9 < sourced.mean() < 1.0
    assert sourced[inside].all() and not sourced[outside].any()
    half = load_sequence(folder, scale=0.5).sourced_pixels()  # a pixel counts when its 2 x 2 block does
    assert half[sourced.reshape(240, 2, 320, 2).all(axis=(1, 3))].all()
    assert not half[outside.reshape(240, 2, 320, 2).any(axis=(1, 3))].any()
    assert load_sequence(folder, camera="fr3").sourced_pixels().all()  # no transform: every pixel seen


def test_import_keeps_which_pixels_the_camera_saw(tmp_path):
    """[ours] An undistorted TUM frame imported at half size: the copy's ``sourced.png`` gives the same
    pixels as reading the original, also when the copy is read at half size again; a folder whose every
    pixel was seen gets no mask."""
    folder, _ = _write("tum", tmp_path)
    original = load_sequence(folder, scale=0.5)
    copy = import_sequence(original, tmp_path / "copy")
    assert (copy / "sourced.png").is_file()
    reread = load_sequence(copy)
    assert reread.sourced_path == copy / "sourced.png"
    np.testing.assert_array_equal(reread.sourced_pixels(), original.sourced_pixels())
    quarter = load_sequence(copy, scale=0.5).sourced_pixels()  # a pixel counts when its 2 x 2 block does
    np.testing.assert_array_equal(quarter, original.sourced_pixels().reshape(120, 2, 160, 2).all(axis=(1, 3)))
    seen = import_sequence(load_sequence(folder, camera="fr3"), tmp_path / "seen")
    assert not (seen / "sourced.png").exists() and load_sequence(seen).sourced_pixels().all()


def test_import_keeps_the_cameras_rolling_shutter_readout(tmp_path):
    """[ours] A TUM fr1 reading (Kinect v1: 25 ms) imported: the copy's intrinsics.json carries ``readout_ms``, so
    the fast preset de-skews the copy as it would the original. A reading without a known readout (fr3) writes
    none. A bad ``readout_ms`` is a one-line error naming intrinsics.json, and the CLI exits 2 on it."""
    from taichi_gs.stages.pose import PRESETS, pose_readout_ms

    folder, _ = _write("tum", tmp_path)
    original = load_sequence(folder, scale=0.5)
    copy = import_sequence(original, tmp_path / "copy")
    assert json.loads((copy / "intrinsics.json").read_text())["readout_ms"] == 25.0
    assert pose_readout_ms(load_sequence(copy), PRESETS["fast"]) == pose_readout_ms(original, PRESETS["fast"]) == 25.0
    plain = import_sequence(load_sequence(folder, camera="fr3"), tmp_path / "plain")
    assert "readout_ms" not in json.loads((plain / "intrinsics.json").read_text())
    assert pose_readout_ms(load_sequence(plain), PRESETS["fast"]) == 0.0
    values = json.loads((copy / "intrinsics.json").read_text())
    for bad in (-1, "fast", 5000):
        (copy / "intrinsics.json").write_text(json.dumps({**values, "readout_ms": bad}))
        with pytest.raises(InputError, match="readout_ms") as error:
            load_sequence(copy)
        assert "intrinsics.json" in str(error.value) and "\n" not in str(error.value)
    result = CliRunner().invoke(app, ["pose", str(copy), "--out", str(tmp_path / "run")])
    assert result.exit_code == 2 and "readout_ms" in result.output


@pytest.mark.parametrize("mask", ["wrong size", "colour", "not a png"])
def test_a_bad_sourced_mask_gives_a_one_line_error(tmp_path, mask):
    folder, _ = _write("tum", tmp_path)
    copy = import_sequence(load_sequence(folder, scale=0.5), tmp_path / "copy")
    path = copy / "sourced.png"
    if mask == "wrong size":
        cv2.imwrite(str(path), np.full((10, 20), 255, np.uint8))
    elif mask == "colour":
        cv2.imwrite(str(path), np.full((240, 320, 3), 255, np.uint8))
    else:
        path.write_bytes(b"not a png")
    with pytest.raises(InputError, match="sourced.png") as error:
        load_sequence(copy).sourced_pixels()
    assert "20x10" in str(error.value) or mask != "wrong size"


def test_tum_frames_of_another_size_than_the_calibration_are_refused(tmp_path):
    folder, _ = _write("tum", tmp_path)
    seq = load_sequence(folder)
    small = cv2.resize(cv2.imread(str(seq.rgb_paths[0])), (320, 240))
    cv2.imwrite(str(seq.rgb_paths[0]), small)
    with pytest.raises(InputError, match="320x240.*640x480"):
        seq.color(0)


def _halve(paths: list[Path]) -> None:
    """Frames resized in place to half their width and height (depth by nearest neighbour)."""
    for path in paths:
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2),
                                          interpolation=cv2.INTER_NEAREST))


def test_a_tum_camera_is_refused_on_frames_of_another_size(tmp_path):
    """The fr1 calibration (folder name) on 320x240 frames would be read as their camera: an error naming a frame
    and the fix; the flags read them at any size, and --scale still shrinks the full-size frames."""
    folder, _ = _write("tum", tmp_path)
    assert load_sequence(folder, scale=0.5).intrinsics.width == 320
    seq = load_sequence(folder)
    _halve(seq.rgb_paths + seq.depth_paths)
    with pytest.raises(InputError, match="320x240, but the fr1 camera is published for 640x480") as error:
        load_sequence(folder)
    assert error.value.path == seq.rgb_paths[0] and "--fx --fy --cx --cy" in error.value.fix
    with pytest.raises(InputError, match="fr3 camera"):
        load_sequence(folder, camera="fr3")
    line = _cli_error(["import", str(folder), "--out", str(tmp_path / "copy")])
    assert "published for 640x480" in line and "intrinsics.json" in line
    flags = IntrinsicsOverride(fx=258.65, fy=258.25, cx=159.05, cy=127.4)
    assert load_sequence(folder, flags).intrinsics.fx == 258.65
    assert load_sequence(folder, flags, camera="fr1").transform is not None  # the flags' camera, fr1's distortion


def test_the_7scenes_camera_is_refused_on_frames_of_another_size(tmp_path):
    """seq-01/ of 320x240 frames without camera-intrinsics.txt: the published 640x480 camera would be read as theirs
    (colour, and depth's when registered). An error naming a frame and the fixes; camera-intrinsics.txt, or the flags
    read unregistered or with intrinsics.json's depth_camera, read them at any size; --scale still works."""
    write_7scenes(tmp_path / "scene", seq=True)
    assert load_sequence(tmp_path / "scene", scale=0.5).intrinsics.width == 320
    frames = tmp_path / "scene" / "seq-01"
    _halve(sorted(frames.glob("*.png")))
    with pytest.raises(InputError, match="320x240, but the 7-Scenes camera .* is published for 640x480") as error:
        load_sequence(tmp_path / "scene")
    assert error.value.path == frames / "frame-000000.color.png" and "camera-intrinsics.txt" in error.value.fix
    flags = IntrinsicsOverride(fx=263.25, fy=263.25, cx=160, cy=120)
    with pytest.raises(InputError, match="published for 640x480") as error:  # registering: the depth camera's too
        load_sequence(tmp_path / "scene", flags)
    assert "--camera shipped" in error.value.fix and "depth_camera" in error.value.fix
    assert load_sequence(tmp_path / "scene", flags, camera="shipped").intrinsics.fx == 263.25
    line = _cli_error(["import", str(tmp_path / "scene"), "--out", str(tmp_path / "copy")])
    assert "published for 640x480" in line and "camera-intrinsics.txt" in line
    (tmp_path / "scene" / "intrinsics.json").write_text(json.dumps(
        {"fx": 263.25, "fy": 263.25, "cx": 160, "cy": 120,
         "depth_camera": {"fx": 292.5, "fy": 292.5, "cx": 160, "cy": 120, "colour_from_depth": [-0.025, 0, 0]}}))
    assert load_sequence(tmp_path / "scene").intrinsics.fx == 263.25
    (tmp_path / "scene" / "intrinsics.json").unlink()
    (frames / "camera-intrinsics.txt").write_text("292.5 0 160\n0 292.5 120\n0 0 1\n")
    seq = load_sequence(tmp_path / "scene")
    assert (seq.intrinsics.width, seq.intrinsics.fx) == (320, pytest.approx(263.25))


def test_tum_needs_a_camera(tmp_path):
    folder, _ = _write("tum", tmp_path)
    plain = folder.rename(tmp_path / "recording")
    with pytest.raises(InputError, match="--camera fr1"):
        load_sequence(plain)
    seq = load_sequence(plain, camera="fr3")
    assert seq.intrinsics.fx == 535.4 and seq.transform is None  # fr3: no distortion


@pytest.mark.parametrize("kind", ["npy", "tiff"])
def test_stray_float_depth_and_confidence(kind, tmp_path):
    write_stray(tmp_path / "s", depth_kind=kind)
    seq = load_sequence(tmp_path / "s")
    depth = seq.depth(0)
    assert np.all(depth[:, :10] == 0) and np.all(depth[:, 10:] > 0)  # confidence 1 dropped, 2 kept
    _, expected = render(seq.K(), truth_poses()[0], 80, 60)
    assert np.allclose(depth[:, 10:], expected[:, 10:], atol=1e-5)


def test_scale_keeps_a_projected_point_on_the_scaled_pixel(tmp_path):
    folder = tmp_path / "own"
    write_own(folder)
    pose = truth_poses()[0]
    point = np.array([0.12, 0.07, PLANE_Z])
    cv2.imwrite(str(folder / "rgb/000000.png"), _blob_image(SMALL_K, pose, point, (80, 60)))
    for scale in (0.5, 0.25, 0.8):
        seq = load_sequence(folder, scale=scale)
        u, v = _project(seq.K(), pose, point)
        cu, cv_ = _centroid(seq.color(0)[..., 0])
        assert abs(cu - u) < 0.08 and abs(cv_ - v) < 0.08, (scale, cu, u, cv_, v)
        assert seq.color(0).shape[:2] == seq.depth(0).shape == (seq.intrinsics.height, seq.intrinsics.width)
    assert seq.source["scale"] == 0.8


def test_depth_resize_never_mixes_surfaces_or_holes():
    rng = np.random.default_rng(3)
    depth = rng.choice([0.0, 1.0, 3.0], size=(60, 80)).astype(np.float32)
    depth[:4, :4] = 0.0
    for w, h in ((40, 30), (20, 15), (64, 48)):
        small = resize_depth(depth, w, h)
        assert small.shape == (h, w) and set(np.unique(small)) <= {0.0, 1.0, 3.0}
    half = resize_depth(depth, 40, 30)
    assert half[0, 0] == 0.0 and half[0, 0] == 0.0  # an all-hole block stays a hole
    block = depth[2:4, 4:6]
    if (block > 0).any():
        assert half[1, 2] in block[block > 0]  # one of the block's valid depths, never blended with 0


def test_every_keeps_timestamps_and_ground_truth(tmp_path):
    folder = tmp_path / "s"
    write_7scenes(folder)
    seq = load_sequence(folder, every=2)
    assert seq.names == ["frame-000000", "frame-000002"]
    assert np.allclose(seq.timestamps, [0, 2 / 30]) and np.allclose(seq.gt_poses, truth_poses()[::2])


def test_first_and_count_pick_a_stretch_and_the_run_reopens_it(tmp_path):
    folder = tmp_path / "s"
    write_7scenes(folder)
    seq = load_sequence(folder, first=1, count=2)
    assert seq.names == ["frame-000001", "frame-000002"]
    assert np.allclose(seq.timestamps, [1 / 30, 2 / 30]) and np.allclose(seq.gt_poses, truth_poses()[1:3])
    assert load_sequence(folder, count=3, every=2).names == ["frame-000000", "frame-000002"]  # as many as there are
    write_run_info(tmp_path / "run", seq)
    assert open_run_sequence(tmp_path / "run").names == seq.names


def test_a_first_frame_past_the_end_or_a_one_frame_stretch_is_refused(tmp_path):
    folder = tmp_path / "s"
    write_7scenes(folder)
    line = _cli_error(["pose", str(folder), "--out", str(tmp_path / "o"), "--first", "9"])
    assert "--first 9" in line and f"{FRAMES} frames" in line
    line = _cli_error(["import", str(folder), "--out", str(tmp_path / "i"), "--first", "1", "--count", "1"])
    assert "1 frame(s)" in line and not (tmp_path / "i").exists()


def test_import_round_trips_and_leaves_the_input_alone(tmp_path):
    src, _ = _write("scannet", tmp_path)
    before = {p: p.stat().st_mtime_ns for p in src.rglob("*")}
    out = tmp_path / "imported"
    result = CliRunner().invoke(app, ["import", str(src), "--out", str(out), "--every", "2", "--scale", "0.5"])
    assert result.exit_code == 0, result.output
    assert {p: p.stat().st_mtime_ns for p in src.rglob("*")} == before
    original, copy = load_sequence(src, every=2, scale=0.5), load_sequence(out)
    assert copy.source["format"] == "taichi-gs" and copy.names == original.names
    assert copy.intrinsics == original.intrinsics
    assert np.allclose(copy.timestamps, original.timestamps, atol=1e-6)
    assert np.allclose(copy.gt_poses, original.gt_poses, atol=1e-7)
    for i in range(len(copy)):
        assert np.abs(copy.color(i) - original.color(i)).max() <= 0.5 / 255 + 1e-6
        assert np.abs(copy.depth(i) - original.depth(i)).max() <= 0.5 / original.intrinsics.depth_scale + 1e-6
    assert not list(tmp_path.glob(".imported.*"))  # no staging folder left behind
    # refusals: an existing non-empty folder, and a folder inside the input
    with pytest.raises(InputError, match="not empty"):
        import_sequence(original, out)
    result = CliRunner().invoke(app, ["import", str(src), "--out", str(src / "copy")])
    assert result.exit_code == 2 and "inside the input" in result.output and not (src / "copy").exists()


def test_run_json_reopens_the_sequence_the_same_way(tmp_path):
    src, _ = _write("replica", tmp_path)
    seq = load_sequence(src, every=2, scale=0.5, format="replica")
    write_run_info(tmp_path / "run", seq)
    record = json.loads((tmp_path / "run" / "run.json").read_text())["load_options"]
    assert (record["format"], record["every"], record["scale"]) == ("replica", 2, 0.5)
    again = open_run_sequence(tmp_path / "run")
    assert again.intrinsics == seq.intrinsics and again.names == seq.names


def _cli_error(args: list[str]) -> str:
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 2, result.output
    line = " ".join(result.output.split())
    assert line.startswith("error:")
    return line


def test_bad_and_mixed_folders_give_one_line_errors(tmp_path):
    mixed = tmp_path / "mixed"
    write_7scenes(mixed)
    write_own(tmp_path / "own")
    for p in (tmp_path / "own").iterdir():
        p.rename(mixed / p.name)
    line = _cli_error(["pose", str(mixed), "--out", str(tmp_path / "o")])
    assert "several layouts" in line and "7scenes" in line and "taichi-gs" in line and "--format" in line
    assert load_sequence(mixed, format="7scenes").source["format"] == "7scenes"

    write_replica(tmp_path / "replica", intrinsics=False)
    line = _cli_error(["import", str(tmp_path / "replica"), "--out", str(tmp_path / "r2")])
    assert "intrinsics.json" in line and "599.5" in line
    assert len(load_sequence(tmp_path / "replica", _override(fx=60, fy=62, cx=39.5, cy=29.5))) == 3

    write_7scenes(tmp_path / "poses")
    (tmp_path / "poses" / "frame-000001.pose.txt").unlink()
    line = _cli_error(["import", str(tmp_path / "poses"), "--out", str(tmp_path / "p2")])
    assert "frame-000001.pose.txt" in line and "pose file missing" in line

    write_scannet(tmp_path / "scannet")
    (tmp_path / "scannet" / "intrinsic" / "intrinsic_depth.txt").unlink()
    line = _cli_error(["import", str(tmp_path / "scannet"), "--out", str(tmp_path / "s2")])
    assert "intrinsic_depth.txt" in line and "SensReader" in line

    (tmp_path / "empty").mkdir()
    assert "no known RGB-D layout" in _cli_error(["import", str(tmp_path / "empty"), "--out", str(tmp_path / "e2")])
    assert "unknown --format" in _cli_error(["import", str(mixed), "--out", str(tmp_path / "m2"), "--format", "kinect"])
    assert "--scale" in _cli_error(["import", str(mixed), "--out", str(tmp_path / "m3"), "--format", "7scenes", "--scale", "0"])


def _override(**values):
    from taichi_gs.io.sequence import IntrinsicsOverride

    return IntrinsicsOverride(**values)


def _project(K: np.ndarray, pose: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    cam = np.linalg.inv(pose) @ np.append(point, 1.0)
    return K[0, 0] * cam[0] / cam[2] + K[0, 2], K[1, 1] * cam[1] / cam[2] + K[1, 2]


def _blob_image(K: np.ndarray, pose: np.ndarray, point: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """8-bit BGR image, black but for a Gaussian blob (sigma 1.5 px at 1/80 of the width) in red
    centred on the point's projection."""
    w, h = size
    u0, v0 = _project(K, pose, point)
    sigma = 1.5 * w / 80
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    blob = np.exp(-((u - u0) ** 2 + (v - v0) ** 2) / (2 * sigma**2))
    image = np.zeros((h, w, 3), np.uint8)
    image[..., 2] = np.round(blob * 255).astype(np.uint8)
    return image


def _centroid(channel: np.ndarray) -> tuple[float, float]:
    weight = np.where(channel > 0.02, channel, 0.0)
    v, u = np.indices(channel.shape)
    return float((weight * u).sum() / weight.sum()), float((weight * v).sum() / weight.sum())


def test_texture_is_not_constant():
    """Guards the colour checks above: the texture varies across the frame in every channel."""
    color, _ = render(SMALL_K, truth_poses()[0], 80, 60)
    assert color.std(axis=(0, 1)).min() > 0.05


def test_export_writes_resampled_frames_at_the_read_size(tmp_path):
    """A sequence read through a transform (ScanNet colour onto the depth grid, --scale) is exported
    as read, so images, depth and intrinsics agree."""
    from taichi_gs.export import export_nerfstudio
    from taichi_gs.io.trajectory import write_tum

    src, _ = _write("scannet", tmp_path)
    seq = load_sequence(src, scale=0.5)
    run = tmp_path / "run"
    write_tum(run / "pose" / "trajectory.txt", seq.timestamps, truth_poses())
    transforms = json.loads(export_nerfstudio(run, seq, tmp_path / "ns").read_text())
    assert (transforms["w"], transforms["h"]) == (40, 30)
    frame = transforms["frames"][1]
    image = cv2.imread(str(tmp_path / "ns" / frame["file_path"]), cv2.IMREAD_UNCHANGED)
    depth = cv2.imread(str(tmp_path / "ns" / frame["depth_file_path"]), cv2.IMREAD_UNCHANGED)
    assert image.shape[:2] == depth.shape == (30, 40)
    assert np.allclose(depth * transforms["depth_unit_scale_factor"], seq.depth(1), atol=1e-3)
