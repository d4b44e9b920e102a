"""Figures of a run as PNG: the loss plot and contact sheets of images.

matplotlib is imported only inside the plotting functions (its Agg canvas, no pyplot state).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from jaxdistill.export.pages import to_uint8
from jaxdistill.io import images as imageio


def _smooth(values: np.ndarray) -> np.ndarray:
    """Centred moving average over ~4 % of the points (window shrinks at the ends)."""
    half = max(1, len(values) // 50)
    sums = np.concatenate([[0.0], np.cumsum(values)])
    idx = np.arange(len(values))
    lo, hi = np.maximum(idx - half, 0), np.minimum(idx + half + 1, len(values))
    return (sums[hi] - sums[lo]) / (hi - lo)


def _series(name: str, steps, values) -> tuple[np.ndarray, np.ndarray]:
    steps, values = np.asarray(steps, np.float64).reshape(-1), np.asarray(values, np.float64).reshape(-1)
    if len(steps) != len(values):
        raise ValueError(f"{name}: {len(steps)} steps but {len(values)} values")
    keep = np.isfinite(steps) & np.isfinite(values)
    return steps[keep], values[keep]


def write_loss_plot(path, steps, values, *, extra: Mapping[str, tuple] | None = None,
                    title: str | None = None) -> Path:
    """Writes a PNG line plot of loss vs step; returns the path.

    The raw curve is drawn faint with a lightly smoothed one over it (smoothing in log space
    when the y axis is logarithmic, which it is when every value is > 0). `extra` maps a name
    to (steps, values) drawn on a second y axis (e.g. albedo PSNR in dB). Non-finite points
    are dropped. Uses matplotlib's Agg canvas directly (no pyplot state).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    steps, values = _series("loss", steps, values)
    if len(values) == 0:
        raise ValueError("loss: no finite (step, value) points to plot")
    fig = Figure(figsize=(8, 4.5), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    log_y = bool(np.all(values > 0))
    smooth = np.exp(_smooth(np.log(values))) if log_y else _smooth(values)
    ax.plot(steps, values, color="tab:blue", alpha=0.3, linewidth=0.8, label="loss")
    ax.plot(steps, smooth, color="tab:blue", linewidth=1.8, label="loss (smoothed)",
            marker="o" if len(values) == 1 else None)
    if log_y:
        ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("loss")
    ax.grid(True, which="major", alpha=0.3)
    handles, labels = ax.get_legend_handles_labels()
    if extra:
        ax2 = ax.twinx()
        colours = ["tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown"]
        for i, (name, (x, y)) in enumerate(extra.items()):
            x, y = _series(name, x, y)
            ax2.plot(x, y, color=colours[i % len(colours)], linewidth=1.5, label=name,
                     marker="o" if len(y) < 20 else None, markersize=3)
        ax2.set_ylabel(", ".join(extra))
        h2, l2 = ax2.get_legend_handles_labels()
        handles, labels = handles + h2, labels + l2
    ax.legend(handles, labels, loc="best", fontsize="small", framealpha=0.8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(os.fspath(path), format="png")
    return path


def _cell_image(image, where: str) -> np.ndarray:
    image = np.asarray(image, np.float32)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    if image.ndim != 3 or image.shape[2] not in (3, 4) or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"{where}: expected an (H, W, 3) image, got shape {image.shape}")
    return np.clip(np.nan_to_num(image[:, :, :3]), 0.0, 1.0)


CHAR_PX = 7  # approximate width of one character of the sheet's 11 px font


def write_contact_sheet(path, rows: Sequence[Sequence], column_names: Sequence[str],
                        row_names: Sequence[str] | None = None, *, gap: int = 4, title_px: int = 20,
                        label_px: int | None = None) -> Path:
    """Writes a PNG grid of images with column titles and row names; returns the path.

    rows: one list per row (view) of (H, W, 3) float images in DISPLAY space [0, 1] (the
    caller encodes; grey (H, W) images are accepted), None for a missing cell (drawn grey).
    Images are drawn 1:1 at the top left of their cell; a column is as wide as its widest
    image, a row as tall as its tallest. Layout in pixels, with a white background:

        width  = label + sum(column widths) + gap * (columns + 1)
        height = title + sum(row heights)   + gap * (rows + 1)

    title = `title_px`; label = `label_px`, or (without it) enough for the longest row name,
    or 0 without row names.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    n_cols = len(column_names)
    if not rows or n_cols == 0:
        raise ValueError("contact sheet: needs at least one row and one column")
    if row_names is not None and len(row_names) != len(rows):
        raise ValueError(f"contact sheet: {len(row_names)} row names for {len(rows)} rows")
    cells = []
    for r, row in enumerate(rows):
        if len(row) != n_cols:
            raise ValueError(f"contact sheet row {r}: {len(row)} images for {n_cols} columns")
        cells.append([None if img is None else _cell_image(img, f"contact sheet row {r} column {c}")
                      for c, img in enumerate(row)])
    sizes = [img.shape[:2] for row in cells for img in row if img is not None]
    default = (int(np.median([s[0] for s in sizes])), int(np.median([s[1] for s in sizes]))) if sizes else (64, 64)
    heights = [max((img.shape[0] for img in row if img is not None), default=default[0]) for row in cells]
    widths = [max((row[c].shape[1] for row in cells if row[c] is not None), default=default[1])
              for c in range(n_cols)]
    if label_px is None:
        label_px = 0 if row_names is None else 2 * gap + CHAR_PX * max(len(str(n)) for n in row_names)
    x0 = label_px + gap + np.concatenate([[0], np.cumsum(np.asarray(widths) + gap)])
    y0 = title_px + gap + np.concatenate([[0], np.cumsum(np.asarray(heights) + gap)])
    width, height = int(x0[-1]), int(y0[-1])
    sheet = np.ones((height, width, 3), np.float32)
    for r, row in enumerate(cells):
        for c, img in enumerate(row):
            if img is None:
                sheet[y0[r]:y0[r] + heights[r], x0[c]:x0[c] + widths[c]] = 0.5
            else:
                sheet[y0[r]:y0[r] + img.shape[0], x0[c]:x0[c] + img.shape[1]] = img

    dpi = 72  # 1 pt = 1 px
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi)
    canvas = FigureCanvasAgg(fig)
    fig.figimage(to_uint8(sheet), xo=0, yo=0, origin="upper", resize=False)  # uint8: no requantising

    def fit(text, px):
        text = str(text)
        most = max(1, px // CHAR_PX)
        return text if len(text) <= most else text[:max(1, most - 1)] + "…"

    for c, name in enumerate(column_names):
        fig.text((x0[c] + widths[c] / 2) / width, 1.0 - (title_px / 2 + gap / 2) / height, fit(name, widths[c]),
                 ha="center", va="center", fontsize=11)
    if row_names is not None and label_px > 0:
        for r, name in enumerate(row_names):
            fig.text(gap / width, 1.0 - (y0[r] + heights[r] / 2) / height, fit(name, label_px - gap),
                     ha="left", va="center", fontsize=11)
    canvas.draw()
    pixels = np.asarray(canvas.buffer_rgba())[:, :, :3].astype(np.float32) / 255.0
    if pixels.shape[:2] != (height, width):  # figure size rounding: keep the arithmetic exact
        padded = np.ones((height, width, 3), np.float32)
        h, w = min(height, pixels.shape[0]), min(width, pixels.shape[1])
        padded[:h, :w] = pixels[:h, :w]
        pixels = padded
    path = Path(path)
    imageio.write_image(path, pixels, encode_srgb=False)
    return path
