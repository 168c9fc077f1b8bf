"""PNG plots drawn with OpenCV (no plotting library needed): line plots and top-down trajectories."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .io.atomic import atomic_path

_COLORS = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75)]  # RGB
_FONT = cv2.FONT_HERSHEY_SIMPLEX
_MARGIN = (70, 20, 40, 50)  # left, right, top, bottom


def _nice_ticks(lo: float, hi: float, count: int = 5) -> np.ndarray:
    if not np.isfinite(lo) or not np.isfinite(hi) or hi <= lo:
        hi = lo + 1.0
    step = (hi - lo) / count
    magnitude = 10 ** np.floor(np.log10(step))
    step = min((m * magnitude for m in (1, 2, 5, 10) if m * magnitude >= step), default=step)
    return np.arange(np.ceil(lo / step) * step, hi + 1e-9 * step, step)


class _Canvas:
    """Axes mapping data coordinates to pixels on a white image."""

    def __init__(self, size: tuple[int, int], xlim: tuple[float, float], ylim: tuple[float, float], equal: bool = False):
        self.w, self.h = size
        self.image = np.full((self.h, self.w, 3), 255, dtype=np.uint8)
        left, right, top, bottom = _MARGIN
        self.box = (left, top, self.w - right, self.h - bottom)
        (x0, x1), (y0, y1) = xlim, ylim
        if equal:
            sx = (self.box[2] - self.box[0]) / (x1 - x0)
            sy = (self.box[3] - self.box[1]) / (y1 - y0)
            s = min(sx, sy)
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            half_w, half_h = (self.box[2] - self.box[0]) / s / 2, (self.box[3] - self.box[1]) / s / 2
            x0, x1, y0, y1 = cx - half_w, cx + half_w, cy - half_h, cy + half_h
        self.xlim, self.ylim = (x0, x1), (y0, y1)

    def to_px(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        (x0, x1), (y0, y1) = self.xlim, self.ylim
        l, t, r, b = self.box
        px = l + (np.asarray(x) - x0) / (x1 - x0) * (r - l)
        py = b - (np.asarray(y) - y0) / (y1 - y0) * (b - t)
        return np.stack([px, py], axis=-1).round().astype(np.int32)

    def axes(self, title: str, xlabel: str, ylabel: str) -> None:
        l, t, r, b = self.box
        for x in _nice_ticks(*self.xlim):
            (px, _), = self.to_px([x], [self.ylim[0]])
            cv2.line(self.image, (px, t), (px, b), (230, 230, 230), 1)
            cv2.putText(self.image, f"{x + 0.0:.3g}", (px - 15, b + 18), _FONT, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
        for y in _nice_ticks(*self.ylim):
            (_, py), = self.to_px([self.xlim[0]], [y])
            cv2.line(self.image, (l, py), (r, py), (230, 230, 230), 1)
            cv2.putText(self.image, f"{y + 0.0:.3g}", (5, py + 4), _FONT, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
        cv2.rectangle(self.image, (l, t), (r, b), (0, 0, 0), 1)
        cv2.putText(self.image, title, (l, 25), _FONT, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(self.image, xlabel, ((l + r) // 2 - 30, self.h - 10), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(self.image, ylabel, (5, t - 8), _FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)

    def polyline(self, x: np.ndarray, y: np.ndarray, color: tuple[int, int, int]) -> None:
        keep = np.isfinite(x) & np.isfinite(y)
        points = self.to_px(np.asarray(x)[keep], np.asarray(y)[keep])
        if len(points) > 1:
            cv2.polylines(self.image, [points.reshape(-1, 1, 2)], False, color, 2, cv2.LINE_AA)
        elif len(points) == 1:
            cv2.circle(self.image, tuple(points[0]), 3, color, -1, cv2.LINE_AA)

    def legend(self, names: list[str]) -> None:
        l, t, r, _ = self.box
        for k, name in enumerate(names):
            y = t + 15 + 16 * k
            cv2.line(self.image, (r - 140, y - 4), (r - 120, y - 4), _COLORS[k % len(_COLORS)], 2)
            cv2.putText(self.image, name, (r - 115, y), _FONT, 0.4, (0, 0, 0), 1, cv2.LINE_AA)

    def save(self, path: str | Path) -> None:
        with atomic_path(path) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(self.image, cv2.COLOR_RGB2BGR))


def _limits(values: list[np.ndarray], log: bool = False) -> tuple[float, float]:
    data = np.concatenate([np.asarray(v, dtype=np.float64).ravel() for v in values])
    data = data[np.isfinite(data)]
    if log:
        data = np.log10(data[data > 0])
    if data.size == 0:
        return 0.0, 1.0
    lo, hi = float(data.min()), float(data.max())
    pad = 0.05 * (hi - lo) if hi > lo else 0.5
    return lo - pad, hi + pad


def line_plot(path: str | Path, series: dict[str, tuple[np.ndarray, np.ndarray]], title: str,
              xlabel: str, ylabel: str, log_y: bool = False, size: tuple[int, int] = (720, 420)) -> None:
    """Write a PNG with one line per named (x, y) series; ``log_y`` plots log10(y)."""
    xs = [np.asarray(x, dtype=np.float64) for x, _ in series.values()]
    ys = [np.asarray(y, dtype=np.float64) for _, y in series.values()]
    if log_y:
        ys = [np.where(y > 0, np.log10(np.where(y > 0, y, 1.0)), np.nan) for y in ys]
        ylabel = f"log10 {ylabel}"
    canvas = _Canvas(size, _limits(xs), _limits(ys))
    canvas.axes(title, xlabel, ylabel)
    for k, (x, y) in enumerate(zip(xs, ys)):
        canvas.polyline(x, y, _COLORS[k % len(_COLORS)])
    canvas.legend(list(series))
    canvas.save(path)


def trajectory_plot(path: str | Path, trajectories: dict[str, np.ndarray], title: str = "trajectory (top view)",
                    size: tuple[int, int] = (640, 640)) -> None:
    """Top-down view (x right, z up the page) of camera positions from N x 4 x 4 poses."""
    xs = [T[:, 0, 3] for T in trajectories.values()]
    zs = [T[:, 2, 3] for T in trajectories.values()]
    canvas = _Canvas(size, _limits(xs), _limits(zs), equal=True)
    canvas.axes(title, "x (m)", "z (m)")
    for k, (x, z) in enumerate(zip(xs, zs)):
        canvas.polyline(x, z, _COLORS[k % len(_COLORS)])
    canvas.legend(list(trajectories))
    canvas.save(path)


def image_grid(path: str | Path, rows: list[list[np.ndarray]], column_titles: list[str],
               row_titles: list[str] | None = None, min_width: int = 240) -> None:
    """Write a PNG grid of images (float in [0, 1] or uint8; grey or RGB; resized to the first
    one's size, enlarged to at least ``min_width`` pixels), with a title above each column and,
    optionally, a label in each row's first image."""
    if not rows or not rows[0]:
        raise ValueError("image_grid needs at least one image")
    h, w = rows[0][0].shape[:2]
    zoom = max(1, -(-min_width // w))
    h, w = h * zoom, w * zoom
    header = 24
    canvas = np.full((header + h * len(rows), w * len(rows[0]), 3), 255, dtype=np.uint8)
    for c, title in enumerate(column_titles):
        cv2.putText(canvas, title, (c * w + 4, 17), _FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for r, row in enumerate(rows):
        for c, image in enumerate(row):
            tile = image if image.dtype == np.uint8 else np.round(np.clip(image, 0, 1) * 255).astype(np.uint8)
            if tile.ndim == 2:
                tile = np.repeat(tile[:, :, None], 3, axis=2)
            if tile.shape[:2] != (h, w):
                tile = cv2.resize(tile, (w, h), interpolation=cv2.INTER_NEAREST if zoom > 1 else cv2.INTER_AREA)
            canvas[header + r * h: header + (r + 1) * h, c * w: (c + 1) * w] = tile
        if row_titles:
            cv2.putText(canvas, row_titles[r], (4, header + r * h + 16), _FONT, 0.45, (255, 255, 0), 1, cv2.LINE_AA)
    with atomic_path(path) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
