"""bench/pose.py: a jump of the reference scores as a break, the ATE between breaks aligns the stretches on
either side of it separately, a variant that changes only the graph starts from the pairs already computed, the
rotation error two independent estimates share against the reference is told from their own, and the oracle
chains each pair's candidate nearest the reference; its ``paper`` and ``method`` rows run the ``paper`` preset."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from format_fixtures import write_7scenes  # noqa: E402
import pose as bench_pose  # noqa: E402
from pose import (OURS, pair_scores, reference_breaks, reference_relatives, run_ours, segment_ate,  # noqa: E402
                  shared_rotation_error_deg)

from taichi_gs.evaluate import ate  # noqa: E402
from taichi_gs.io.load import load_sequence  # noqa: E402
from taichi_gs.stages.pose_config import PRESETS  # noqa: E402


def _walk(n: int) -> np.ndarray:
    poses = np.tile(np.eye(4), (n, 1, 1))
    for i in range(n):
        poses[i, :3, :3] = cv2.Rodrigues(np.array([0.0, 0.02 * i, 0.01 * i]))[0]
        poses[i, :3, 3] = [0.01 * i, 0.002 * i * i, 0.005 * i]
    return poses


def test_the_ate_between_breaks_ignores_a_jump_of_the_reference():
    estimate = _walk(30)
    reference = estimate.copy()
    reference[15:, :3, 3] += [0.035, 0.0, 0.0]  # the reference jumps 35 mm between frames 14 and 15
    assert ate(estimate, reference) > 0.005  # about 10 mm after the best rigid alignment
    assert segment_ate(estimate, reference, [14]) < 1e-9
    assert segment_ate(estimate, reference, []) == ate(estimate, reference)
    # a real error inside a stretch still counts
    wrong = estimate.copy()
    wrong[20:, :3, 3] += [0.0, 0.01, 0.0]
    assert segment_ate(wrong, reference, [14]) > 0.003


def test_breaks_are_pairs_far_above_the_reference_median():
    scores = np.full(21, 0.05)
    scores[10] = 0.3
    scores[4] = 0.12  # 2.4x: the spread of a real reference, not a break
    assert reference_breaks(scores, 3.0) == [10]
    assert reference_breaks(scores, 0.0) == []


def test_a_jumped_reference_pair_scores_far_worse_than_the_true_one(tmp_path):
    write_7scenes(tmp_path / "s")
    sequence = load_sequence(tmp_path / "s")
    truth = reference_relatives(sequence.gt_poses)
    jumped = [r.copy() for r in truth]
    jumped[1][:3, 3] += [0.035, 0.0, 0.0]
    true_scores, jumped_scores = pair_scores(sequence, truth), pair_scores(sequence, jumped)
    assert true_scores[0] == jumped_scores[0]
    assert jumped_scores[1] > 10 * true_scores[1]


def test_a_variant_that_changes_only_the_graph_starts_from_the_earlier_pairs(tmp_path, monkeypatch):
    found = []

    def fake_run_pose(sequence, work, config):
        pairs = work / "pose" / "pairs"
        found.append(sorted(p.name for p in pairs.glob("*.json")) if pairs.is_dir() else [])
        pairs.mkdir(parents=True, exist_ok=True)
        (pairs / f"{config.pair_key()}.json").write_text("{}")
        return SimpleNamespace(pairs=[{"seconds": 1.0, "weak": False}], edges=[], graph_seconds=0.5,
                               pairs_as_read_seconds=0.0)

    monkeypatch.setattr(bench_pose, "run_pose", fake_run_pose)
    caches = {}
    for method in ("ours", "ours no long edges", "ours no flow check", "ours long edges every frame"):
        _, seconds, _ = run_ours([0, 1], OURS[method], tmp_path / method, caches)
        assert seconds == 1.5  # the pairs' own seconds and the graph's
    ours_pairs = [f"{bench_pose.POSE_PRESETS['fast'].pair_key()}.json"]
    assert found == [[], ours_pairs, [], ours_pairs]  # the flow-check variant changes the pairs: its own cache


def test_the_paper_rows_run_the_paper_preset():
    assert OURS["paper"] == PRESETS["paper"]
    assert OURS["ours"] == PRESETS["fast"]
    # method: the paper preset with ICP capped for a benchmark's cost, nothing else changed
    assert dataclasses.replace(OURS["method"], icp_max_points=0) == PRESETS["paper"]
    assert OURS["method"].icp_max_points > 0


def _measured(sequence: str, method: str, ate_mm: float, *, synthetic: bool = True, width: int = 320,
              rot: float = 0.02, pairs=(1.0, 1.0, 2.0), seconds: float | None = 1.0):
    return bench_pose.Measured(sequence, method, synthetic, width, ate_mm, ate_mm, 1.0, rot, 0.001, 0.97,
                               np.array(pairs), seconds, "-")


def test_the_target_report_counts_each_target_and_names_the_misses():
    measured = [
        _measured("a", "ours", 1.0),
        _measured("a", "O3D hybrid", 4.0),
        _measured("a", "DIS RANSAC", 2.5),  # the best peer: 1.0 is not at most 2.5 / 3
        _measured("b", "ours", 6.0, pairs=(1.0, 1.0, 3.5), rot=0.12),
        _measured("b", "O3D ICP", 30.0),
        _measured("c", "ours", 9.0, synthetic=False, width=640, seconds=2.4),
        _measured("c", "ours no graph", 1.0, width=640, seconds=0.1),  # not ours: never counted
    ]
    lines = bench_pose.target_report(measured)
    assert lines == [
        "- ATE at most 1/3 of the best peer's: met on 1 of 2; missed: a (1.0 mm against DIS RANSAC's 2.5)",
        "- ATE at most 5 mm on synthetic sequences: met on 1 of 2; missed: b (6.0 mm)",
        "- RPE rotation under 0.1 deg: met on 2 of 3; missed: b (0.120 deg)",
        "- no pair error above 3x the median: met on 2 of 3; missed: b (3.5 mm, 3.5x 1.0)",
        "- at most 2 s per pair at 640x480: met on 0 of 1; missed: c (2.40 s)",
    ]


def test_the_target_report_says_when_no_sequence_applies():
    lines = bench_pose.target_report([_measured("a", "ours", 1.0, seconds=None)])
    assert lines[0] == "- ATE at most 1/3 of the best peer's: no sequence of this run applies"
    assert lines[-1] == "- at most 2 s per pair at 640x480: no sequence of this run applies"
    assert "met on 1 of 1" in lines[1]


def test_a_table_row_prints_the_measured_figures():
    line = bench_pose.row(_measured("a", "ours", 1.234, pairs=(0.5, 1.5, 4.0), seconds=None))
    assert line == "| a | ours | 1.2 | 1.2 | 1.0 | 0.020 | 0.001 | 0.970 | 1.5 / 3.5 / 4.0 | - | - |"


def test_sequence_folders_are_read_as_the_options_say(tmp_path):
    write_7scenes(tmp_path / "kitchen")  # three frames
    whole = load_sequence(tmp_path / "kitchen", camera="shipped")
    for first, every, frames, label in ((1, 1, 2, "kitchen from 1 x0.5"), (0, 2, 0, "kitchen every 2 x0.5")):
        args = SimpleNamespace(sequence=[tmp_path / "kitchen"], first=first, every=every, camera="shipped", scale=0.5,
                               frames=frames)
        [(name, sequence, synthetic)] = list(bench_pose.sequences(args, tmp_path))
        kept = [first, first + every]
        assert name == label and not synthetic
        assert sequence.names == [whole.names[i] for i in kept]
        assert (sequence.intrinsics.width, sequence.intrinsics.height) == (40, 30)
        assert np.allclose(sequence.gt_poses, whole.gt_poses[kept])
    plain = SimpleNamespace(sequence=[tmp_path / "kitchen"], first=0, every=1, camera=None, scale=1.0, frames=0)
    assert [name for name, _, _ in bench_pose.sequences(plain, tmp_path)] == ["kitchen"]


def test_the_7_scenes_grid_is_read_as_shipped_or_registered(tmp_path, monkeypatch):
    """``--real-camera`` picks the reader's camera for the 7-Scenes grid, and a registered row says so."""
    write_7scenes(tmp_path / "kitchen")
    monkeypatch.setattr(bench_pose, "SEVEN_SCENES", tmp_path / "kitchen")
    for camera, label in (("shipped", "7-Scenes every 1 x1"), ("registered", "7-Scenes every 1 x1 registered")):
        args = SimpleNamespace(sequence=None, size="40x30", scenes="", trajectories="handheld", seeds="0",
                               synth_readout_ms=0.0, real_every="1", real_scale=1.0, real_camera=camera, frames=0)
        [(name, sequence, synthetic)] = list(bench_pose.sequences(args, tmp_path))
        assert name == label and not synthetic
        assert sequence.source["camera"] == camera
        assert np.allclose(sequence.gt_poses, load_sequence(tmp_path / "kitchen", camera=camera).gt_poses)


