"""Stage 1 end to end on hand-made data: relative pose, failure handling, outputs and resuming."""

from __future__ import annotations

import dataclasses
import json
import threading
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from test_pose_scene import MOTION, pair, render, small_K

import taichi_gs.stages.pose as pose_stage
import taichi_gs.stages.pose_edges as pose_edges
import taichi_gs.stages.pose_frames as pose_frames
import taichi_gs.stages.pose_pair as pose_pair
from taichi_gs.evaluate import ate, rpe
from taichi_gs.geometry import invert, se3_exp, se3_log
from taichi_gs.io.ply import read_point_cloud
from taichi_gs.io.trajectory import read_tum
from taichi_gs.stages.pose import run_pose
from taichi_gs.stages.pose_config import METHOD_ONLY, PoseConfig
from taichi_gs.stages.pose_pair import estimate_relative_pose

W, H = 160, 120


class SceneSequence:
    """In-memory sequence of the test scene along given camera-to-world poses."""

    def __init__(self, poses: np.ndarray, broken_depth: set[int] = frozenset()):
        K = small_K(W, H)
        self.intrinsics = SimpleNamespace(width=W, height=H, K=lambda: K)
        self.gt_poses = poses
        self.timestamps = np.arange(len(poses)) / 30.0
        self.names = [f"frame{i:03d}" for i in range(len(poses))]
        self.depth_paths = [Path("depth") / f"{name}.png" for name in self.names]
        self.frames = [render(p, K, W, H) for p in poses]
        self.broken_depth = broken_depth

    def __len__(self) -> int:
        return len(self.frames)

    def color(self, i: int) -> np.ndarray:
        return self.frames[i][0]

    def depth(self, i: int) -> np.ndarray:
        return np.zeros((H, W), np.float32) if i in self.broken_depth else self.frames[i][1]


def walk(n: int) -> np.ndarray:
    """Camera-to-world poses of a smooth curving walk."""
    return np.stack([se3_exp(np.array([0.03 * i, 0.01 * np.sin(i), 0.02 * i, 0.01 * i, -0.015 * i, 0.005 * np.cos(i)]))
                     for i in range(n)])


def rotation_error_deg(A: np.ndarray, B: np.ndarray) -> float:
    return float(np.degrees(np.linalg.norm(se3_log(A @ invert(B))[3:])))


def test_relative_pose_from_dis_flow_and_icp():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    result = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K, config=METHOD_ONLY)
    assert not result.weak, result.reason
    assert result.estimate == "icp" and result.icp_fitness > 0.9
    assert np.linalg.norm(result.transform[:3, 3] - MOTION[:3, 3]) < 2e-3
    assert rotation_error_deg(result.transform, MOTION) < 0.1  # ICP at 160x120: ~0.05 deg measured
    assert np.linalg.norm(result.flow_transform[:3, 3] - MOTION[:3, 3]) < 5e-3


def test_pair_without_depth_is_weak_and_returns_the_prior():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    prior = se3_exp(np.array([0.01, 0, 0, 0, 0, 0]))
    result = estimate_relative_pose(color_t, np.zeros_like(depth_t), color_t1, depth_t1, K, config=METHOD_ONLY, prior=prior)
    assert result.weak and result.estimate == "constant-velocity" and "pixels" in result.reason
    np.testing.assert_array_equal(result.transform, prior)


def test_icp_that_jumps_away_keeps_the_flow_estimate():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    config = dataclasses.replace(METHOD_ONLY, icp_max_jump_m=1e-9, icp_max_jump_deg=1e-9)
    result = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K, config=config)
    assert result.weak and result.estimate == "flow" and "ICP moved" in result.reason
    np.testing.assert_array_equal(result.transform, result.flow_transform)


