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
