import cv2
import numpy as np

from taichi_gs import geometry as g
from taichi_gs.plots import line_plot, trajectory_plot


def coloured_pixels(path, rgb):
    image = cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB).astype(int)
    return int(np.sum(np.all(np.abs(image - np.array(rgb)) < 30, axis=2)))


def test_line_plot_draws_each_series(tmp_path):
    x = np.arange(50)
    line_plot(tmp_path / "l.png", {"a": (x, np.exp(-x / 10)), "b": (x, x * 0.01 + 0.001)}, "t", "it", "loss", log_y=True)
    assert coloured_pixels(tmp_path / "l.png", (31, 119, 180)) > 100
    assert coloured_pixels(tmp_path / "l.png", (255, 127, 14)) > 100


def test_trajectory_plot_handles_nan_and_writes_png(tmp_path):
    poses = np.stack([g.pose_from_rt(np.eye(3), [np.cos(a), 0, np.sin(a)]) for a in np.linspace(0, 3, 30)])
    poses[4] = np.nan
    trajectory_plot(tmp_path / "t.png", {"gt": poses})
    assert coloured_pixels(tmp_path / "t.png", (31, 119, 180)) > 100


def test_tick_labels_read_as_plain_numbers_not_exponents():
    from taichi_gs.plots import _plain_number

    assert [_plain_number(v) for v in (0.001, 0.01, 0.1, 1.0, 1000.0, 1500.0, 0.0)] == \
        ["0.001", "0.01", "0.1", "1", "1,000", "1,500", "0"]


def test_ground_truth_stays_visible_over_identical_estimates(tmp_path):
    poses = np.stack([g.pose_from_rt(np.eye(3), [x, 0, 0]) for x in np.linspace(-1, 1, 20)])
    trajectory_plot(tmp_path / "t.png", {"ground truth": poses, "pose": poses.copy(), "deblur": poses.copy()})
    image = cv2.imread(str(tmp_path / "t.png")).astype(int)
    h, w = image.shape[:2]
    centre = image[int(0.4 * h):int(0.6 * h), int(0.3 * w):int(0.7 * w)]  # the line, away from legend and labels
    dark = np.all(centre < 60, axis=2).sum()
    assert dark > 50  # the dashed black reference line is drawn on top


def test_depth_colour_scale_spans_its_range(tmp_path):
    from taichi_gs.plots import colour_map, colour_scale, image_grid

    depth = np.linspace(1.0, 4.0, 48 * 64).reshape(48, 64)
    depth[:4] = 0.0
    tile = colour_map(depth, 1.0, 4.0)
    assert np.all(tile[:4] == 0) and len(np.unique(tile[10:].reshape(-1, 3), axis=0)) > 20
    scale = colour_scale(240, 1.0, 4.0, "depth (m)")
    assert scale.shape[1] == 240 and scale.dtype == np.uint8
    image_grid(tmp_path / "g.png", [[np.zeros((48, 64, 3)), tile]], ["rgb", "depth"], footer=scale)
    grid = cv2.imread(str(tmp_path / "g.png"))
    assert grid.shape[0] == 24 + 48 * 4 + scale.shape[0]  # tiles enlarged to 256 px wide, scale below