def test_pair_beyond_dis_range_is_recovered_with_prior_seeded_flow():
    motion = se3_exp(np.array([0.02, 0.0, 0.01, 0.0, np.radians(12.0), 0.0]))  # ~30 px at 160x120
    prior = se3_exp(np.array([0.0, 0.0, 0.0, 0.0, np.radians(10.0), 0.0]))  # constant-velocity guess, 2 deg off
    color_t, depth_t, color_t1, depth_t1, K = pair(motion)
    unseeded = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K, config=METHOD_ONLY, prior=prior)
    assert unseeded.weak and unseeded.flow_seed == "none"
    result = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K,
                                    config=dataclasses.replace(METHOD_ONLY, seeded_retry=True), prior=prior)
    assert not result.weak and result.flow_seed == "constant-velocity" and result.estimate == "icp"
    assert result.reason.startswith("unseeded flow failed")
    assert np.linalg.norm(result.transform[:3, 3] - motion[:3, 3]) < 0.01  # 4.6 mm measured
    assert rotation_error_deg(result.transform, motion) < 0.15  # 0.06 deg measured


def test_rgbd_refinement_replaces_the_icp_estimate_when_it_stays_close():
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    result = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K, config=dataclasses.replace(METHOD_ONLY, rgbd_refine=True))
    assert not result.weak and result.estimate == "rgbd"
    assert np.linalg.norm(result.transform[:3, 3] - MOTION[:3, 3]) < 5e-3  # 2.1 mm measured (ICP alone: 0.8 mm)
    assert rotation_error_deg(result.transform, MOTION) < 0.15  # 0.06 deg measured
    guarded = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K,
                                     config=dataclasses.replace(METHOD_ONLY, rgbd_refine=True, icp_max_jump_m=1e-4,
                                                                icp_max_jump_deg=2.0))
    assert guarded.estimate != "rgbd"  # a refinement moving > 0.1 mm is not kept


def test_icp_point_cap_coarsens_the_voxels_and_stays_accurate():
    from taichi_gs.icp import align, capped_voxel_down_sample, depth_cloud, prepare_icp

    _, depth_t, _, depth_t1, K = pair(MOTION, 320, 240)
    source, target = (depth_cloud(d, K, d > 0) for d in (depth_t, depth_t1))
    assert capped_voxel_down_sample(source, 0.01, 0)[1] == 1.0
    scale = capped_voxel_down_sample(source, 0.01, 20000)[1]  # 76k points at 1 cm
    assert scale > 1.0 and len(source.voxel_down_sample(0.01 * scale).points) <= 20000
    assert len(source.voxel_down_sample(0.01 * scale / 1.25).points) > 20000
    result = align(prepare_icp(source, target, (0.04, 0.02, 0.01), (30, 20, 15), 2.0, 3.0, 30, max_points=20000), np.eye(4))
    assert np.linalg.norm(result.transform[:3, 3] - MOTION[:3, 3]) < 2e-3  # 0.7 mm measured (no cap: 0.04 mm)
    assert rotation_error_deg(result.transform, MOTION) < 0.1


def test_information_clouds_keep_at_most_the_cap_and_the_matrix_shape():
    from taichi_gs.icp import open3d

    _, depth_t, _, depth_t1, K = pair(MOTION, 320, 240)
    rng = np.random.default_rng(0)
    noisy = [(d + rng.normal(0.0, 0.01, d.shape) * (d > 0)).astype(np.float32) for d in (depth_t, depth_t1)]
    matrices = {}
    for cap in (0, 5000):
        config = PoseConfig(graph_info_max_points=cap)
        clouds = [pose_frames._information_cloud(d, K, config) for d in noisy]
        sizes = [len(c.points) for c in clouds]
        assert all(n <= 5000 for n in sizes) if cap else all(n > 30000 for n in sizes)  # 1 cm noise: 2 cm voxels in layers
        info = np.asarray(open3d().pipelines.registration.get_information_matrix_from_point_clouds(
            *clouds, config.graph_info_distance_m, MOTION))
        matrices[cap] = info / np.trace(info)
    assert np.linalg.norm(matrices[5000] - matrices[0]) < 0.05 * np.linalg.norm(matrices[0])  # 1.2% measured


def _linear_voxel_scale(cloud, voxel: float, max_points: int) -> float:
    """The reference search: grow the voxel by 25% until the cloud has at most ``max_points`` points."""
    scale = 1.0
    while len(cloud.voxel_down_sample(scale * voxel).points) > max_points:
        scale *= 1.25
    return scale


