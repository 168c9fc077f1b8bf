"""bench/pgt_to_tum.py and bench/pose.py --reference: a 7-Scenes pseudo ground truth file (world-to-camera, COLMAP's
convention) becomes the camera-to-world poses of one sequence, stamped as the 7-Scenes reader stamps its frames."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

from format_fixtures import write_7scenes  # noqa: E402
from pgt_to_tum import read_pgt  # noqa: E402
from pose import reference_poses  # noqa: E402

from taichi_gs.evaluate import ate  # noqa: E402
from taichi_gs.geometry import invert, rotmat_to_quat  # noqa: E402
from taichi_gs.io.formats.common import NOMINAL_FPS  # noqa: E402
from taichi_gs.io.load import load_sequence  # noqa: E402
from taichi_gs.io.trajectory import write_tum  # noqa: E402


def _pgt_line(sequence: str, frame: int, camera_to_world: np.ndarray) -> str:
    world_to_camera = invert(camera_to_world)
    q, t = rotmat_to_quat(world_to_camera[:3, :3]), world_to_camera[:3, 3]
    return f"{sequence}/frame-{frame:06d}.color.png {' '.join(f'{v:.9f}' for v in (*q, *t))} 525.505"


def test_a_pseudo_ground_truth_file_gives_the_sequence_its_own_poses(tmp_path):
    write_7scenes(tmp_path / "kitchen")
    sequence = load_sequence(tmp_path / "kitchen", camera="shipped")
    lines = [_pgt_line("seq-02", 0, np.eye(4))]  # another sequence's line, left out
    lines += [_pgt_line("seq-01", i, pose) for i, pose in reversed(list(enumerate(sequence.gt_poses)))]
    (tmp_path / "pgt.txt").write_text("\n".join(lines) + "\n")

    frames, poses = read_pgt(tmp_path / "pgt.txt", "seq-01")
    assert frames.tolist() == list(range(len(sequence.gt_poses)))
    write_tum(tmp_path / "reference.txt", frames / NOMINAL_FPS, poses)
    assert np.allclose(reference_poses(tmp_path / "reference.txt", sequence.timestamps), sequence.gt_poses, atol=1e-7)
    kept = sequence.timestamps[::2]
    assert np.allclose(reference_poses(tmp_path / "reference.txt", kept), sequence.gt_poses[::2], atol=1e-7)


def test_a_reference_without_a_frame_of_the_sequence_is_refused(tmp_path):
    write_tum(tmp_path / "reference.txt", np.array([0.0, 1 / 30]), np.tile(np.eye(4), (2, 1, 1)))
    with pytest.raises(SystemExit, match=r"no pose at time 0\.0667 s \(frame 2 of the sequence\)"):
        reference_poses(tmp_path / "reference.txt", np.array([0.0, 1 / 30, 2 / 30]))


def test_a_file_without_the_sequence_is_refused(tmp_path):
    (tmp_path / "pgt.txt").write_text(_pgt_line("seq-03", 0, np.eye(4)) + "\n")
    with pytest.raises(SystemExit, match="no line for seq-01"):
        read_pgt(tmp_path / "pgt.txt", "seq-01")


def test_the_bench_scores_a_real_sequence_against_both_references(tmp_path, monkeypatch, capsys):
    import pose as bench_pose

    write_7scenes(tmp_path / "kitchen")
    sequence = load_sequence(tmp_path / "kitchen", camera="shipped")
    shifted = sequence.gt_poses.copy()
    shifted[1:, 0, 3] += 0.01  # a second reference 10 mm off from frame 1 on
    write_tum(tmp_path / "other.txt", sequence.timestamps, shifted)
    monkeypatch.setattr(sys, "argv", ["pose.py", "--sequence", str(tmp_path / "kitchen"), "--camera", "shipped",
                                      "--methods", "O3D ICP", "--reference", str(tmp_path / "other.txt"),
                                      "--gt-check-ratio", "0", "--break-ratio", "0", "--out", str(tmp_path / "out")])
    bench_pose.main()
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines() if line.startswith("| kitchen")]
    assert [(r[0], r[1]) for r in rows] == [("| kitchen vs other", "the sequence's own reference"),
                                            ("| kitchen", "O3D ICP"), ("| kitchen vs other", "O3D ICP")]
    expected = 1000 * ate(sequence.gt_poses, shifted)
    assert expected > 1.0 and float(rows[0][2]) == pytest.approx(expected, abs=0.05)
