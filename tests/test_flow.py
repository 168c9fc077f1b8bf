"""Optical flow: file formats, precomputed-flow folders, forward-backward check, DIS accuracy."""

from __future__ import annotations

import numpy as np
import pytest
from test_pose_scene import MOTION, exact_flow, pair

from taichi_gs.errors import InputError
from taichi_gs.geometry import se3_exp
from taichi_gs.stages.pose.flow import (FileFlow, dis_flow, finest_scale, finite_flow, forward_backward_mask,
                                        read_flow, rigid_flow, to_gray_u8, write_flow)


def random_flow(h: int = 12, w: int = 17, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0, 3, (h, w, 2)).astype(np.float32)


@pytest.mark.parametrize("suffix", [".flo", ".npy"])
def test_flow_files_round_trip(tmp_path, suffix):
    flow = random_flow()
    write_flow(tmp_path / f"f{suffix}", flow)
    back = read_flow(tmp_path / f"f{suffix}")
    assert back.dtype == np.float32 and back.shape == flow.shape
    np.testing.assert_array_equal(back, flow)


def test_flo_layout_is_middlebury(tmp_path):
    flow = random_flow(3, 5)
    write_flow(tmp_path / "f.flo", flow)
    data = (tmp_path / "f.flo").read_bytes()
    assert np.frombuffer(data[:4], "<f4")[0] == 202021.25
    assert tuple(np.frombuffer(data[4:12], "<i4")) == (5, 3)
    assert np.frombuffer(data[12:20], "<f4")[0] == flow[0, 0, 0]


def test_truncated_flo_is_an_input_error(tmp_path):
    write_flow(tmp_path / "f.flo", random_flow())
    (tmp_path / "f.flo").write_bytes((tmp_path / "f.flo").read_bytes()[:-8])
    with pytest.raises(InputError, match="truncated"):
        read_flow(tmp_path / "f.flo")


def test_file_flow_finds_index_and_stem_names_and_optional_backward(tmp_path):
    names = ["a", "b", "c"]
    write_flow(tmp_path / "000000.flo", random_flow(seed=1))
    write_flow(tmp_path / "b.npy", random_flow(seed=2))
    write_flow(tmp_path / "b_backward.npy", random_flow(seed=3))
    provider = FileFlow(tmp_path, names)
    provider.check()
    np.testing.assert_array_equal(provider.flow(0, 1), random_flow(seed=1))
    np.testing.assert_array_equal(provider.flow(1, 2), random_flow(seed=2))
    np.testing.assert_array_equal(provider.flow(2, 1), random_flow(seed=3))
    assert provider.flow(1, 0) is None


def test_file_flow_check_names_the_missing_pair(tmp_path):
    write_flow(tmp_path / "000000.flo", random_flow())
    with pytest.raises(InputError, match="pair 1"):
        FileFlow(tmp_path, ["a", "b", "c"]).check()


def test_forward_backward_mask_rejects_inconsistent_flow():
    forward = np.zeros((20, 30, 2), np.float32)
    forward[..., 0] = 3.0
    backward = -forward.copy()
    backward[5:10, 10:20] = [4.0, -2.0]  # reached from forward pixels in columns 7..16
    mask = forward_backward_mask(forward, backward)
    assert mask[15, 5] and mask[15, 20]
    assert not mask[7, 10]
    assert not mask[:, -3:].any()  # forward flow leaves the image
    assert mask.mean() > 0.7


def test_flow_with_either_component_not_finite_is_neither_finite_nor_consistent():
    forward = np.full((6, 8, 2), 0.5, np.float32)
    forward[1, 2, 0] = np.nan
    forward[3, 4, 1] = np.inf
    backward = -forward
    expected = np.ones((6, 8), bool)
    expected[1, 2] = expected[3, 4] = False
    np.testing.assert_array_equal(finite_flow(forward), expected)
    assert not forward_backward_mask(forward, np.nan_to_num(backward))[1, 2]
    assert not forward_backward_mask(forward, np.nan_to_num(backward))[3, 4]


def test_dis_flow_is_subpixel_on_the_test_scene():
    color_t, depth_t, color_t1, _, K = pair(MOTION, 320, 240)
    flow = dis_flow(to_gray_u8(color_t), to_gray_u8(color_t1), "medium")
    error = np.linalg.norm(flow - exact_flow(depth_t, K, MOTION), axis=-1)
    assert np.median(error[20:-20, 20:-20]) < 0.3


@pytest.mark.parametrize("preset_scale, width, finest_width, expected", [
    (1, 320, 320, 0), (1, 256, 320, 0), (1, 640, 320, 1), (1, 639, 320, 0), (2, 640, 320, 1), (1, 1280, 320, 1),
    (3, 1280, 320, 2), (1, 320, 0, 1), (2, 640, 0, 2),
])
def test_finest_scale_keeps_the_finest_level_at_least_as_wide_as_asked(preset_scale, width, finest_width, expected):
    assert finest_scale(preset_scale, width, finest_width) == expected


def test_rigid_flow_is_the_exact_flow_and_fills_holes_when_asked():
    _, depth_t, _, _, K = pair(MOTION)
    np.testing.assert_allclose(rigid_flow(depth_t, K, MOTION), exact_flow(depth_t, K, MOTION), atol=1e-3)
    holed = depth_t.copy()
    holed[:10] = 0.0
    assert np.isnan(rigid_flow(holed, K, MOTION)[:10]).all()
    filled = rigid_flow(holed, K, MOTION, fill_holes=True)
    assert np.isfinite(filled).all()
    np.testing.assert_allclose(filled[10:], exact_flow(depth_t, K, MOTION)[10:], atol=1e-3)
    assert not rigid_flow(np.zeros_like(depth_t), K, MOTION, fill_holes=True).any()


def test_seeded_dis_follows_a_motion_that_unseeded_dis_loses():
    motion = se3_exp(np.array([0.02, 0.0, 0.01, 0.0, np.radians(12.0), 0.0]))
    guess = se3_exp(np.array([0.0, 0.0, 0.0, 0.0, np.radians(10.0), 0.0]))
    color_t, depth_t, color_t1, _, K = pair(motion)
    a, b = to_gray_u8(color_t), to_gray_u8(color_t1)
    exact = exact_flow(depth_t, K, motion)
    unseeded = np.median(np.linalg.norm(dis_flow(a, b) - exact, axis=-1))
    seeded = np.median(np.linalg.norm(dis_flow(a, b, initial=rigid_flow(depth_t, K, guess, fill_holes=True)) - exact, axis=-1))
    assert unseeded > 10.0 and seeded < 0.5  # ~40 px and ~0.2 px measured


def test_a_hand_written_middlebury_file_is_read(tmp_path):
    flow = random_flow(2, 3, seed=5)
    header = np.array([202021.25], "<f4").tobytes() + np.array([3, 2], "<i4").tobytes()
    (tmp_path / "m.flo").write_bytes(header + flow.astype("<f4").tobytes())
    np.testing.assert_array_equal(read_flow(tmp_path / "m.flo"), flow)