@pytest.mark.parametrize("max_points", [1, 40, 900, 20000, 60000, 10**7])
def test_voxel_search_finds_the_same_voxel_as_growing_it_step_by_step(max_points):
    from taichi_gs.icp import capped_voxel_down_sample, depth_cloud

    _, depth_t, _, depth_t1, K = pair(MOTION, 320, 240)
    rng = np.random.default_rng(0)
    noisy = depth_t1 * (1 + 0.01 * rng.standard_normal(depth_t1.shape))  # a volumetric, non-planar cloud
    for depth in (depth_t, noisy):
        cloud = depth_cloud(depth, K, depth > 0)
        for voxel in (0.002, 0.01, 0.03):
            assert capped_voxel_down_sample(cloud, voxel, max_points)[1] == pytest.approx(_linear_voxel_scale(cloud, voxel, max_points))


def test_one_prepared_icp_pyramid_aligns_from_any_start_as_a_fresh_one():
    from taichi_gs.icp import align, depth_cloud, prepare_icp

    _, depth_t, _, depth_t1, K = pair(MOTION, 320, 240)
    source, target = (depth_cloud(d, K, d > 0) for d in (depth_t, depth_t1))
    settings = ((0.04, 0.02, 0.01), (30, 20, 15), 2.0, 3.0, 30, 20000)
    prepared = prepare_icp(source, target, *settings)
    nudged = MOTION @ se3_exp(np.array([0.01, -0.005, 0.0, 0.0, 0.01, 0.0]))
    for init in (np.eye(4), nudged, MOTION):
        shared, fresh = align(prepared, init), align(prepare_icp(source, target, *settings), init)
        np.testing.assert_allclose(shared.transform, fresh.transform, rtol=0, atol=1e-12)  # Open3D sums in threads
        assert (shared.fitness, shared.inlier_rmse) == pytest.approx((fresh.fitness, fresh.inlier_rmse), rel=1e-9)
    empty = prepare_icp(depth_cloud(depth_t, K, depth_t < 0), target, *settings)
    assert align(empty, nudged).fitness == 0.0 and np.array_equal(align(empty, nudged).transform, nudged)


def test_icp_results_that_coincide_share_one_rgbd_odometry_run(monkeypatch):
    color_t, depth_t, color_t1, depth_t1, K = pair(MOTION)
    starts = []
    original = pose_pair.rgbd_odometry
    monkeypatch.setattr(pose_pair, "rgbd_odometry",
                        lambda *args, **kwargs: starts.append(args[5].copy()) or original(*args, **kwargs))
    result = estimate_relative_pose(color_t, depth_t, color_t1, depth_t1, K, config=PoseConfig())
    icp, icp_prior = (np.array(result.candidates[n]["transform"]) for n in ("icp", "icp-prior"))
    assert np.abs(icp - icp_prior).max() <= pose_pair.SAME_START_ATOL  # both ICP runs converge here
    assert len(starts) == 1  # one odometry run serves both
    np.testing.assert_array_equal(result.candidates["rgbd-icp"]["transform"], result.candidates["rgbd-icp-prior"]["transform"])


def test_distinct_starts_each_get_their_own_run():
    runs, calls = [], []
    run = lambda start: calls.append(1) or start[0, 3]  # noqa: E731
    first, second = np.eye(4), np.eye(4)
    second[0, 3] = 1e-6
    assert pose_pair._run_once(runs, first, run) == 0.0
    assert pose_pair._run_once(runs, first + 1e-12, run) == 0.0  # within SAME_START_ATOL: reused
    assert pose_pair._run_once(runs, second, run) == 1e-6
    assert len(calls) == 2


@pytest.fixture(scope="module")
def walk_sequence() -> SceneSequence:
    return SceneSequence(walk(5))


