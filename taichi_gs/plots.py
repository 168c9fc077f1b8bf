"""PNG plots: line plots and top-down trajectories with matplotlib (Agg, no display needed), and
image grids with OpenCV (pixel-exact tiles), optionally with a colour scale underneath."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from .io.atomic import atomic_path

_FONT = cv2.FONT_HERSHEY_SIMPLEX
DEPTH_COLORMAP = "turbo"


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=fig.dpi)
    _pyplot().close(fig)


def _plain_number(value: float, _position: int | None = None) -> str:
    """Tick labels as plain numbers (0.001, 1000), not exponents (1e-03, 1e+03)."""
    if value == 0:
        return "0"
    if 1e-4 <= abs(value) < 1e6:
        return f"{value:.6f}".rstrip("0").rstrip(".") if abs(value) < 1 else f"{value:,.6g}"
    return f"{value:.0e}"


def line_plot(path: str | Path, series: dict[str, tuple[np.ndarray, np.ndarray]], title: str,
              xlabel: str, ylabel: str, log_y: bool = False, size: tuple[int, int] = (720, 420)) -> None:
    """Write a PNG with one line per named (x, y) series; ``log_y`` uses a logarithmic y axis
    (ticks still read as plain numbers). Non-finite points are left out."""
    from matplotlib.ticker import FuncFormatter

    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    for name, (x, y) in series.items():
        x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
        keep = np.isfinite(x) & np.isfinite(y) & ((y > 0) if log_y else True)
        ax.plot(x[keep], y[keep], label=name, linewidth=1.5, marker="o" if keep.sum() == 1 else None)
    if log_y:
        ax.set_yscale("log")
    ax.xaxis.set_major_formatter(FuncFormatter(_plain_number))
    ax.yaxis.set_major_formatter(FuncFormatter(_plain_number))
    ax.set(title=title, xlabel=xlabel, ylabel=ylabel)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="best")
    fig.tight_layout()
    _save(fig, path)


def trajectory_plot(path: str | Path, trajectories: dict[str, np.ndarray], title: str = "trajectory (top view)",
                    size: tuple[int, int] = (640, 640), reference: str = "ground truth") -> None:
    """Top-down view (x right, z up the page, metres, equal axes) of camera positions from
    N x 4 x 4 poses; the ``reference`` trajectory is drawn last, dashed, so estimates lying on it
    do not hide it."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(size[0] / 100, size[1] / 100), dpi=100)
    order = [name for name in trajectories if name != reference] + [name for name in trajectories if name == reference]
    for name in order:
        T = np.asarray(trajectories[name], dtype=np.float64)
        if name == reference:
            ax.plot(T[:, 0, 3], T[:, 2, 3], "k--", linewidth=1.5, label=name, zorder=10)
        else:
            ax.plot(T[:, 0, 3], T[:, 2, 3], linewidth=3, label=name)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(title=title, xlabel="x (m)", ylabel="z (m)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best")
    fig.tight_layout()
    _save(fig, path)


def colour_scale(width: int, lo: float, hi: float, label: str, cmap: str = DEPTH_COLORMAP) -> np.ndarray:
    """A horizontal colour bar (RGB uint8, ``width`` pixels wide) from ``lo`` to ``hi``, labelled."""
    from matplotlib.colorbar import ColorbarBase
    from matplotlib.colors import Normalize

    plt = _pyplot()
    fig = plt.figure(figsize=(width / 100, 0.7), dpi=100)
    ax = fig.add_axes((0.05, 0.55, 0.9, 0.3))
    ColorbarBase(ax, cmap=plt.get_cmap(cmap), norm=Normalize(lo, hi), orientation="horizontal")
    ax.set_xlabel(label, fontsize=8, labelpad=1)
    ax.tick_params(labelsize=7, pad=1)
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].copy()
    plt.close(fig)
    return image


def colour_map(values: np.ndarray, lo: float, hi: float, cmap: str = DEPTH_COLORMAP) -> np.ndarray:
    """Values mapped to RGB floats in [0, 1] by ``cmap`` over [lo, hi]; non-positive values black."""
    import matplotlib

    rgb = matplotlib.colormaps[cmap](np.clip((values - lo) / max(hi - lo, 1e-12), 0, 1))[..., :3]
    return np.where((values > 0)[..., None], rgb, 0.0)


def image_grid(path: str | Path, rows: list[list[np.ndarray]], column_titles: list[str],
               row_titles: list[str] | None = None, min_width: int = 240, footer: np.ndarray | None = None) -> None:
    """Write a PNG grid of images (float in [0, 1] or uint8; grey or RGB; resized to the first
    one's size, enlarged to at least ``min_width`` pixels), with a title above each column and,
    optionally, a label in each row's first image and a ``footer`` image (e.g. a colour scale)
    under the last column."""
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
    if footer is not None:
        strip = np.full((footer.shape[0], canvas.shape[1], 3), 255, dtype=np.uint8)
        fw = min(footer.shape[1], canvas.shape[1])
        strip[:, canvas.shape[1] - fw:] = footer[:, :fw]
        canvas = np.concatenate([canvas, strip], axis=0)
    with atomic_path(path) as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(canvas, cv2.COLOR_RGB2BGR))
