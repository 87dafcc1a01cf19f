"""The report's figures (PIL images): top views, matches, error map, histograms.

Each function takes what exists and returns a PIL image, or None when its inputs are missing.
Coordinates are shown relative to a local origin (metres), never as raw UTM numbers. Point clouds
are drawn as rasters of the panel's own pixels (``toolkit.point_raster``), frames and labels by
``toolkit.report_canvas``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image, ImageDraw

from toolkit.point_raster import dilate_max, inferno_r_lut, largest_value, overview_mask, topmost
from toolkit.report_canvas import SMALL_PX, Canvas, Panel, fit_equal, rgb

if TYPE_CHECKING:
    from toolkit.metrics_model import Histogram, RunMetrics, SegmentRow

MAX_PLOT_POINTS = 80_000  # 1 px dots at about the density of the former 40k matplotlib dots (~1.5 px wide)
SEGMENT_COLOURS = np.array([
    [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75],
    [227, 119, 194], [188, 189, 34], [23, 190, 207], [174, 199, 232], [255, 187, 120], [152, 223, 138],
    [255, 152, 150], [197, 176, 213], [196, 156, 148], [247, 182, 210], [219, 219, 141], [158, 218, 229],
], np.uint8)
GREY = np.array([204, 204, 204], np.uint8)
OK, BAD, UNKNOWN, UNMATCHED = "#2ca02c", "#d62728", "#1f77b4", "#999999"
OVERVIEW_COLOURS = np.array([[244, 244, 244], [185, 199, 217]], np.float64)  # background, segment
FACADE_DOT_PX = 2  # façade points drawn as 2×2 px dots over 1 px ground points
MAP_MARGINS_PX = (80, 34, 14, 50)  # left, top, right, bottom: tick labels, axis labels, title


@dataclass(frozen=True)
class Frame:
    """A local origin for plots (x0, y0) in scene or street coordinates."""

    x0: float
    y0: float

    def xy(self, pts: np.ndarray) -> np.ndarray:
        return np.asarray(pts, np.float64)[:, :2] - [self.x0, self.y0]


def plot_indices(n: int, max_points: int = MAX_PLOT_POINTS) -> np.ndarray:
    """Evenly spread deterministic subsample of range(n)."""
    return np.arange(n) if n <= max_points else np.linspace(0, n - 1, max_points).astype(np.int64)


def map_panel(box_px: tuple[int, int, int, int], xy: np.ndarray, margin_m: float = 15.0) -> Panel:
    """An equal-aspect panel inside ``box_px`` (left, top, width, height) showing the bulk of ``xy``."""
    if len(xy):
        lo, hi = np.percentile(xy, [0.5, 99.5], axis=0) + [[-margin_m], [margin_m]]
    else:
        lo, hi = np.zeros(2), np.ones(2)
    left, top, width, height = box_px
    ml, mt, mr, mb = MAP_MARGINS_PX
    return fit_equal(left + ml, top + mt, width - ml - mr, height - mt - mb, (lo[0], hi[0]), (lo[1], hi[1]))


def base_layer(panel: Panel, overview, frame: Frame, alpha: float = 1.0) -> np.ndarray:
    """(H, W, 3) uint8: white, with the over-view segments as a light raster when there is one."""
    if overview is None:
        return np.full((panel.height, panel.width, 3), 255, np.uint8)
    mask = overview_mask(panel, overview, frame.x0, frame.y0)  # −1 outside, 0 background, 1 segment
    colours = np.vstack([[255.0, 255.0, 255.0], alpha * OVERVIEW_COLOURS + (1 - alpha) * 255.0])
    return colours.round().astype(np.uint8)[mask + 1]


def levelled_xy(street, points: np.ndarray) -> np.ndarray:
    """x, y of ``street.level(points)``, by elementwise products: a (N,3)@(3,3) BLAS call can cost
    ~50 ms of CPU in spinning threads for 2·10^5 points."""
    centred = np.asarray(points, np.float64) - street.origin
    R = street.up_rotation
    return np.column_stack([centred[:, 0] * R[i, 0] + centred[:, 1] * R[i, 1] + centred[:, 2] * R[i, 2]
                            for i in (0, 1)])


def paint_segments(picture: np.ndarray, panel: Panel, xy: np.ndarray, labels: np.ndarray) -> None:
    """Ground/clutter (label < 0) as grey 1 px dots, façade segments as larger coloured dots on top."""
    seg = labels >= 0
    # priority: ground 0 under façade colours 1.., a higher palette index on top (the scatter's order)
    priority = np.where(seg, 1 + np.where(seg, labels, 0) % len(SEGMENT_COLOURS), 0)
    top = topmost(panel, xy, priority)
    facade = dilate_max(np.where(top >= 1, top, -1), FACADE_DOT_PX)
    top = np.where(facade >= 1, facade, top)
    table = np.vstack([GREY, SEGMENT_COLOURS])
    drawn = top >= 0
    picture[drawn] = table[top[drawn]]


def top_views(street_points, street, registration, overview, frame: Frame) -> Image.Image | None:
    """Before (levelled street frame) and after (scene CRS over the over-view segments)."""
    if street_points is None and registration is None:
        return None
    canvas = Canvas(1300, 620)
    labels = street.point_labels if street is not None else None
    if street_points is not None:
        idx = plot_indices(len(street_points))
        pts = np.asarray(street_points)[idx]
        xy = levelled_xy(street, pts) if street is not None else pts[:, :2]
        lab = labels[idx] if labels is not None else np.full(len(idx), -1)
        xy -= np.median(xy, axis=0)
        panel = map_panel((0, 0, 650, 620), xy, 5.0)
        picture = base_layer(panel, None, frame)
        paint_segments(picture, panel, xy, lab)
        canvas.raster(panel, picture)
        frame_name = "levelled street frame" if street is not None else "input street frame"
        canvas.axes(panel, f"before: street cloud ({frame_name})", "x (m)", "y (m)")
    else:
        canvas.text((325, 310), "no street cloud", anchor="mm")
    if registration is not None:
        idx = plot_indices(len(registration.points))
        xy = frame.xy(registration.points[idx])
        lab = labels[idx] if labels is not None else registration.point_segment[idx]
        panel = map_panel((650, 0, 650, 620), xy)
        picture = base_layer(panel, overview, frame)
        paint_segments(picture, panel, xy, lab)
        canvas.raster(panel, picture)
        canvas.axes(panel, "after: registered cloud on the over-view segments (blue)", "x (m)", "y (m)")
    else:
        canvas.text((975, 310), "no registration (the recipe stops before warp)", anchor="mm")
    return canvas.image


def _plus_markers(draw: ImageDraw.ImageDraw, cols: np.ndarray, rows: np.ndarray, arm_px: int = 2) -> None:
    for c, r in zip(np.round(cols), np.round(rows)):
        draw.line((c - arm_px, r, c + arm_px, r), fill=(0, 0, 0))
        draw.line((c, r - arm_px, c, r + arm_px), fill=(0, 0, 0))


def matches_view(street, overview, matches, registration, segment_rows: list[SegmentRow],
                 frame: Frame) -> Image.Image | None:
    """Each matched street segment (registered façade points) linked to its over-view segment."""
    if matches is None or street is None or overview is None or registration is None:
        return None
    S = len(street)
    # Only façade points count: centres from all of them (one column gathered at a time is ~1.4x
    # faster than whole rows), an even subsample of them drawn.
    seg_rows = np.flatnonzero(street.point_labels >= 0)
    seg_labels = street.point_labels[seg_rows]
    cnt = np.maximum(np.bincount(seg_labels, minlength=S)[:S], 1)
    centres = np.column_stack([np.bincount(seg_labels, weights=registration.points[seg_rows, k], minlength=S)[:S] / cnt
                               for k in (0, 1)]) - [frame.x0, frame.y0]
    seg_rows = seg_rows[plot_indices(len(seg_rows))]
    seg_labels = street.point_labels[seg_rows]
    xy_seg = frame.xy(registration.points[seg_rows])
    ov_c = overview.centroids - [frame.x0, frame.y0]
    kinds = [UNMATCHED, UNKNOWN, OK, BAD]  # drawn in this order: a wrong match on top
    seg_kind = np.zeros(S, np.int64)
    for s in range(S):
        correct = segment_rows[s].correct if s < len(segment_rows) else None
        if matches.segment_match[s] >= 0:
            seg_kind[s] = 1 if correct is None else (2 if correct else 3)
    panel = map_panel((0, 0, 750, 660), xy_seg if len(xy_seg) else frame.xy(registration.points))
    picture = base_layer(panel, overview, frame)
    top = dilate_max(topmost(panel, xy_seg, seg_kind[seg_labels]), FACADE_DOT_PX)
    drawn = top >= 0
    picture[drawn] = np.array([rgb(k) for k in kinds], np.uint8)[top[drawn]]
    layer = Image.fromarray(picture, "RGB")
    draw = ImageDraw.Draw(layer)
    matched = np.flatnonzero(matches.segment_match >= 0)
    a_col, a_row = panel.to_local_px(centres[matched, 0], centres[matched, 1])
    b_col, b_row = panel.to_local_px(ov_c[matches.segment_match[matched], 0], ov_c[matches.segment_match[matched], 1])
    for k in (1, 2, 3):
        for i in np.flatnonzero(seg_kind[matched] == k):
            draw.line((a_col[i], a_row[i], b_col[i], b_row[i]), fill=rgb(kinds[k]), width=2)
    _plus_markers(draw, *panel.to_local_px(ov_c[:, 0], ov_c[:, 1]))
    canvas = Canvas(750, 660)
    canvas.raster(panel, layer)
    used = set(seg_kind.tolist())
    legend = [("line", OK, "correct match", 2), ("line", BAD, "wrong match", 3), ("line", UNKNOWN, "match (no truth)", 1),
              ("dot", UNMATCHED, "unmatched", 0)]
    canvas.legend(panel, [(kind, colour, label) for kind, colour, label, k in legend if k in used])
    canvas.axes(panel, f"matches: {int((matches.segment_match >= 0).sum())} of {S} street segments matched",
                "x (m)", "y (m)")
    return canvas.image


def error_map(registration, per_point_error, overview, frame: Frame) -> Image.Image | None:
    if registration is None or per_point_error is None:
        return None
    idx = plot_indices(len(registration.points))
    xy = frame.xy(registration.points[idx])
    panel = map_panel((0, 0, 640, 660), xy)
    picture = base_layer(panel, overview, frame, alpha=0.6)
    vmax = max(float(np.percentile(per_point_error, 95)), 0.5)
    vmax = vmax if np.isfinite(vmax) else 0.5
    largest = largest_value(panel, xy, per_point_error[idx])  # large errors on top
    drawn = np.isfinite(largest)
    lut = inferno_r_lut()
    picture[drawn] = lut[np.clip(largest[drawn] / vmax * 256, 0, 255).astype(np.int64)]
    canvas = Canvas(750, 660)
    canvas.raster(panel, picture)
    canvas.axes(panel, "per-point error (registered vs true position)", "x (m)", "y (m)")
    bar_height = int(0.8 * panel.height)
    canvas.colour_bar(panel.right + 30, panel.top + (panel.height - bar_height) // 2, 20, bar_height, lut, vmax,
                      "3D error vs truth (m)")
    return canvas.image


def _histogram_panel(canvas: Canvas, box_px: tuple[int, int, int, int], title: str, h: Histogram,
                     mean: float | None, std: float | None) -> None:
    counts = np.asarray(h.counts, float)
    edges = [e for e in h.edges_m if e is not None]
    last = edges[-1] + (edges[-1] - edges[-2] if len(edges) > 1 else 1.0)
    edges = np.asarray(edges + ([last] if len(edges) == len(counts) else []), float)
    total = counts.sum()
    frac = counts / total if total else counts
    overflow = h.edges_m[-1] is None and counts[-1] > 0
    # show up to the bin holding the 99.5th percentile (an overflow bin is always shown)
    cum = np.cumsum(counts) / total if total else np.ones(len(counts))
    k = len(counts) - 1 if overflow or not total else int(np.searchsorted(cum, 0.995))
    xmax = max(1.0, float(edges[min(k + 1, len(edges) - 1)]) * 1.05)
    ymax = max(float(frac.max()) * 100 * 1.05, 1e-9) if len(frac) else 1.0
    left, top, width, height = box_px
    panel = Panel(left + 66, top + 30, width - 66 - 16, height - 30 - 52, (0.0, xmax), (0.0, ymax))
    layer = Image.new("RGB", (panel.width, panel.height), "white")
    draw = ImageDraw.Draw(layer)
    cols, _ = panel.to_local_px(edges, 0.0)
    _, rows = panel.to_local_px(0.0, frac * 100)
    for i in np.flatnonzero(frac > 0):
        draw.rectangle((cols[i], rows[i], cols[i + 1], panel.height), fill=rgb("#4c72b0"))
    if mean is not None:
        col = float(panel.to_local_px(mean, 0.0)[0])
        draw.line((col, 0, col, panel.height), fill=rgb("#c44e52"), width=2)
    canvas.raster(panel, layer)
    if mean is not None:
        label = f"mean {mean:.2f} m" + (f" ± {std:.2f}" if std is not None else "")
        canvas.text((panel.right - 0.03 * panel.width, panel.top + 0.07 * panel.height), label, size_px=13, anchor="ra")
    if overflow:
        canvas.text((panel.right - 0.03 * panel.width, panel.top + 0.17 * panel.height),
                    f"{frac[-1]:.1%} beyond {edges[-2]:.0f} m (last bin)", size_px=SMALL_PX, anchor="ra", fill="#555555")
    canvas.axes(panel, title, "distance (m)", "% of pairs" if "Chamfer" in title else "% of points", title_px=14)


def error_histograms(metrics: RunMetrics) -> Image.Image | None:
    """Like the paper's Fig. 8: distribution of Chamfer pair distances (and truth errors)."""
    panels = []  # (title, histogram, mean, std)
    if metrics.chamfer is not None:
        for dims, stats in (("3D", metrics.chamfer.d3), ("2D", metrics.chamfer.d2)):
            if stats is not None and stats.histogram is not None:
                panels.append((f"Chamfer pairs, {dims} (paper metric)", stats.histogram, stats.mean_m, stats.std_m))
    truth = metrics.truth
    if truth is not None and truth.histogram is not None:
        mean = truth.error_3d.mean_m if truth.error_3d is not None else None
        panels.append(("per-point error vs truth, 3D", truth.histogram, mean, None))
    if not panels:
        return None
    canvas = Canvas(460 * len(panels), 380)
    for i, (title, histogram, mean, std) in enumerate(panels):
        _histogram_panel(canvas, (460 * i, 0, 460, 380), title, histogram, mean, std)
    return canvas.image