def test_run_pose_writes_outputs_that_match_ground_truth(tmp_path, walk_sequence):
    progress = []
    result = run_pose(walk_sequence, tmp_path, PoseConfig(), progress=lambda *step: progress.append(step))
    timestamps, poses = read_tum(tmp_path / "pose" / "trajectory.txt")  # before the run below rewrites it
    total = 4 + 4 + 5  # pairs, the graph's frames, the fused frames
    assert [done for done, _, _ in progress] == list(range(1, total + 1)) and {t for _, t, _ in progress} == {total}
    assert [kind for _, _, kind in progress] == ["pairs"] * 4 + ["graph"] * 4 + ["fused cloud"] * 5
    progress.clear()
    run_pose(walk_sequence, tmp_path, PoseConfig(pose_graph=False), progress=lambda *step: progress.append(step))
    assert [kind for _, _, kind in progress] == ["pairs"] * 4 + ["fused cloud"] * 5  # cached pairs count too
    assert progress[-1][:2] == (9, 9) == (pose_stage.progress_steps(5, PoseConfig(pose_graph=False)),) * 2
    assert result.poses.shape == (5, 4, 4)
    np.testing.assert_allclose(result.poses[0], np.eye(4))
    gt = invert(walk_sequence.gt_poses[0]) @ walk_sequence.gt_poses
    assert ate(result.poses, gt) < 2e-3
    trans, rot = rpe(result.poses, gt)
    assert trans < 2e-3 and rot < 0.1

    np.testing.assert_allclose(timestamps, walk_sequence.timestamps, atol=1e-6)
    np.testing.assert_allclose(poses, result.poses, atol=1e-6)
    points, colors = read_point_cloud(tmp_path / "pose" / "points.ply")
    assert len(points) > 1000 and colors.shape == points.shape
    pairs = json.loads((tmp_path / "pose" / "pairs.json").read_text())
    assert pairs["summary"].startswith("4 pairs, 0 weak")
    assert [p["index"] for p in pairs["pairs"]] == [0, 1, 2, 3]
    assert {"flow_residual_px", "icp_fitness", "icp_inlier_rmse_m", "weak", "reason", "seconds"} <= set(pairs["pairs"][0])
    assert len(list((tmp_path / "pose" / "pairs").glob("*.json"))) == 4


def test_rerun_reads_cached_pairs_and_recomputes_after_a_config_change(tmp_path, walk_sequence, monkeypatch):
    first = run_pose(walk_sequence, tmp_path, PoseConfig())
    (tmp_path / "pose" / "pairs" / "000002.json").unlink()
    calls = []
    original = pose_stage.estimate_relative_pose
    monkeypatch.setattr(pose_stage, "estimate_relative_pose", lambda *a, **k: calls.append(1) or original(*a, **k))
    second = run_pose(walk_sequence, tmp_path, PoseConfig(voxel_size_m=0.05))  # fusion only: pairs stay valid
    assert len(calls) == 1
    np.testing.assert_allclose(second.poses, first.poses, atol=1e-9)
    run_pose(walk_sequence, tmp_path, PoseConfig(max_points=3000))
    assert len(calls) == 5


def test_each_frame_view_is_computed_once_for_pairs_and_graph(tmp_path, walk_sequence, monkeypatch):
    computed, edges = [], []
    original_view, original_edge = pose_frames.frame_view, pose_edges._graph_edge
    monkeypatch.setattr(pose_frames, "frame_view",
                        lambda color, *a, **k: computed.append(color) or original_view(color, *a, **k))
    monkeypatch.setattr(pose_edges, "_graph_edge", lambda *a, **k: edges.append(1) or original_edge(*a, **k))
    run_pose(walk_sequence, tmp_path, PoseConfig())
    assert len(edges) == 5  # skip edges (i, i + 2) and (i, i + 3) verified on the pairs' views
    frames = [[j for j, color in enumerate(computed) if np.shares_memory(color, walk_sequence.color(i))]
              for i in range(len(walk_sequence))]
    assert len(computed) == len(walk_sequence) and all(len(f) == 1 for f in frames)  # once per frame


