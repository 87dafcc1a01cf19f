"""Points drawn into a panel's pixel grid with numpy: one image instead of a scatter of many dots.

A panel of W×H pixels shows (xmin..xmax, ymin..ymax) metres; pixel (row, col) covers
x in [xmin + col·sx, xmin + (col+1)·sx) and y in (ymax − (row+1)·sy, ymax − row·sy].
Where several points fall in one pixel the one drawn on top wins, as in a scatter plot: the
highest priority (or the largest value).
"""

from __future__ import annotations

import numpy as np

from toolkit.report_canvas import Panel

# matplotlib's "inferno" at 17 evenly spaced stops (0..255 RGB); linear in between is within 7/255
INFERNO_STOPS = np.array([
    [0, 0, 4], [11, 7, 36], [33, 12, 74], [61, 9, 101], [87, 16, 110], [113, 25, 110], [138, 34, 106],
    [163, 44, 97], [188, 55, 84], [210, 70, 68], [228, 90, 49], [241, 115, 29], [249, 142, 9],
    [252, 172, 17], [249, 203, 53], [242, 234, 105], [252, 255, 164],
], np.float64)


def inferno_r_lut() -> np.ndarray:
    """(256, 3) uint8: reversed inferno (0 → pale yellow, 255 → black)."""
    t = np.linspace(0.0, 1.0, len(INFERNO_STOPS))
    levels = np.linspace(0.0, 1.0, 256)
    lut = np.column_stack([np.interp(levels, t, INFERNO_STOPS[:, k]) for k in range(3)])
    return lut[::-1].round().astype(np.uint8)


def pixel_index(panel: Panel, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Flat pixel index (row·W + col) of the points inside the panel, and which points those are."""
    (x0, x1), (y0, y1) = panel.xlim, panel.ylim
    col = np.floor((xy[:, 0] - x0) * (panel.width / (x1 - x0)))
    row = np.floor((y1 - xy[:, 1]) * (panel.height / (y1 - y0)))
    inside = (col >= 0) & (col < panel.width) & (row >= 0) & (row < panel.height)
    flat = row[inside].astype(np.int64) * panel.width + col[inside].astype(np.int64)
    return flat, inside


def topmost(panel: Panel, xy: np.ndarray, priority: np.ndarray) -> np.ndarray:
    """(H, W) int64: the largest ``priority`` (≥ 0) of the points in each pixel, −1 where none."""
    flat, inside = pixel_index(panel, xy)
    out = np.full(panel.width * panel.height, -1, np.int64)
    np.maximum.at(out, flat, np.asarray(priority, np.int64)[inside])
    return out.reshape(panel.height, panel.width)


def largest_value(panel: Panel, xy: np.ndarray, values: np.ndarray) -> np.ndarray:
    """(H, W) float64: the largest value of the points in each pixel, NaN where none."""
    flat, inside = pixel_index(panel, xy)
    out = np.full(panel.width * panel.height, -np.inf)
    np.maximum.at(out, flat, np.asarray(values, np.float64)[inside])
    out[np.isneginf(out)] = np.nan
    return out.reshape(panel.height, panel.width)


def dilate_max(image: np.ndarray, size_px: int) -> np.ndarray:
    """Each pixel takes the largest value of the size×size block to its lower right (a square dot)."""
    out = image.copy()
    for dr in range(size_px):
        for dc in range(size_px):
            if dr or dc:
                np.maximum(out[dr:, dc:], image[:image.shape[0] - dr, :image.shape[1] - dc], out=out[dr:, dc:])
    return out


def overview_mask(panel: Panel, overview, frame_x0: float, frame_y0: float) -> np.ndarray:
    """(H, W) int8: 1 on an over-view segment, 0 on its background, −1 outside its raster."""
    a, _, c, _, e, f = overview.grid.transform
    lab = overview.label_image
    (x0, x1), (y0, y1) = panel.xlim, panel.ylim
    # pixel centres in scene coordinates → the over-view pixel holding each
    xs = frame_x0 + x0 + (np.arange(panel.width) + 0.5) * ((x1 - x0) / panel.width)
    ys = frame_y0 + y1 - (np.arange(panel.height) + 0.5) * ((y1 - y0) / panel.height)
    cols = np.floor((xs - c) / a).astype(np.int64)
    rows = np.floor((ys - f) / e).astype(np.int64)
    col_ok = (cols >= 0) & (cols < lab.shape[1])
    row_ok = (rows >= 0) & (rows < lab.shape[0])
    hit = lab[np.clip(rows, 0, lab.shape[0] - 1)[:, None], np.clip(cols, 0, lab.shape[1] - 1)[None, :]] >= 0
    out = hit.astype(np.int8)
    out[~(row_ok[:, None] & col_ok[None, :])] = -1
    return out

