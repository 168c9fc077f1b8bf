"""The sequence reader: both layouts, association, ground truth, and one test per bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from taichi_gs.errors import InputError
from taichi_gs.io.formats.tum import _open_tum_layout, associate, typical_offsets
from taichi_gs.io.load import load_sequence
from taichi_gs.io.sequence import IntrinsicsOverride
from conftest import write_frame_images, write_intrinsics


def test_own_layout_reads_frames_and_ground_truth(own_layout):
    seq = load_sequence(own_layout)
    assert len(seq) == 3 and seq.layout == "taichi-gs"
    color, depth = seq.color(1), seq.depth(1)
    assert color.shape == (30, 40, 3) and color.dtype == np.float32 and 0 <= color.min() and color.max() <= 1
    assert depth.dtype == np.float32 and np.allclose(depth, 2.0)
    assert np.allclose(seq.gt_poses[2][:3, 3], [0.2, 0, 0]) and seq.names == ["000000", "000001", "000002"]
    assert np.allclose(seq.K(), [[50, 0, 20], [0, 50, 15], [0, 0, 1]])


def test_tum_layout_associates_and_interpolates_ground_truth(tum_layout):
    seq = load_sequence(tum_layout)
    assert len(seq) == 4 and seq.layout == "tum"
    assert seq.depth_paths[2].name == "000002.png"
    # Ground truth x = (t - 1000) at 100 Hz, linearly interpolated to the colour timestamps.
    assert np.allclose(seq.gt_poses[:, 0, 3], seq.timestamps - 1000.0, atol=1e-9)


def test_associate_uses_each_stamp_once_closest_first():
    a = np.array([0.0, 0.010, 0.100])
    b = np.array([0.004, 0.012, 0.5])
    assert associate(a, b, 0.02) == [(0, 0), (1, 1)]


def half_frame_streams(frames: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Colour at 30 Hz with +-3 ms jitter, depth at 30 Hz 15.5 ms before each colour slot (so also 17.8 ms
    after the previous one), as Kinect v1 streams in TUM fr1: the closest depth frame flips sides with the jitter."""
    rng = np.random.default_rng(0)
    colour = 1000.0 + np.arange(frames) / 30 + rng.uniform(-0.003, 0.003, frames)
    depth = 1000.0 + np.arange(frames + 1) / 30 - 0.0155
    return colour, depth


def test_pairing_keeps_depth_on_one_side_of_half_frame_offset_streams():
    colour, depth = half_frame_streams()
    closest = associate(colour, depth, 0.02)
    sides = np.sign([depth[j] - colour[i] for i, j in closest])
    assert (sides < 0).any() and (sides > 0).any()  # plain closest-first pairing flips
    offsets = typical_offsets(colour, depth, closest)
    kept = associate(colour, depth, 0.02, offsets)
    assert [i for i, _ in kept] == list(range(len(colour)))  # every colour frame keeps a depth frame
    gaps = np.array([depth[j] - colour[i] for i, j in kept])
    assert np.all(gaps < 0) and np.all(np.abs(gaps) <= 0.02)
    # consecutive depth frames are now one depth interval apart, as their colour frames are
    assert np.all(np.diff([j for _, j in kept]) == 1)


def test_pairing_of_synchronised_streams_is_unchanged():
    colour = 1000.0 + np.arange(20) / 30
    depth = colour + np.random.default_rng(1).uniform(-0.002, 0.002, 20)
    closest = associate(colour, depth, 0.02)
    assert associate(colour, depth, 0.02, typical_offsets(colour, depth, closest)) == closest


def half_frame_folder(folder: Path, frames: int = 12) -> Path:
    """A TUM folder of :func:`half_frame_streams`: depth frame i is stamped 15.5 ms before colour frame i."""
    colour, depth = half_frame_streams(frames)
    rgb_lines, depth_lines = [], []
    for i in range(len(depth)):
        rgb, depth_name = write_frame_images(folder, i)
        depth_lines.append(f"{depth[i]:.6f} {depth_name}")
        if i < len(colour):
            rgb_lines.append(f"{colour[i]:.6f} {rgb}")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    write_intrinsics(folder)
    return folder


def test_tum_reader_pairs_each_colour_frame_with_the_depth_frame_on_the_common_side(tmp_path):
    seq = load_sequence(half_frame_folder(tmp_path / "tum"))
    assert [p.name for p in seq.depth_paths] == [f"{i:06d}.png" for i in range(12)]


