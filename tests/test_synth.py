"""Synthetic sequences: layout, determinism, exact depth, exposure poses, blur levels, trajectories."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from taichi_gs.geometry import backproject, interpolate, invert, pose_from_rt, project, so3_exp, so3_log, transform
from taichi_gs import synth
from taichi_gs.io.images import encode_depth
from taichi_gs.io.load import load_sequence
from taichi_gs.io.trajectory import read_tum, read_tum_rows
from taichi_gs.synth import (
    CAMERA_DISC_RADIUS_M, DEPTH_NOISE_QUADRATIC, SCENES, SUBFRAME_STEP_PX, TRAJECTORIES, SynthConfig, build_scene,
    camera_matrix, generate, render_view, subframe_count, trajectory_poses,
)

SMALL = {"width": 64, "height": 48}


def _clean(**overrides) -> SynthConfig:
    values = {**SMALL, "frames": 4, "depth_noise": False, "holes": False, **overrides}
    return SynthConfig(**values)


def _depth(path: Path) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw.dtype == np.uint16
    return raw.astype(np.float64) / 5000.0


def _rgb(path: Path) -> np.ndarray:
    return cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1].astype(np.float64) / 255.0


@pytest.fixture(scope="module")
def clean_sequence(tmp_path_factory) -> tuple[SynthConfig, Path]:
    config = _clean(frames=4, seed=2)
    return config, generate(config, tmp_path_factory.mktemp("clean") / "seq")


@pytest.fixture(scope="module")
def noisy_sequence(tmp_path_factory) -> tuple[SynthConfig, Path]:
    config = SynthConfig(**SMALL, frames=3, seed=4)
    return config, generate(config, tmp_path_factory.mktemp("noisy") / "seq")


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [("trajectory", "spin", "translation, turn, handheld"), ("blur", "heavy", "none, moderate, extreme"),
     ("frames", 1, "at least 2"), ("width", 8, "too small"), ("fps", 0.0, "positive"),
     ("readout_ms", -1.0, "readout_ms must lie in"), ("readout_ms", 40.0, "one frame interval")],
)
def test_bad_config_values_are_rejected_with_the_allowed_ones(field, value, message):
    with pytest.raises(ValueError, match=message):
        SynthConfig(**{field: value})


def test_same_seed_gives_identical_bytes_and_another_seed_differs(tmp_path, noisy_sequence):
    config, first = noisy_sequence
    second = generate(config, tmp_path / "again")
    files = sorted(p.relative_to(first) for p in first.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(second) for p in second.rglob("*") if p.is_file())
    for name in files:
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    other = generate(SynthConfig(**{**vars(config), "seed": config.seed + 1}), tmp_path / "other")
    assert (other / "rgb/000000.png").read_bytes() != (first / "rgb/000000.png").read_bytes()


def test_layout_and_formats_match_the_reader(noisy_sequence):
    config, root = noisy_sequence
    intrinsics = json.loads((root / "intrinsics.json").read_text())
    K = camera_matrix(config)
    assert intrinsics == {"width": 64, "height": 48, "fx": K[0, 0], "fy": K[1, 1], "cx": 31.5, "cy": 23.5,
                          "depth_scale": 5000.0}
    lines = (root / "frames.txt").read_text().splitlines()
    assert lines[0] == "# timestamp rgb depth"
    assert lines[1:] == [f"{i / 30:.6f} rgb/{i:06d}.png depth/{i:06d}.png" for i in range(3)]
    for i in range(3):
        depth = cv2.imread(str(root / f"depth/{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert depth.dtype == np.uint16 and depth.shape == (48, 64)
        for folder in ("rgb", "sharp"):
            image = cv2.imread(str(root / f"{folder}/{i:06d}.png"), cv2.IMREAD_UNCHANGED)
            assert image.dtype == np.uint8 and image.shape == (48, 64, 3)
    assert (root / "exposure.txt").read_text().startswith(
        "# timestamp start(tx ty tz qx qy qz qw) end(tx ty tz qx qy qz qw)\n")
    assert read_tum_rows(root / "exposure.txt", columns=15).shape == (3, 15)
    summary = json.loads((root / "synth.json").read_text())
    assert summary["config"] == vars(config)
    assert len(summary["subframes"]) == 3 and summary["smear_px"]["max"] >= summary["smear_px"]["mean"] > 0

    timestamps, mids, exposure = trajectory_poses(config)
    gt_times, gt_poses = read_tum(root / "groundtruth.txt")
    np.testing.assert_allclose(gt_times, timestamps, atol=1e-6)
    sequence = load_sequence(root)
    assert len(sequence) == 3 and sequence.sharp_paths is not None
    np.testing.assert_allclose(sequence.gt_poses, mids, atol=1e-6)
    np.testing.assert_allclose(sequence.exposure_poses, exposure, atol=1e-6)


def test_written_depth_is_the_exact_ray_cast_depth(clean_sequence):
    config, root = clean_sequence
    _, mids, _ = trajectory_poses(config)
    K = camera_matrix(config)
    for i, pose in enumerate(mids):
        depth = _depth(root / f"depth/{i:06d}.png")
        sharp, exact = render_view(pose, K, config.width, config.height, config.seed)
        assert np.all(depth > 0.3), "camera inside the room: every pixel sees a surface"
        np.testing.assert_allclose(depth, exact, atol=0.5 / 5000 + 1e-5)
        np.testing.assert_allclose(_rgb(root / f"sharp/{i:06d}.png"), sharp, atol=0.5 / 255 + 1e-6)


def test_depth_of_one_frame_reprojects_onto_the_next_with_ground_truth_poses(clean_sequence):
    config, root = clean_sequence
    _, mids, _ = trajectory_poses(config)
    K = camera_matrix(config)
    for i in range(config.frames - 1):
        depth_a, depth_b = _depth(root / f"depth/{i:06d}.png"), _depth(root / f"depth/{i + 1:06d}.png")
        in_b = transform(invert(mids[i + 1]) @ mids[i], backproject(depth_a, K)).reshape(-1, 3)
        uv = project(in_b, K)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= config.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= config.height - 1)
        assert inside.mean() > 0.5
        inverse_b = cv2.remap((1.0 / depth_b).astype(np.float32), uv[inside, 0].astype(np.float32)[:, None],
                              uv[inside, 1].astype(np.float32)[:, None], cv2.INTER_LINEAR)[:, 0]
        relative = np.abs(1.0 / inverse_b - in_b[inside, 2]) / in_b[inside, 2]
        assert np.median(relative) < 1e-3
        assert np.mean(relative < 0.01) > 0.85  # the rest: occlusions and depth edges


def test_blur_levels_order_and_reach_their_smear_targets(tmp_path):
    smear, image_change, start_end_px = {}, {}, {}
    for blur in ("none", "moderate", "extreme"):
        config = _clean(frames=3, seed=1, blur=blur)
        root = generate(config, tmp_path / blur)
        smear[blur] = json.loads((root / "synth.json").read_text())["smear_px"]["mean"] * 640 / config.width
        image_change[blur] = np.mean([np.abs(_rgb(root / f"rgb/{i:06d}.png") - _rgb(root / f"sharp/{i:06d}.png")).mean()
                                      for i in range(3)])
        _, mids, exposure = trajectory_poses(config)
        K = camera_matrix(config)
        moves = []
        for i in range(3):
            points = transform(mids[i], backproject(_depth(root / f"depth/{i:06d}.png"), K)).reshape(-1, 3)
            start, end = (project(transform(invert(T), points), K) for T in exposure[i])
            moves.append(np.linalg.norm(end - start, axis=1).mean())
        start_end_px[blur] = np.mean(moves) * 640 / config.width
    assert image_change["none"] == 0
    assert smear["none"] < 1e-9 and start_end_px["none"] < 1e-9  # one pose: projections agree to rounding
    assert 3 < smear["moderate"] < 12 and 15 < smear["extreme"] < 45
    assert image_change["moderate"] < image_change["extreme"]
    assert start_end_px["moderate"] < start_end_px["extreme"]
    assert abs(start_end_px["extreme"] - smear["extreme"]) < 0.2 * smear["extreme"]


def test_subframes_are_close_enough_to_move_points_under_a_pixel():
    assert subframe_count(0.0) == 1
    for smear in (0.3, 1.0, 7.9, 40.0):
        count = subframe_count(smear)
        assert count >= 2 and smear / (count - 1) <= SUBFRAME_STEP_PX


@pytest.mark.parametrize("trajectory", TRAJECTORIES)
def test_exposure_start_and_end_interpolate_to_the_mid_pose(trajectory):
    config = _clean(frames=6, trajectory=trajectory)
    timestamps, mids, exposure = trajectory_poses(config)
    np.testing.assert_allclose(timestamps, np.arange(6) / 30.0)
    for mid, (start, end) in zip(mids, exposure):
        np.testing.assert_allclose(interpolate(start, end, 0.5), mid, atol=1e-9)
        assert np.abs(start - end).max() > 1e-4
    _, sharp_mids, sharp_exposure = trajectory_poses(_clean(frames=6, trajectory=trajectory, blur="none"))
    np.testing.assert_allclose(sharp_mids, mids)
    np.testing.assert_allclose(sharp_exposure, np.stack([mids, mids], axis=1))


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("trajectory", TRAJECTORIES)
def test_every_trajectory_stays_in_the_room_overlaps_and_generates(tmp_path, trajectory, scene):
    config = _clean(frames=30, trajectory=trajectory, scene=scene, width=48, height=36)  # turn: 12 deg a frame
    _, mids, _ = trajectory_poses(config)
    assert np.all(np.hypot(mids[:, 0, 3], mids[:, 2, 3]) <= CAMERA_DISC_RADIUS_M)
    assert np.all(np.abs(mids[:, :3, 3]) < build_scene(config.seed, scene).room_half - 0.5)
    K = camera_matrix(config)
    for a, b in zip(mids[:-1], mids[1:]):
        _, depth = render_view(a, K, 48, 36, config.seed, scene)
        assert depth.min() > 0.3, "the camera must never stand in or against anything"
        uv = project(transform(invert(b) @ a, backproject(depth, K)), K)
        overlap = np.mean((uv[..., 0] >= 0) & (uv[..., 0] <= 47) & (uv[..., 1] >= 0) & (uv[..., 1] <= 35))
        assert overlap > 0.6, "consecutive frames must overlap enough to track"
    root = generate(SynthConfig(**{**vars(config), "frames": 2}), tmp_path / trajectory)
    assert all(_depth(root / f"depth/{i:06d}.png").min() > 0 for i in range(2))
    assert json.loads((root / "synth.json").read_text())["config"]["scene"] == scene


def test_turn_makes_one_full_turn_and_translation_keeps_its_orientation():
    frames = 12
    _, turn, _ = trajectory_poses(_clean(frames=frames, trajectory="turn"))
    steps = [np.linalg.norm(so3_log(a[:3, :3].T @ b[:3, :3])) for a, b in zip(turn[:-1], turn[1:])]
    np.testing.assert_allclose(steps, 2 * math.pi / frames, atol=1e-9)
    _, sweep, _ = trajectory_poses(_clean(frames=frames, trajectory="translation"))
    np.testing.assert_allclose(sweep[:, :3, :3], np.broadcast_to(sweep[0, :3, :3], (frames, 3, 3)), atol=1e-12)
    sideways = (sweep[1:, :3, 3] - sweep[:-1, :3, 3]) @ sweep[0, :3, :3]  # motion in camera axes
    assert np.all(np.abs(sideways[:, 1:]) < 1e-9) and np.abs(sideways[:, 0]).max() > 0.05


def test_sensor_model_adds_depth_proportional_noise_and_holes(noisy_sequence):
    config, root = noisy_sequence
    _, mids, _ = trajectory_poses(config)
    K = camera_matrix(config)
    normalised, holes = [], []
    for i, pose in enumerate(mids):
        depth = _depth(root / f"depth/{i:06d}.png")
        _, exact = render_view(pose, K, config.width, config.height, config.seed)
        valid = depth > 0
        holes.append(1.0 - valid.mean())
        normalised.append((depth[valid] - exact[valid]) / (DEPTH_NOISE_QUADRATIC * exact[valid] ** 2))
    assert 0.005 < np.mean(holes) < 0.3
    assert 0.8 < np.std(np.concatenate(normalised)) < 1.2


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_objects_stay_inside_the_room_and_clear_of_the_camera_disc(seed):
    scene = build_scene(seed)
    objects = scene.prims[1:]
    assert len(objects) >= 6 and set(objects[:, 0]) == {1.0, 2.0, 3.0}  # spheres, cylinders, boxes
    centre, half = objects[:, 1:4], objects[:, 4:7]
    reach = np.where(objects[:, 0] == 3.0, np.hypot(half[:, 0], half[:, 2]), half[:, 0])
    assert np.all(np.abs(centre[:, [0, 2]]) + reach[:, None] <= scene.room_half[[0, 2]])
    assert np.all(np.abs(centre[:, 1]) + half[:, 1] <= scene.room_half[1] + 1e-6)
    assert np.all(np.hypot(centre[:, 0], centre[:, 2]) - reach >= CAMERA_DISC_RADIUS_M + 0.3)


def _box_corners_xz(row: np.ndarray) -> np.ndarray:
    """The four horizontal corners of a box primitive in world (x, z), its yaw applied."""
    c, s = row[7], row[8]
    local = np.array([[sx * row[4], sz * row[6]] for sx in (-1, 1) for sz in (-1, 1)])
    return row[[1, 3]] + np.stack([c * local[:, 0] + s * local[:, 1], -s * local[:, 0] + c * local[:, 1]], axis=1)


def _nearest_horizontal_distance(row: np.ndarray) -> float:
    """Distance from the room's vertical axis to the nearest point of a primitive's footprint."""
    if row[0] != 3.0:  # sphere or cylinder
        return float(np.hypot(row[1], row[3]) - row[4])
    c, s = row[7], row[8]
    x, z = -row[1], -row[3]  # the origin in the box's frame (yaw undone)
    local = np.array([c * x - s * z, s * x + c * z])
    outside = np.maximum(np.abs(local) - row[[4, 6]], 0.0)
    return float(np.hypot(*outside))


@pytest.mark.parametrize("scene", SCENES)
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_every_scene_kind_keeps_its_objects_inside_and_clear_of_the_camera_disc(scene, seed):
    room = build_scene(seed, scene)
    objects = room.prims[1:]
    assert room.prims[0, 0] == 0.0 and len(objects) >= 3
    for row in objects:
        assert _nearest_horizontal_distance(row) >= CAMERA_DISC_RADIUS_M + 0.3
        corners = _box_corners_xz(row) if row[0] == 3.0 else row[[1, 3]] + row[4] * np.array([[1, 1], [-1, -1]])
        assert np.all(np.abs(corners) <= room.room_half[[0, 2]] + 1e-5)
        assert abs(row[2]) + row[5] <= room.room_half[1] + 1e-5
    assert room.textures.shape[1:] == (256, 256, 3) and objects[:, 11:17].max() < len(room.textures)


def test_scene_kinds_differ_in_size_shape_and_texture():
    offices = np.stack([build_scene(seed, "office").room_half for seed in range(6)])
    assert np.ptp(offices[:, [0, 2]]) > 1.0, "office sizes must vary with the seed"
    corridors = np.stack([build_scene(seed, "corridor").room_half for seed in range(4)])
    assert np.all(corridors[:, 2] > 2.3 * corridors[:, 0]), "a corridor is long and narrow"
    assert np.all(corridors[:, 2] * 2 * 5000 < 65535), "the far end's depth must fit in 16 bits"
    config = _clean()
    K = camera_matrix(config)
    views = [pose_from_rt(so3_exp([0.0, yaw, 0.0]), np.zeros(3)) for yaw in np.linspace(0, 2 * math.pi, 9)[:8]]

    def texture(scene: str) -> float:
        grads = []
        for pose in views:
            grey = render_view(pose, K, config.width, config.height, 0, scene)[0].mean(axis=2)
            grads.append(np.abs(np.diff(grey, axis=1)).mean() + np.abs(np.diff(grey, axis=0)).mean())
        return float(np.median(grads))

    assert texture("plain") < 0.5 * texture("room"), "plain walls must carry little texture"


def test_unknown_scene_is_refused_with_the_choices():
    with pytest.raises(ValueError, match="room, office, plain, corridor"):
        SynthConfig(scene="cave")


def test_a_rolling_shutter_renders_each_row_at_its_own_time():
    """[ours] ``readout_ms`` without blur: row v of the colour and of the exact depth is row v of a render at
    t + readout ((v + 1/2) / H - 1/2), the middle rows at the frame's own pose; the sharp frame stays the
    global-shutter render at t."""
    config = synth.SynthConfig(width=40, height=24, frames=3, trajectory="turn", blur="none", seed=4,
                               depth_noise=False, holes=False, readout_ms=30.0)
    t = 1 / config.fps
    mid = synth._camera_path(config)(t)
    images, _ = synth.render_frame(config, 1, mid, np.stack([mid, mid]))
    K = synth.camera_matrix(config)
    global_rgb, _ = synth.render_view(mid, K, 40, 24, 4, "room")
    for v in (0, 5, 11, 12, 23):
        row_time = t + 0.030 * ((v + 0.5) / 24 - 0.5)
        rgb, depth = synth.render_view(synth._camera_path(config)(row_time), K, 40, 24, 4, "room")
        np.testing.assert_allclose(images.blurred[v], rgb[v], atol=1e-6)
        np.testing.assert_allclose(images.depth_raw[v], encode_depth(depth, config.depth_scale)[v])
    np.testing.assert_allclose(images.sharp, global_rgb, atol=1e-6)
    assert np.abs(images.blurred[0] - global_rgb[0]).mean() > 0.02  # the top row was read 15 ms early


def test_a_rolling_shutter_with_blur_moves_the_rows_away_from_the_middle_one(tmp_path):
    """[ours] With blur, each row averages its own exposure: the middle rows (read at the frame's time) are those
    of an all-but-instant readout, the top and bottom rows are not."""
    frames = {}
    for readout in (0.001, 30.0):
        config = synth.SynthConfig(width=64, height=48, frames=30, trajectory="turn", blur="extreme", seed=4,
                                   depth_noise=False, holes=False, readout_ms=readout)
        _, mids, exposure, fraction = synth._sequence_poses(config)
        frames[readout] = synth.render_frame(config, 1, mids[1], exposure[1], fraction / config.fps)[0].blurred
    difference = np.abs(frames[30.0] - frames[0.001]).mean(axis=(1, 2))
    assert difference[23:25].mean() < 0.01 and difference[:4].mean() > 10 * difference[23:25].mean()