def test_the_graph_pass_slides_the_frame_cache_once_from_where_the_pairs_left_it(tmp_path, monkeypatch):
    sequence = SceneSequence(walk(12))
    monkeypatch.setattr(pose_frames.FrameCache.__init__, "__defaults__", (6,))  # keep 6 frames
    computed, informed = [], []
    original_view, original_cloud = pose_frames.frame_view, pose_frames._information_cloud
    monkeypatch.setattr(pose_frames, "frame_view",
                        lambda color, *a, **k: computed.append(color) or original_view(color, *a, **k))
    monkeypatch.setattr(pose_frames, "_information_cloud",
                        lambda depth, *a, **k: informed.append(depth) or original_cloud(depth, *a, **k))
    result = run_pose(sequence, tmp_path, PoseConfig(threads=1))  # one thread: the frames in the serial order
    counts = [sum(np.shares_memory(c, sequence.color(i)) for c in computed) for i in range(len(sequence))]
    assert counts == [2] * 6 + [1] * 6  # frames 6-11 were still cached; frame by frame and gap by gap: 3 each
    assert len(informed) == len(sequence)
    kinds = [e["kind"] for e in result.edges]
    assert kinds == sorted(kinds, key=["odometry", "skip", "loop"].index)  # the optimiser sees the old order
    assert [e["source"] for e in result.edges if e["kind"] == "odometry"] == list(range(11))


def test_graph_edges_take_their_own_odometry_iterations_and_pairs_stay_cached(tmp_path, walk_sequence, monkeypatch):
    run_pose(walk_sequence, tmp_path, PoseConfig())
    iterations = []
    original = pose_pair.rgbd_odometry

    def recording(*args, **kwargs):
        iterations.append(kwargs["iterations"] if "iterations" in kwargs else args[6])  # pairs pass it by name
        return original(*args, **kwargs)

    for module in (pose_pair, pose_edges):  # the pairs' and the graph's
        monkeypatch.setattr(module, "rgbd_odometry", recording)
    light = PoseConfig(graph_rgbd_iterations=(10, 5, 3))
    assert light.pair_key() == PoseConfig().pair_key()
    run_pose(walk_sequence, tmp_path, light)
    assert iterations and set(iterations) == {(10, 5, 3)}  # only the graph's edges ran: the pairs came from the cache


def test_long_edges_join_only_cameras_as_close_as_a_loop_closure():
    config = PoseConfig(graph_long_spans=(8, 16), graph_long_every=1, loop_max_distance_m=0.3, loop_max_angle_deg=30.0)
    line = np.tile(np.eye(4), (40, 1, 1))
    line[:, 0, 3] = 0.02 * np.arange(40)  # 2 cm a frame: 16 cm at span 8, 32 cm at span 16
    assert pose_edges._long_candidates(line, config) == [(i, i + 8) for i in range(32)]
    turn = np.tile(np.eye(4), (40, 1, 1))
    for i in range(40):
        turn[i, :3, :3] = se3_exp(np.array([0.0, 0.0, 0.0, 0.0, np.radians(3.0 * i), 0.0]))[:3, :3]  # 3 deg a frame
    assert pose_edges._long_candidates(turn, config) == [(i, i + 8) for i in range(32)]
    assert pose_edges._long_candidates(line, PoseConfig(graph_long_spans=())) == []
    assert pose_edges._long_candidates(line[:12], config) == [(i, i + 8) for i in range(4)]  # no span of 16 there
    every_4th = dataclasses.replace(config, graph_long_every=4)
    default = PoseConfig()
    assert (default.graph_long_spans, default.graph_long_every) == ((16, 32), 4)
    assert pose_edges._long_candidates(line, every_4th) == [(i, i + 8) for i in range(0, 32, 4)]
    line[12:, 0, 3] += 1.0  # a 1 m jump between frames 11 and 12: no close pair spans it
    assert pose_edges._long_candidates(line, every_4th) == [(0, 8), (12, 20), (16, 24), (20, 28), (24, 32), (28, 36)]