def _rotated(T: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ cv2.Rodrigues(rotvec)[0]
    return out


def test_the_shared_rotation_error_keeps_what_two_estimates_have_in_common_and_drops_their_own_noise():
    rng = np.random.default_rng(3)
    truths = reference_relatives(_walk(401))
    common = np.radians(0.2) * rng.standard_normal((400, 3)) / np.sqrt(3)  # 0.2 deg RMS, in both estimates
    a = [_rotated(t, c + np.radians(0.3) * rng.standard_normal(3) / np.sqrt(3)) for t, c in zip(truths, common)]
    b = [_rotated(t, c + np.radians(0.3) * rng.standard_normal(3) / np.sqrt(3)) for t, c in zip(truths, common)]
    shared = shared_rotation_error_deg(a, b, truths)
    assert 0.17 < shared < 0.23  # each estimate alone: 0.36 deg RMS
    independent = [_rotated(t, np.radians(0.3) * rng.standard_normal(3) / np.sqrt(3)) for t in truths]
    assert shared_rotation_error_deg(a[:200] + [None] * 200, b[:200] + [None] * 200, truths) > 0.15  # None: skipped
    assert shared_rotation_error_deg(independent, b, truths) < 0.08
    assert np.isnan(shared_rotation_error_deg([None] * 400, b, truths))


def test_the_oracle_chains_the_candidate_nearest_the_reference_in_every_pair():
    gt = _walk(6)
    truths = reference_relatives(gt)
    off = np.eye(4)
    off[:3, 3] = [0.004, 0.0, 0.0]
    pairs = []
    for k, truth in enumerate(truths):
        near, far = _rotated(truth, np.radians([0.01, 0.0, 0.0])), off @ truth
        first, second = (far, near) if k % 2 else (near, far)  # the nearer one comes first or second
        pairs.append({"transform": far.tolist(), "candidates": {"a": {"transform": first.tolist()},
                                                                "b": {"transform": second.tolist()}}})
    poses = bench_pose.oracle(SimpleNamespace(pairs=pairs), gt)
    assert ate(poses, gt) < 1e-3
    assert bench_pose.pair_errors_mm(poses, gt).max() < 0.1
    assert bench_pose.pair_errors_mm(bench_pose.derived(SimpleNamespace(pairs=pairs), "ours no graph"), gt).min() > 3.9