def test_a_depth_latency_pairs_each_colour_frame_with_the_depth_frame_after_it(tmp_path):
    """Depth stamped 15.5 ms before and 17.8 ms after each colour frame: a depth frame that shows the moment 15 ms
    before its stamp is nearly simultaneous with the colour frame before it, so with that latency every colour
    frame takes the next depth frame, still one depth interval apart."""
    folder = half_frame_folder(tmp_path / "tum")
    seq = _open_tum_layout(folder, IntrinsicsOverride(), 0.02, depth_latency=0.015)
    assert [p.name for p in seq.depth_paths] == [f"{i:06d}.png" for i in range(1, 13)]
    assert [p.name for p in _open_tum_layout(folder, IntrinsicsOverride(), 0.02).depth_paths] == \
        [f"{i:06d}.png" for i in range(12)]


def test_depth_timestamps_are_the_moment_each_paired_depth_frame_shows_and_survive_import(tmp_path):
    """A TUM reading keeps each paired depth frame's stamp minus the latency; import writes it as frames.txt's 4th
    column, the own layout reads it back, and picking frames keeps it with its frame."""
    from taichi_gs.io.convert import import_sequence
    from taichi_gs.io.load import subsample

    folder = half_frame_folder(tmp_path / "tum")
    seq = _open_tum_layout(folder, IntrinsicsOverride(), 0.02, depth_latency=0.015)
    depth_stamps = np.array([float(line.split()[0]) for line in (folder / "depth.txt").read_text().splitlines()])
    np.testing.assert_allclose(seq.depth_timestamps, depth_stamps[1:13] - 0.015)
    np.testing.assert_allclose(seq.depth_offsets(), seq.depth_timestamps - seq.timestamps)
    assert np.all(np.abs(seq.depth_offsets()) < 0.01)  # the next depth frame: 17.8 ms after, 2.8 ms once shifted

    imported = load_sequence(import_sequence(seq, tmp_path / "own"))
    np.testing.assert_allclose(imported.depth_offsets(), seq.depth_offsets(), atol=2e-6)
    np.testing.assert_allclose(subsample(imported, 2, first=1).depth_offsets(), seq.depth_offsets()[1::2], atol=2e-6)


def test_a_frame_list_without_depth_timestamps_pairs_depth_with_colour(own_layout):
    seq = load_sequence(own_layout)
    assert seq.depth_timestamps is None
    np.testing.assert_array_equal(seq.depth_offsets(), np.zeros(len(seq)))


@pytest.mark.parametrize("fourth, message", [(["1.0", None, "2.0"], "2 of 3 lines give a depth timestamp"),
                                             (["1.0", "soon", "2.0"], "is not a number"),
                                             (["1.0", "nan", "2.0"], "NaN or inf")])
def test_a_bad_depth_timestamp_column_gives_a_one_line_error(own_layout, fourth, message):
    lines = [line for line in (own_layout / "frames.txt").read_text().splitlines() if not line.startswith("#")]
    (own_layout / "frames.txt").write_text("\n".join(
        line if extra is None else f"{line} {extra}" for line, extra in zip(lines, fourth)) + "\n")
    with pytest.raises(InputError, match=message) as error:
        load_sequence(own_layout)
    assert "frames.txt" in str(error.value) and "\n" not in str(error.value)


def test_cli_flags_override_intrinsics(own_layout):
    seq = load_sequence(own_layout, IntrinsicsOverride(fx=99.0, depth_scale=2500.0))
    assert seq.intrinsics.fx == 99.0 and seq.intrinsics.fy == 50.0
    assert np.allclose(seq.depth(0), 4.0)


def expect_error(folder, match, file=None, **kwargs):
    with pytest.raises(InputError, match=match) as info:
        seq = load_sequence(folder, **kwargs)
        seq.check_all()
    if file is not None:
        assert info.value.path is not None and info.value.path.name == file
    assert "\n" not in str(info.value)
    return info.value


def test_missing_folder(tmp_path):
    expect_error(tmp_path / "nope", "folder not found", file="nope")


def test_missing_lists(tmp_path):
    expect_error(tmp_path, "no known RGB-D layout")


def test_tum_missing_depth_list(tum_layout):
    (tum_layout / "depth.txt").unlink()
    expect_error(tum_layout, "file list missing", file="depth.txt")