def test_long_edges_are_tried_without_the_score_cap_and_share_the_pair_cache(tmp_path, walk_sequence, monkeypatch):
    run_pose(walk_sequence, tmp_path, PoseConfig())
    tried = []
    original = pose_edges._graph_edge

    def recording(frames, i, j, poses, K, config, kind, max_score):
        tried.append((kind, j - i, max_score))
        return original(frames, i, j, poses, K, config, kind, max_score)

    monkeypatch.setattr(pose_edges, "_graph_edge", recording)
    config = PoseConfig(graph_long_spans=(4,))
    assert config.pair_key() == PoseConfig().pair_key()
    result = run_pose(walk_sequence, tmp_path, config)
    long = [t for t in tried if t[0] == "long"]
    assert [span for _, span, _ in long] == [4] and long[0][2] == float("inf")
    assert all(np.isfinite(cap) for kind, _, cap in tried if kind != "long")
    gt = invert(walk_sequence.gt_poses[0]) @ walk_sequence.gt_poses
    assert ate(result.poses, gt) < 2e-3


def test_frame_without_depth_becomes_weak_constant_velocity_pairs(tmp_path):
    poses = walk(5)
    sequence = SceneSequence(poses, broken_depth={2})
    result = run_pose(sequence, tmp_path, METHOD_ONLY)
    estimates = [p["estimate"] for p in result.pairs]
    assert estimates[2] == "constant-velocity" and result.pairs[2]["weak"]
    assert estimates[0] == "icp" and estimates[3] == "icp"
    relatives = [invert(result.poses[k + 1]) @ result.poses[k] for k in range(4)]
    np.testing.assert_allclose(relatives[2], relatives[1], atol=1e-9)  # previous motion repeated
    assert result.summary().startswith("4 pairs, 2 weak (2 replaced")  # pairs 1->2 and 2->3
    warnings = pose_stage.weak_pair_warnings(sequence, result.pairs, METHOD_ONLY)
    assert len(warnings) == 1  # the frame is named once, not its two weak pairs
    assert warnings[0].startswith(f"{Path('depth') / 'frame002.png'}: 0 pixels of usable depth")


def test_weak_pairs_with_depth_are_named_up_to_a_count():
    sequence = SceneSequence(walk(3))
    pairs = [{"index": 0, "source": "a", "target": "b", "weak": True, "estimate": "flow", "reason": "overlap 0.10"}
             for _ in range(pose_stage.MAX_PAIR_WARNINGS + 2)]
    pairs.append({"index": 1, "source": "b", "target": "c", "weak": False, "estimate": "icp", "reason": ""})
    warnings = pose_stage.weak_pair_warnings(sequence, pairs, PoseConfig())
    assert warnings[0] == "weak pair a -> b (overlap 0.10); its edge (the flow estimate) is weighted down in the pose graph"
    assert len(warnings) == pose_stage.MAX_PAIR_WARNINGS + 1 and warnings[-1].startswith("2 more weak pairs")
    assert pose_stage.weak_pair_warnings(sequence, pairs[:1], METHOD_ONLY)[0].endswith("the trajectory keeps the flow estimate")
    assert pose_stage.weak_pair_warnings(sequence, pairs[-1:], PoseConfig()) == []


def test_exception_in_one_pair_is_recorded_and_the_run_continues(tmp_path, walk_sequence, monkeypatch):
    original = pose_stage.estimate_relative_pose

    def failing_on_pair_1(color_t, *args, **kwargs):
        if np.shares_memory(color_t, walk_sequence.color(1)):
            raise FloatingPointError("overflow in test")
        return original(color_t, *args, **kwargs)

    monkeypatch.setattr(pose_stage, "estimate_relative_pose", failing_on_pair_1)
    result = run_pose(walk_sequence, tmp_path, PoseConfig())
    assert result.pairs[1]["estimate"] == "constant-velocity"
    assert result.pairs[1]["reason"] == "FloatingPointError: overflow in test"
    assert [p["weak"] for p in result.pairs] == [False, True, False, False]


