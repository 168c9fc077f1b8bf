"""bench/real_blur.py (issue 84): a sequence's facts from the files ``import --average`` writes, and one table row
per run from its metrics, the gain over the blurred input included."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np

from taichi_gs.io.images import to_uint8, write_png

BENCH = Path(__file__).resolve().parents[1] / "bench" / "real_blur.py"
spec = importlib.util.spec_from_file_location("real_blur", BENCH)
real_blur = importlib.util.module_from_spec(spec)
spec.loader.exec_module(real_blur)


def averaged_folder(root: Path) -> Path:
    """The files of an averaged sequence that the benchmark reads (no images needed)."""
    root.mkdir()
    (root / "intrinsics.json").write_text(json.dumps({"width": 320, "height": 240}))
    (root / "frames.txt").write_text("# timestamp rgb depth\n" + "".join(f"{i} rgb/{i}.png depth/{i}.png\n" for i in range(4)))
    (root / "blur.json").write_text(json.dumps({"window": 5, "frames": [{"median_px": m} for m in (3.0, 1.0, 2.0, 9.0)]}))
    return root


def test_row_and_table_from_a_runs_metrics(tmp_path):
    sequence = averaged_folder(tmp_path / "7s_w5_320")
    metrics = {"trajectory": {"pose": {"ate_m": 0.021}, "deblur": {"ate_m": 0.018}},
               "images": {"test": {"psnr_db": 28.5, "ssim": 0.86, "blurred_input_psnr_db": 25.5,
                                   "blurred_input_ssim": 0.80}},
               "stages": {"pose": {"seconds": 40.0}, "refine": {"seconds": 1.0}, "deblur": {"seconds": 79.0}}}
    seconds = real_blur.stage_seconds(metrics, ("pose", "refine", "deblur"))
    row = real_blur.row(sequence, tmp_path / "run", "ours", metrics, seconds)
    assert (row["window"], row["size"], row["frames"], row["streak_px"]) == (5, "320x240", 4, 3.0)
    assert row["stage1_ate_mm"] == 21.0 and row["final_ate_mm"] == 18.0 and row["seconds_per_frame"] == 30.0
    line = real_blur.table([row]).splitlines()[-1]
    assert "| 28.50 / 0.860 | 25.50 / 0.800 | 3.00 / 0.060 | - | - (-) | 30.0 |" in line


def test_a_run_without_stage_3_images_prints_dashes(tmp_path):
    sequence = averaged_folder(tmp_path / "seq")
    row = real_blur.row(sequence, tmp_path / "run", "paper", {"trajectory": {}, "images": None, "stages": {}}, 12.0)
    assert "| - / - | - / - | - / - | - | - (-) | 3.0 |" in real_blur.table([row])


def test_registration_finds_a_render_that_sits_off_the_centre_frame(tmp_path):
    """A held-out render that is the centre frame moved 1.5 px sideways: the shift is found, and the moved-back
    render scores far above the render as it sits (no as_read/ folder: as read is the render itself)."""
    sequence = averaged_folder(tmp_path / "seq")
    run = tmp_path / "run"
    (run / "deblur" / "renders" / "sharp").mkdir(parents=True)
    (run / "deblur" / "split.json").write_text(json.dumps({"train": [0, 2, 3], "test": [1]}))
    (sequence / "sharp").mkdir()
    texture = cv2.GaussianBlur(np.random.default_rng(0).uniform(size=(240, 320, 3)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    write_png(sequence / "sharp" / "1.png", to_uint8(texture))
    moved = cv2.warpAffine(texture, np.float32([[1, 0, 1.5], [0, 1, 0]]), (320, 240), flags=cv2.INTER_CUBIC,
                           borderMode=cv2.BORDER_REFLECT)
    write_png(run / "deblur" / "renders" / "sharp" / "1.png", to_uint8(moved))
    figures = real_blur.registration(sequence, run)
    assert abs(figures["shift_px"] - 1.5) < 0.1
    assert figures["shifted_psnr_db"] > figures["as_read_psnr_db"] + 10.0