def test_missing_frame_file(own_layout):
    (own_layout / "depth" / "000001.png").unlink()
    expect_error(own_layout, "missing", file="000001.png")


def test_corrupt_image(own_layout):
    (own_layout / "rgb" / "000002.png").write_bytes(b"\x89PNG garbage")
    expect_error(own_layout, "unreadable or corrupt", file="000002.png")


def test_depth_not_16_bit(own_layout):
    cv2.imwrite(str(own_layout / "depth" / "000001.png"), np.full((30, 40), 10, dtype=np.uint8))
    expect_error(own_layout, "16-bit", file="000001.png")


def test_colour_depth_size_mismatch(own_layout):
    cv2.imwrite(str(own_layout / "depth" / "000001.png"), np.full((20, 40), 10000, dtype=np.uint16))
    expect_error(own_layout, "40x20", file="000001.png")


def test_no_association_within_tolerance(tum_layout):
    lines = (tum_layout / "depth.txt").read_text().splitlines()
    shifted = [lines[0]] + [f"{float(l.split()[0]) + 5:.6f} {l.split()[1]}" for l in lines[1:]]
    (tum_layout / "depth.txt").write_text("\n".join(shifted) + "\n")
    expect_error(tum_layout, "no colour frame has a depth frame", file="rgb.txt")


def test_non_increasing_timestamps(own_layout):
    text = (own_layout / "frames.txt").read_text().replace("0.066667", "0.010000")
    (own_layout / "frames.txt").write_text(text)
    expect_error(own_layout, "not increasing", file="frames.txt")


@pytest.mark.parametrize("scale, shown", [(50.0, "200"), (5e6, "0.002")])
def test_absurd_depth_scale(own_layout, scale, shown):
    err = expect_error(own_layout, "median depth", override=IntrinsicsOverride(depth_scale=scale))
    assert shown in str(err) and "--depth-scale" in str(err)


def test_nan_in_depth(own_layout):
    rgb, _ = write_frame_images(own_layout, 7)
    depth = np.full((30, 40), 2.0, dtype=np.float32)
    depth[3, 3] = np.nan
    np.save(own_layout / "depth" / "000007.npy", depth)
    with open(own_layout / "frames.txt", "a") as f:
        f.write(f"0.300000 {rgb} depth/000007.npy\n")
    expect_error(own_layout, "NaN or inf", file="000007.npy")


def test_nan_in_intrinsics(own_layout):
    data = json.loads((own_layout / "intrinsics.json").read_text())
    data["fx"] = float("nan")
    (own_layout / "intrinsics.json").write_text(json.dumps(data))
    expect_error(own_layout, "finite", file="intrinsics.json")


def test_nan_timestamp(own_layout):
    text = (own_layout / "frames.txt").read_text().replace("0.033333", "nan")
    (own_layout / "frames.txt").write_text(text)
    expect_error(own_layout, "NaN", file="frames.txt")


def test_nan_in_ground_truth(own_layout):
    (own_layout / "groundtruth.txt").write_text("0.0 nan 0 0 0 0 0 1\n")
    expect_error(own_layout, "NaN", file="groundtruth.txt")


def test_fewer_than_two_frames(own_layout):
    lines = (own_layout / "frames.txt").read_text().splitlines()[:2]
    (own_layout / "frames.txt").write_text("\n".join(lines) + "\n")
    expect_error(own_layout, "1 frame", file="own")


def test_missing_intrinsics(own_layout):
    (own_layout / "intrinsics.json").unlink()
    expect_error(own_layout, "fx, fy, cx, cy not given", file="intrinsics.json")
    assert len(load_sequence(own_layout, IntrinsicsOverride(fx=50, fy=50, cx=20, cy=15))) == 3


def test_no_valid_depth(own_layout):
    for i in range(3):
        cv2.imwrite(str(own_layout / "depth" / f"{i:06d}.png"), np.zeros((30, 40), dtype=np.uint16))
    expect_error(own_layout, "no valid depth")


def test_reader_never_writes_into_input(own_layout):
    before = sorted((p, p.stat().st_mtime_ns) for p in Path(own_layout).rglob("*"))
    load_sequence(own_layout).check_all()
    assert sorted((p, p.stat().st_mtime_ns) for p in Path(own_layout).rglob("*")) == before
