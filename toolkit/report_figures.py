"""The report's figures (matplotlib, Agg, no pyplot state): top views, matches, error map, histograms.

Each function takes what exists and returns a matplotlib Figure, or None when its inputs are
missing. Coordinates are shown relative to a local origin (metres), never as raw UTM numbers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from matplotlib.colors import ListedColormap, to_rgba_array
from matplotlib.figure import Figure

MAX_PLOT_POINTS = 40_000  # a 750×660 px panel shows no more; drawing scales with it
SEGMENT_COLOURS = np.array([
    [31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75],
    [227, 119, 194], [188, 189, 34], [23, 190, 207], [174, 199, 232], [255, 187, 120], [152, 223, 138],
    [255, 152, 150], [197, 176, 213], [196, 156, 148], [247, 182, 210], [219, 219, 141], [158, 218, 229],
]) / 255.0
GREY = np.array([0.80, 0.80, 0.80])
OK, BAD, UNKNOWN = "#2ca02c", "#d62728", "#1f77b4"


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


def marker_size(n: int) -> float:
    """Dot area (pt²) so that sparse clouds stay visible and dense ones do not blot."""
    return float(np.clip(4e4 / max(n, 1), 0.3, 6.0))


def segment_colours(labels: np.ndarray) -> np.ndarray:
    labels = np.asarray(labels)
    out = np.tile(GREY, (len(labels), 1))
    seg = labels >= 0
    out[seg] = SEGMENT_COLOURS[labels[seg] % len(SEGMENT_COLOURS)]
    return out


def scatter_by_colour(ax, xy: np.ndarray, colour_index: np.ndarray, palette: np.ndarray, s: float,
                      zorder: int) -> None:
    """``palette[colour_index]``-coloured dots as one scatter per colour, in palette order.

    A single-colour scatter is drawn by blitting one rendered marker (Agg ``draw_markers``); a
    many-coloured one rasterises every dot on its own, several times slower.
    """
    order = np.argsort(colour_index, kind="stable")
    present, starts = np.unique(colour_index[order], return_index=True)
    for k, rows in zip(present, np.split(order, starts[1:])):
        ax.scatter(xy[rows, 0], xy[rows, 1], s=s, c=palette[k:k + 1], linewidths=0, zorder=zorder)


def scatter_segments(ax, xy: np.ndarray, labels: np.ndarray, zorder: int = 2) -> None:
    """Ground/clutter as small light dots, façade segments larger and coloured on top."""
    seg = labels >= 0
    size = marker_size(len(xy))
    ax.scatter(xy[~seg, 0], xy[~seg, 1], s=size, c=[GREY], linewidths=0, zorder=zorder)
    scatter_by_colour(ax, xy[seg], labels[seg] % len(SEGMENT_COLOURS), SEGMENT_COLOURS, min(3 * size, 8.0),
                      zorder + 1)


def _overview_image(ax, overview, frame: Frame, alpha: float = 1.0) -> None:
    """Over-view segments as a light raster under everything else."""
    lab = overview.label_image
    step = max(1, int(np.ceil(max(lab.shape) / 1500)))
    lab = lab[::step, ::step]
    a, _, c, _, e, f = overview.grid.transform
    H, W = overview.label_image.shape
    extent = (c - frame.x0, c + a * W - frame.x0, f + e * H - frame.y0, f - frame.y0)
    img = np.where(lab >= 0, 1, 0)
    ax.imshow(img, extent=extent, origin="upper", cmap=ListedColormap(["#f4f4f4", "#b9c7d9"]),
              vmin=0, vmax=1, interpolation="nearest", alpha=alpha, zorder=0)


def _limits(ax, xy: np.ndarray, margin_m: float = 15.0) -> None:
    if len(xy):
        lo, hi = np.percentile(xy, 0.5, axis=0) - margin_m, np.percentile(xy, 99.5, axis=0) + margin_m
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")


def top_views(street_points, street, registration, overview, frame: Frame) -> Figure | None:
    """Before (levelled street frame) and after (scene CRS over the over-view segments)."""
    if street_points is None and registration is None:
        return None
    fig = Figure(figsize=(13, 6.2), dpi=100)
    axes = fig.subplots(1, 2)
    labels = street.point_labels if street is not None else None
    if street_points is not None:
        idx = plot_indices(len(street_points))
        pts = street.level(street_points[idx]) if street is not None else np.asarray(street_points)[idx]
        lab = labels[idx] if labels is not None else np.full(len(idx), -1)
        xy = pts[:, :2] - np.median(pts[:, :2], axis=0)
        scatter_segments(axes[0], xy, lab)
        _limits(axes[0], xy, 5)
        frame_name = "levelled street frame" if street is not None else "input street frame"
        axes[0].set_title(f"before: street cloud ({frame_name})")
    else:
        axes[0].text(0.5, 0.5, "no street cloud", ha="center", va="center", transform=axes[0].transAxes)
    if registration is not None:
        idx = plot_indices(len(registration.points))
        xy = frame.xy(registration.points[idx])
        lab = labels[idx] if labels is not None else registration.point_segment[idx]
        if overview is not None:
            _overview_image(axes[1], overview, frame)
        scatter_segments(axes[1], xy, lab)
        _limits(axes[1], xy)
        axes[1].set_title("after: registered cloud on the over-view segments (blue)")
    else:
        axes[1].text(0.5, 0.5, "no registration (the recipe stops before warp)", ha="center", va="center",
                     transform=axes[1].transAxes)
    fig.tight_layout()
    return fig


def matches_view(street, overview, matches, registration, segment_rows: list[dict], frame: Frame) -> Figure | None:
    """Each matched street segment (registered façade points) linked to its over-view segment."""
    if matches is None or street is None or overview is None or registration is None:
        return None
    fig = Figure(figsize=(7.5, 6.6), dpi=100)
    ax = fig.subplots()
    _overview_image(ax, overview, frame)
    S = len(street)
    # Only façade points count: gather them once (not every point's local xy, most are ground).
    seg_rows = np.flatnonzero(street.point_labels >= 0)
    seg_labels = street.point_labels[seg_rows]
    xy_seg = frame.xy(registration.points[seg_rows, :2])
    cx = np.bincount(seg_labels, weights=xy_seg[:, 0], minlength=S)[:S]
    cy = np.bincount(seg_labels, weights=xy_seg[:, 1], minlength=S)[:S]
    cnt = np.maximum(np.bincount(seg_labels, minlength=S)[:S], 1)
    centres = np.column_stack([cx / cnt, cy / cnt])
    ov_c = overview.centroids - [frame.x0, frame.y0]
    status = []
    for s in range(S):
        m = int(matches.segment_match[s])
        correct = segment_rows[s].get("correct") if s < len(segment_rows) else None
        colour = "#999999" if m < 0 else (UNKNOWN if correct is None else (OK if correct else BAD))
        status.append(colour)
        if m >= 0:
            ax.plot([centres[s, 0], ov_c[m, 0]], [centres[s, 1], ov_c[m, 1]], color=colour, lw=1.6, zorder=3)
    idx = plot_indices(len(seg_rows))
    kinds = ["#999999", UNKNOWN, OK, BAD]  # the colours of `status`, one scatter each
    seg_kind = np.array([kinds.index(c) for c in status], np.int64)
    scatter_by_colour(ax, xy_seg[idx], seg_kind[seg_labels[idx]], to_rgba_array(kinds), marker_size(len(idx)), 2)
    ax.scatter(ov_c[:, 0], ov_c[:, 1], s=10, c="k", marker="+", zorder=4, label="over-view centroid")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], color=OK, lw=2, label="correct match"),
               Line2D([], [], color=BAD, lw=2, label="wrong match"),
               Line2D([], [], color=UNKNOWN, lw=2, label="match (no truth)"),
               Line2D([], [], color="#999999", marker="o", lw=0, label="unmatched")]
    used = set(status)
    ax.legend(handles=[h for h in handles if h.get_color() in used], loc="upper right", fontsize=8)
    _limits(ax, xy_seg[idx] if len(idx) else frame.xy(registration.points))
    ax.set_title(f"matches: {int((matches.segment_match >= 0).sum())} of {S} street segments matched")
    fig.tight_layout()
    return fig


def error_map(registration, per_point_error, overview, frame: Frame) -> Figure | None:
    if registration is None or per_point_error is None:
        return None
    fig = Figure(figsize=(7.5, 6.6), dpi=100)
    ax = fig.subplots()
    if overview is not None:
        _overview_image(ax, overview, frame, alpha=0.6)
    idx = plot_indices(len(registration.points))
    xy = frame.xy(registration.points[idx])
    err = per_point_error[idx]
    vmax = max(float(np.percentile(per_point_error, 95)), 0.5)
    order = np.argsort(err)  # large errors drawn last
    sc = ax.scatter(xy[order, 0], xy[order, 1], s=marker_size(len(xy)), c=err[order], cmap="inferno_r", vmin=0, vmax=vmax,
                    linewidths=0, zorder=2)
    fig.colorbar(sc, ax=ax, shrink=0.8, label="3D error vs truth (m)")
    _limits(ax, xy)
    ax.set_title("per-point error (registered vs true position)")
    fig.tight_layout()
    return fig


def error_histograms(values: dict[str, Any]) -> Figure | None:
    """Like the paper's Fig. 8: distribution of Chamfer pair distances (and truth errors)."""
    chamfer = values.get("chamfer") or {}
    truth = values.get("truth") or {}
    panels = [(f"Chamfer pairs, {k.upper()} (paper metric)", chamfer[k]) for k in ("3d", "2d") if chamfer.get(k)]
    if truth.get("histogram"):
        panels.append(("per-point error vs truth, 3D", truth))
    if not panels:
        return None
    fig = Figure(figsize=(4.6 * len(panels), 3.8), dpi=100)
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (title, d) in zip(axes, panels):
        h = d["histogram"]
        counts = np.asarray(h["counts"], float)
        edges = [e for e in h["edges_m"] if e is not None]
        last = edges[-1] + (edges[-1] - edges[-2] if len(edges) > 1 else 1.0)
        edges = np.asarray(edges + ([last] if len(edges) == len(counts) else []), float)
        total = counts.sum()
        frac = counts / total if total else counts
        # one artist for all bins (a bar chart draws one patch per bin, ~10x slower to render)
        ax.stairs(frac * 100, edges, fill=True, color="#4c72b0")
        mean = d.get("mean_m", (d.get("error_3d") or {}).get("mean_m"))
        std = d.get("std_m")
        if mean is not None:
            ax.axvline(mean, color="#c44e52", lw=1.2)
            label = f"mean {mean:.2f} m" + (f" ± {std:.2f}" if std is not None else "")
            ax.text(0.97, 0.93, label, transform=ax.transAxes, ha="right", va="top", fontsize=9)
        if h["edges_m"][-1] is None and counts[-1] > 0:
            ax.text(0.97, 0.83, f"{frac[-1]:.1%} beyond {edges[-2]:.0f} m (last bin)", transform=ax.transAxes, ha="right",
                    va="top", fontsize=8, color="#555")
        # show up to the bin holding the 99.5th percentile (an overflow bin is always shown)
        cum = np.cumsum(counts) / total if total else np.ones(len(counts))
        k = int(np.searchsorted(cum, 0.995)) if total else len(counts) - 1
        if h["edges_m"][-1] is None and counts[-1] > 0:
            k = len(counts) - 1
        ax.set_xlim(0, max(1.0, float(edges[min(k + 1, len(edges) - 1)]) * 1.05))
        ax.set_xlabel("distance (m)")
        ax.set_ylabel("% of pairs" if "Chamfer" in title else "% of points")
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig
