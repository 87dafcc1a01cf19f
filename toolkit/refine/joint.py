"""Joint 2D registration of the segments captured close together along the route.

The over-view outline of one building carries that building's own error: an OSM footprint is
shifted by its own digitising offset (synthetic campus: 0.7 m sigma per axis), a label-map edge is
eroded or dilated per building, and a single straight wall cannot fix the position along itself.
A segment registered on its own inherits all of it: on campus, the error of a segment's own
transform at its centre had a median of 0.7–1.1 m with OSM or a label map (0.25–0.5 m with the
DSM), and its rotation 0.5–1.5° (median).

The drift of a monocular street frame is smooth along the route (heading, pitch, roll random walks,
slow scale drift), so the segments captured within a short stretch of the route share nearly the
same transform. Here each segment's 2D transform is re-estimated by registering, as one rigid body,
the footprints of every valid segment captured within ``window_m`` of it along the route (and
within ``2·window_m`` in space, so another pass of the route never joins), seeded by the segment's
own transform and searched against every over-view outline around them: independent per-building
outline errors average out, corners of other buildings fix the position along straight walls and
the longer lever fixes the rotation. A window may hold a single straight wall (at the ends of the
route, or where the neighbours were rejected), whose cost is flat along itself: ``shift_penalty``
(off by default) keeps it at the segment's own position, but also damps the window's corrections
elsewhere.
The window must stay short, because the true transform does change along the route (campus
seed 1: the true transform of a segment applied to another one 25–50 m along the route away is
0.23 m off at the median, 50–100 m away 0.53 m, 100–200 m away 1.1 m).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal

import numpy as np
from pydantic import Field

from toolkit.forked import map_chunks_forked
from toolkit.params import ParamGroup
from toolkit.refine.columns import column_means
from toolkit.refine.route import route_neighbours, tricube
from toolkit.refine.search2d import AllOutlines, SearchParams, search_segments
from toolkit.refine.segments import thin_xy
from toolkit.types import Grid


@dataclass(frozen=True)
class JointParams:
    window_m: float = 80.0           # route distance of the segments registered together
    rotation_deg: float = 2.0        # rotation searched either side of the segment's own
    rotation_step_deg: float = 0.5
    shift_m: float = 2.0             # offsets searched either side of the segment's own
    cell_m: float = 0.5              # the joint footprint is thinned to one point per cell
    max_points: int = 4000
    truncate_m: float = 3.0
    inlier_m: float = 1.0
    shift_penalty: float = 0.0       # cost per metre of shift from the seed (m of chamfer per m)
    segment_points: int = 0          # at most this many thinned footprint points per segment (0: all)
    kernel: str = "box"              # "box": every segment in the window in full; "tricube": a share of its
                                     # points falling with its route distance, (1 − (Δs/window)³)³
    outline_points: int = 0          # at most this many thinned points per over-view outline (0: all)


class JointConfig(ParamGroup):
    """The joint pass as a stage sets it (``steps.refine.params.joint``; old flat keys: ``joint_<field>``)."""

    window_m: float = Field(50.0, ge=0, description="re-fit each 2D transform jointly with the segments within "
                                                    "this route distance (m; route-aware only; 0: off)")
    rotation_deg: float = Field(2.0, ge=0, description="rotation searched either side of the segment's own (degrees)")
    shift_m: float = Field(2.0, ge=0, description="offsets searched either side of the segment's own (metres)")
    segment_points: int = Field(0, ge=0, description="cap on footprint points (0.5 m cells) per segment (count; 0: all)")
    outline_points: int = Field(0, ge=0, description="cap on footprint points (0.5 m cells) per over-view outline (count; 0: all)")
    kernel: Literal["box", "tricube"] = Field(
        "box", description="weighting by route distance Δs: 'box' (all equal) or 'tricube' ((1 − (Δs/window)³)³)")
    shift_penalty: float = Field(0.0, ge=0, description="cost of moving a segment from its own transform (m of chamfer per m; 0: none)")

    def search(self, *, rotation_step_deg: float, cell_m: float, max_points: int, truncate_m: float,
               inlier_m: float) -> JointParams:
        """The pass's ``JointParams``: this group with the search's step, cell, cap and distances."""
        return JointParams(**self.model_dump(), rotation_step_deg=rotation_step_deg, cell_m=cell_m,
                           max_points=max_points, truncate_m=truncate_m, inlier_m=inlier_m)


class OutlineLabels:
    """The over-view segment whose outline is nearest to a scene point (KD-tree over the labelled
    pixels that touch another label or the background)."""

    def __init__(self, grid: Grid, label_image: np.ndarray) -> None:
        from scipy.spatial import cKDTree

        lab = np.asarray(label_image)
        pad = np.pad(lab, 1, mode="constant", constant_values=-1)
        edge = (lab >= 0) & ((pad[:-2, 1:-1] != lab) | (pad[2:, 1:-1] != lab)
                             | (pad[1:-1, :-2] != lab) | (pad[1:-1, 2:] != lab))
        rows, cols = np.nonzero(edge)
        self.label = lab[rows, cols]
        self.tree = cKDTree(grid.pixel_to_world(rows, cols)) if len(rows) else None

    def __call__(self, xy: np.ndarray) -> np.ndarray:
        if self.tree is None or len(xy) == 0:
            return np.full(len(xy), -1, np.int64)
        return self.label[self.tree.query(xy)[1]].astype(np.int64)


def cap_per_label(points: np.ndarray, labels: np.ndarray, cap: int) -> np.ndarray:
    """At most ``cap`` of ``points`` per label (an even stride, deterministic), in their order."""
    keep = np.ones(len(points), bool)
    _, inverse, counts = np.unique(labels, return_inverse=True, return_counts=True)
    for u in np.flatnonzero(counts > cap):
        rows = np.flatnonzero(inverse == u)
        keep[rows] = False
        keep[rows[np.linspace(0, len(rows) - 1, cap).astype(np.int64)]] = True
    return points[keep]


def joint_footprint(footprints: dict[int, np.ndarray], near: np.ndarray, ds_m: np.ndarray,
                    p: JointParams, labels: dict[int, np.ndarray] | None = None,
                    thinned: bool = False) -> np.ndarray:
    """The footprints of segments ``near`` (route distances ``ds_m`` from the segment searched) as one
    point set: each thinned to ``p.cell_m``, at most ``p.segment_points`` points per segment (so that
    a few long walls do not outweigh the other buildings' independent outline errors), a share
    ``(1 − (Δs/window)³)³`` of them under the tricube kernel (every segment keeps at least one point),
    taken by an even stride (deterministic); with ``labels`` (per segment, the nearest over-view
    outline of each point of its thinned footprint), at most ``p.outline_points`` per outline; then at
    most ``p.max_points`` in all. ``thinned``: the footprints are already thinned to ``p.cell_m``."""
    parts, part_labels = [], []
    for j, ds in zip(near, ds_m):
        f = footprints[int(j)]
        if p.segment_points <= 0 and p.kernel == "box" and labels is None:
            parts.append(f)
            continue
        if not thinned:
            f = thin_xy(f, p.cell_m, len(f))
        lab = labels[int(j)] if labels is not None else None
        n = len(f) if p.segment_points <= 0 else min(len(f), p.segment_points)
        if p.kernel == "tricube":
            n = int(np.ceil(n * tricube(float(ds) / p.window_m)))
        elif p.kernel != "box":
            raise ValueError(f"unknown joint kernel {p.kernel!r}")
        if n < len(f):
            rows = np.linspace(0, len(f) - 1, max(n, 1)).astype(np.int64)
            f, lab = f[rows], (lab[rows] if lab is not None else None)
        parts.append(f)
        part_labels.append(lab)
    joint = np.concatenate(parts)
    if labels is not None and p.outline_points > 0:
        joint = cap_per_label(joint, np.concatenate(part_labels), p.outline_points)
    return thin_xy(joint, p.cell_m, p.max_points)


def joint_transforms(footprints: dict[int, np.ndarray], T2d: np.ndarray, route_s: np.ndarray,
                     anchors_xy: np.ndarray, grid: Grid, label_image: np.ndarray,
                     p: JointParams, outlines: AllOutlines | None = None,
                     scale: np.ndarray | None = None, pivots_xy: np.ndarray | None = None) -> np.ndarray:
    """(S,3,3) jointly re-estimated 2D transforms (levelled → scene) of the segments in ``footprints``
    (their levelled footprints); the others, and a segment with no other in its window, keep T2d.
    ``route_s``: (S,) metres along the route; ``anchors_xy``: (S,2) segment centres in the street
    frame (for the spatial gate); ``outlines``: the over-view's outline field, shared with other
    searches (made here when not given). ``scale``, ``pivots_xy``: (S,) and (S,2): each footprint was
    scaled by scale[j] about pivots_xy[j] (``toolkit.refine.scale``); segment i's window is then scaled
    as one body by scale[i] about its pivot, so that the neighbours keep their distances at segment
    i's scale."""
    sp = SearchParams.model_construct(rotation_range_deg=p.rotation_deg, rotation_step_deg=p.rotation_step_deg,
                                      margin_m=0.0, truncate_m=p.truncate_m, inlier_m=p.inlier_m,
                                      shift_penalty=p.shift_penalty, subpixel=True)   # not validated: any rotation
    idx = np.array(sorted(i for i in footprints if np.isfinite(route_s[i])), np.int64)
    out = np.array(T2d, np.float64, copy=True)
    outlines = outlines if outlines is not None else AllOutlines(grid, label_image, p.truncate_m)
    r = int(np.ceil(p.shift_m / grid.gsd_m))
    thinned = p.segment_points > 0 or p.kernel != "box" or p.outline_points > 0
    if thinned:                     # once per segment, not once per window it falls in
        footprints = {int(j): thin_xy(footprints[int(j)], p.cell_m, len(footprints[int(j)])) for j in idx}
    labels = None
    if p.outline_points > 0:        # each segment's points by the outline they lie on under its own transform
        nearest_outline = OutlineLabels(grid, label_image)
        labels = {int(j): nearest_outline(footprints[int(j)] @ T2d[j][:2, :2].T + T2d[j][:2, 2]) for j in idx}
    ds, within = route_neighbours(route_s[idx], anchors_xy[idx], p.window_m)
    searched, problems = [], []
    for row, i in enumerate(idx):
        near = idx[within[row]]
        if len(near) < 2:
            # alone in its window: a re-fit would be the segment's own search without its shift penalty,
            # free to slide along a straight wall (the route's ends, rejected neighbours)
            continue
        parts = footprints if scale is None else _at_scale_of(i, near, footprints, scale, pivots_xy)
        fp = joint_footprint(parts, near, ds[row, within[row]], p, labels, thinned)
        if len(fp) < 10:
            continue
        centre = column_means(fp @ T2d[i][:2, :2].T + T2d[i][:2, 2])
        cr, cc = np.round(grid.world_to_pixel(centre[None])[0]).astype(int)
        searched.append(i)
        problems.append((fp, T2d[i], None, (slice(cr - r, cr + r + 1), slice(cc - r, cc + r + 1))))
    # independent searches: beside this process in forked children when there are cores to spare
    results = map_chunks_forked(partial(search_segments, grid=grid, label_image=label_image, p=sp, outlines=outlines,
                                        with_seed_cost=False), problems)
    for i, res in zip(searched, results):
        out[i] = res.T2d
    return out


def _at_scale_of(i: int, near: np.ndarray, footprints: dict[int, np.ndarray], scale: np.ndarray,
                 pivots_xy: np.ndarray) -> dict[int, np.ndarray]:
    """Footprints of ``near`` (each scaled by its own scale about its pivot) at segment i's scale about
    i's pivot: c_i + s_i (c_j − c_i) + (s_i / s_j)(f_j − c_j)."""
    ci, si = pivots_xy[i], scale[i]
    return {int(j): ci + si * (pivots_xy[j] - ci) + (si / scale[j]) * (footprints[int(j)] - pivots_xy[j])
            for j in near}