def test_threads_give_the_serial_result_and_share_each_frame_once(tmp_path, walk_sequence, monkeypatch):
    serial = run_pose(walk_sequence, tmp_path / "one", PoseConfig(threads=1))
    computed, workers = [], set()
    original_view, original_start = pose_frames.frame_view, pose_stage.start_pair
    monkeypatch.setattr(pose_frames, "frame_view",
                        lambda color, *a, **k: computed.append(color) or original_view(color, *a, **k))
    monkeypatch.setattr(pose_stage, "start_pair",
                        lambda *a, **k: workers.add(threading.current_thread().name) or original_start(*a, **k))
    threaded = run_pose(walk_sequence, tmp_path / "three", PoseConfig(threads=3))
    assert any(name.startswith("pose") for name in workers)  # the pairs' first parts ran on the pool
    assert len(computed) == len(walk_sequence)  # each frame's view once, however many threads asked for it
    for a, b in zip(serial.pairs, threaded.pairs, strict=True):
        assert (a["estimate"], a["weak"], sorted(a["candidates"])) == (b["estimate"], b["weak"], sorted(b["candidates"]))
        np.testing.assert_allclose(a["transform"], b["transform"], atol=1e-9)
    assert [(e["source"], e["target"], e["kind"], e["pruned"]) for e in serial.edges] == \
        [(e["source"], e["target"], e["kind"], e["pruned"]) for e in threaded.edges]
    np.testing.assert_allclose(threaded.poses, serial.poses, atol=1e-9)


def test_a_failure_on_a_worker_thread_ends_the_run_with_its_own_error(tmp_path, walk_sequence, monkeypatch):
    def broken(*args, **kwargs):
        raise KeyError("a programming error in a pair's first part")

    monkeypatch.setattr(pose_stage, "start_pair", broken)
    with pytest.raises(KeyError, match="programming error"):
        run_pose(walk_sequence, tmp_path, PoseConfig(threads=2))
    assert not list((tmp_path / "pose" / "pairs").glob("*.json"))


def test_stage_1_takes_one_thread_per_core_up_to_a_cap_and_the_callers_count_when_given(monkeypatch):
    assert pose_stage.stage_threads(PoseConfig(threads=3)) == 3
    monkeypatch.setattr(pose_stage, "available_cores", lambda: 64)
    assert pose_stage.stage_threads(PoseConfig()) == pose_stage.DEFAULT_MAX_THREADS  # by default, up to a cap
    monkeypatch.setattr(pose_stage, "available_cores", lambda: 2)
    assert pose_stage.stage_threads(PoseConfig()) == 2
    assert pose_stage.stage_threads(PoseConfig(threads=3), threads=1) == 1  # --profile passes one


def test_stage_does_not_import_taichi():
    import subprocess
    import sys

    code = "import sys, taichi_gs.stages.pose, taichi_gs.flow, taichi_gs.icp; print('taichi' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip() == "False"


def test_near_tied_candidates_far_enough_apart_become_alternative_edges(monkeypatch):
    monkeypatch.setattr(pose_edges, "_information", lambda frames, i, j, T, config: np.eye(6))
    moved = {mm: se3_exp(np.array([mm / 1000, 0.0, 0.0, 0.0, 0.0, 0.0])) @ MOTION for mm in (0, 5, 5.5, 10, 20)}
    scores = {"constant-velocity": (0.100, 20), "flow": (0.1015, 5.5), "joint": (0.101, 5),
              "icp": (0.103, 10), "rgbd-icp": (0.100, 0), "rgbd-icp-prior": (0.1001, 0)}
    candidates = {name: {"score": score, "transform": moved[mm].tolist()} for name, (score, mm) in scores.items()}
    config = PoseConfig(verify_margin=0.02, graph_near_tie_mm=2.0, graph_weak_weight=0.01)
    for weak in (False, True):
        relative = pose_pair.RelativePose(MOTION, "rgbd-icp", weak=weak, candidates=candidates)
        ties = pose_edges._near_tie_edges(3, relative, None, config)
        # the prior is never offered, icp scores outside the 2% tie, rgbd-icp-prior sits on the chosen
        # transform, and joint lies 0.5 mm from flow, which comes first in the candidates' order
        assert [(e.estimate, e.source, e.target, e.kind, e.weak) for e in ties] == [("flow", 3, 4, "odometry", weak)]
        assert np.allclose(ties[0].transform, moved[5.5]) and ties[0].information[0, 0] == (0.01 if weak else 1.0)
