"""Small hand-built matching problems with known answers (tests and benchmarks of graph/unary/match).

A grid of city blocks separated by streets; each block holds up to four rectangular buildings
(slightly rotated, set back from the street). The over-view side is the rasterised footprints as
``OverviewSegments``; the street side is one segment per street-facing façade (points along the
wall with noise, some façades missing), expressed in an arbitrary 2D rigid frame, optionally with a
scale error, as ``StreetSegments``. ``truth`` gives the over-view segment of every street segment.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from toolkit.types import Grid, OverviewSegments, StreetSegments


@dataclass(frozen=True)
class ToyScene:
    overview: OverviewSegments
    street: StreetSegments
    truth: np.ndarray          # (S_street,) over-view segment index of each street segment (-1: none)
    theta: float               # true transform levelled street → scene: x = s·R(θ) x_street + t
    t: np.ndarray
    scale: float
    footprints: list[np.ndarray]  # (4,2) world corners of each over-view segment's building
    cameras: np.ndarray           # (C,2) street-frame observer positions (three per façade, in the street)


def _rect(cx: float, cy: float, w: float, h: float, ang: float) -> np.ndarray:
    c, s = np.cos(ang), np.sin(ang)
    local = np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) / 2
    return local @ np.array([[c, s], [-s, c]]) + [cx, cy]


def make_toy(blocks: tuple[int, int] = (3, 3), seed: int = 0, gsd_m: float = 0.5,
             origin: tuple[float, float] = (500_000.0, 4_400_000.0), noise_m: float = 0.08,
             street_m: float = 16.0, facade_drop: float = 0.15, scale: float = 1.0,
             n_clutter: int = 0, spacing_m: float = 0.2,
             route: tuple[int, int, int, int] | None = None) -> ToyScene:
    """``route`` (bx0, bx1, by0, by1): the vehicle drives the loop of streets around blocks
    [bx0, bx1) × [by0, by1) and sees only the façades facing it; None: every street."""
    rng = np.random.default_rng(seed)
    nbx, nby = blocks
    widths = rng.uniform(55, 90, nbx)
    heights = rng.uniform(55, 90, nby)
    xs = street_m + np.concatenate([[0], np.cumsum(widths + street_m)])
    ys = street_m + np.concatenate([[0], np.cumsum(heights + street_m)])
    size_x, size_y = xs[-1], ys[-1]

    rects, facades = [], []   # facades: (building index, p0, p1)
    for bx in range(nbx):
        for by in range(nby):
            x0, x1, y0, y1 = xs[bx], xs[bx] + widths[bx], ys[by], ys[by] + heights[by]
            mx, my = (x0 + x1) / 2, (y0 + y1) / 2
            for qx, qy in ((0, 0), (1, 0), (0, 1), (1, 1)):
                if rng.random() < 0.15:
                    continue  # empty lot
                lx0, lx1 = (x0, mx) if qx == 0 else (mx, x1)
                ly0, ly1 = (y0, my) if qy == 0 else (my, y1)
                setback = rng.uniform(1.5, 5.0, 2)
                w = rng.uniform(0.45, 0.8) * (lx1 - lx0)
                h = rng.uniform(0.45, 0.8) * (ly1 - ly0)
                # building pushed to the street corner of its lot
                cx = lx0 + setback[0] + w / 2 if qx == 0 else lx1 - setback[0] - w / 2
                cy = ly0 + setback[1] + h / 2 if qy == 0 else ly1 - setback[1] - h / 2
                ang = np.deg2rad(rng.uniform(-6, 6))
                corners = _rect(cx, cy, w, h, ang)
                b = len(rects)
                rects.append(corners)
                # street-facing sides: the outward normal points out of the block
                for i in range(4):
                    p0, p1 = corners[i], corners[(i + 1) % 4]
                    mid = (p0 + p1) / 2
                    normal = np.array([p1[1] - p0[1], p0[0] - p1[0]])
                    normal /= np.linalg.norm(normal)
                    if np.dot(normal, mid - [cx, cy]) < 0:
                        normal = -normal
                    faces_x = (qx == 0 and normal[0] < -0.7) or (qx == 1 and normal[0] > 0.7)
                    faces_y = (qy == 0 and normal[1] < -0.7) or (qy == 1 and normal[1] > 0.7)
                    if route is not None:  # street index faced: west street of block bx is bx
                        sx, sy = bx + qx, by + qy
                        rx0, rx1, ry0, ry1 = route
                        faces_x = faces_x and sx in (rx0, rx1) and ry0 <= by < ry1
                        faces_y = faces_y and sy in (ry0, ry1) and rx0 <= bx < rx1
                    if (faces_x or faces_y) and rng.random() >= facade_drop:
                        # cameras in the street in front of the façade, as a drive past would have
                        cams_here = [p0 + f * (p1 - p0) + 8.0 * normal for f in (0.25, 0.5, 0.75)]
                        facades.append((b, p0, p1, cams_here))

    overview = _overview_of(rects, size_x, size_y, gsd_m, origin)

    # street segments in an arbitrary rigid frame
    theta, t = _street_frame(rng, origin, size_x, size_y)
    c, s = np.cos(theta), np.sin(theta)
    seg_pts, truth, cams = [], [], []
    for b, p0, p1, cam in facades:
        length = np.linalg.norm(p1 - p0)
        if length < 5:
            continue
        u = np.sort(rng.uniform(0, 1, int(length / spacing_m)))
        d = (p1 - p0) / length
        pts = p0 + u[:, None] * (p1 - p0) + rng.normal(0, noise_m, len(u))[:, None] * [-d[1], d[0]]
        seg_pts.append(pts + origin)
        truth.append(b)
        cams.extend(np.asarray(cam) + origin)
    for _ in range(n_clutter):  # walls/fences that no over-view segment explains
        seg_pts.append(_clutter_wall(rng, size_x, size_y) + origin)
        truth.append(-1)
    Rinv = np.array([[c, s], [-s, c]])
    street_xy = [((p - t) @ Rinv.T) / scale for p in seg_pts]  # world = scale·R x + t
    street = street_from_boundaries(street_xy)
    cameras = ((np.asarray(cams).reshape(-1, 2) - t) @ Rinv.T) / scale
    return ToyScene(overview, street, np.asarray(truth, np.int64), theta, t, scale,
                    [r + origin for r in rects], cameras)


def _overview_of(rects: list, size_x: float, size_y: float, gsd_m: float, origin) -> OverviewSegments:
    """The over-view label raster of the buildings (north-up; local metres → world by + origin)."""
    from skimage.draw import polygon as draw_polygon

    W, H = int(np.ceil(size_x / gsd_m)), int(np.ceil(size_y / gsd_m))
    top = origin[1] + H * gsd_m
    grid = Grid((gsd_m, 0.0, origin[0], 0.0, -gsd_m, top), W, H, "EPSG:32617")
    label = np.full((H, W), -1, np.int32)
    for b, corners in enumerate(rects):
        rc = grid.world_to_pixel(corners + origin)
        rr, cc = draw_polygon(rc[:, 0] + 0.5, rc[:, 1] + 0.5, shape=(H, W))
        label[rr, cc] = b
    return overview_from_labels(label, grid)


def _street_frame(rng: np.random.Generator, origin, size_x: float, size_y: float) -> tuple[float, np.ndarray]:
    """A random rotation and a frame origin near the city (as a levelled SfM frame is)."""
    theta = float(rng.uniform(-np.pi, np.pi))
    c, s = np.cos(theta), np.sin(theta)
    centre = np.array(origin) + [size_x / 2, size_y / 2]
    return theta, centre - np.array([[c, -s], [s, c]]) @ rng.uniform(-200, 200, 2)


def _clutter_wall(rng: np.random.Generator, size_x: float, size_y: float) -> np.ndarray:
    """60 points of a 6-20 m straight wall at a random place and direction (local metres)."""
    p0 = rng.uniform([0, 0], [size_x, size_y])
    d = rng.normal(size=2)
    d /= np.linalg.norm(d)
    u = np.sort(rng.uniform(0, rng.uniform(6, 20), 60))
    return p0 + u[:, None] * d


def overview_from_labels(label: np.ndarray, grid: Grid) -> OverviewSegments:
    """OverviewSegments from an (H,W) segment-index image (-1 = background)."""
    n = int(label.max()) + 1
    pad = np.pad(label, 1, constant_values=-1)
    inner = pad[1:-1, 1:-1]
    edge = ((inner != pad[:-2, 1:-1]) | (inner != pad[2:, 1:-1]) |
            (inner != pad[1:-1, :-2]) | (inner != pad[1:-1, 2:])) & (inner >= 0)
    rows, cols = np.nonzero(edge)
    labs = inner[rows, cols]
    order = np.argsort(labs, kind="stable")
    splits = np.searchsorted(labs[order], np.arange(1, n))
    boundary = tuple(np.stack([r, c], 1).astype(np.int32) for r, c in
                     zip(np.split(rows[order], splits), np.split(cols[order], splits)))
    idx = np.arange(n)
    cr = ndi.mean(np.indices(label.shape)[0], label, idx)
    cc = ndi.mean(np.indices(label.shape)[1], label, idx)
    centroids = grid.pixel_to_world(np.asarray(cr), np.asarray(cc))
    from shapely.geometry import MultiPoint

    polys = tuple(MultiPoint(grid.pixel_to_world(b[:, 0], b[:, 1])).convex_hull for b in boundary)
    return OverviewSegments(grid=grid, label_image=label, ids=np.arange(n, dtype=np.int64),
                            boundary_px=boundary, centroids=centroids, polygons=polys,
                            ground_height=np.full(n, np.nan), ground_normal=np.tile([0.0, 0, 1], (n, 1)),
                            source="toy")


def street_from_boundaries(boundary_xy: list[np.ndarray]) -> StreetSegments:
    """StreetSegments holding only 2D façade footprints (identity levelling)."""
    S = len(boundary_xy)
    pts = [np.asarray(b, dtype=np.float64).reshape(-1, 2) for b in boundary_xy]
    labels = (np.concatenate([np.full(len(b), i, np.int32) for i, b in enumerate(pts)]) if S
              else np.zeros(0, np.int32))
    cent = np.array([b.mean(axis=0) for b in pts]).reshape(-1, 2)
    ext = np.array([np.linalg.norm(b.max(axis=0) - b.min(axis=0)) for b in pts])
    return StreetSegments(origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=labels,
                          ids=np.arange(S, dtype=np.int64), boundary_xy=tuple(pts), centroids=cent,
                          extent_m=ext, ground_z=np.full(S, np.nan), ground_normal=np.tile([0.0, 0, 1], (S, 1)))
