"""street.region_growing: building façade segments of the street cloud (Ling & Qin 2022, street-view segments).

Steps (helpers in ``toolkit/street``):
1. Local origin (median), Morton order; by default a voxel reduction (``voxel_m``, 0.3 m), the
   voxel grid laid out in a frame levelled by a first, coarser pass (a grid tilted against the
   vertical biases voxel-centroid normals towards its axes). Labels go back to every input point.
2. Open3D PCA normals (KNN ``knn``); vertical from the sphere histogram of normal orientations,
   refined by least squares, sign and axis checked by "façades rise above the ground"
   (``vertical.py``).
3. Façade rule: normal > ``facade_angle_deg`` from vertical AND > ``facade_neighbour_fraction``
   of the k neighbours too, optionally voted over ``multiscale_knn`` (``facade.py``).
4. Region growing (Rabbani) as connected components of the façade kNN graph (union-find pass +
   scipy.sparse.csgraph), bends split (``growing.py``); rows of terraced houses cut where the façade
   top steps (``split.py``); walls meeting at a corner and pieces of one occluded wall merged when
   they reach the same height (``merge.py``); segments under ``min_diameter_m`` wide,
   ``min_height_m`` high or ``min_points`` dropped; leftover façade points absorbed by an adjacent
   segment whose normal agrees (``absorb.py``). Segment indices are ordered by decreasing size; ids = indices.
5. Ground (normal within ``ground_angle_deg`` of vertical) and every other point carried by the
   nearest segment within ``association_radius_m`` (2D); per-segment ground height and normal.

Why a voxel default: at full resolution the k = 20 neighbourhoods of the 0.13 m-spaced synthetic
campus cloud span ~0.3 m, too little against its 3-10 cm MVS noise; normals scatter, growing
fragments walls and the façade recall drops to 0.34 (0.90 at 0.3 m). The reduction also keeps
the stage within 3x the cloud's memory; ``voxel_m: 0`` analyses every point.
"""

from __future__ import annotations

import contextlib
import logging
import time
from typing import Any

import numpy as np
from pydantic import Field, model_validator

from toolkit.errors import StageError
from toolkit.observe import DebugLines, DebugPoints
from toolkit.scene import load_points
from toolkit.stage import Stage, StageParams
from toolkit.street.absorb import absorb_leftovers
from toolkit.street.associate import ground_statistics, nearest_segment
from toolkit.street.facade import facade_points
from toolkit.street.growing import group_min_max, grow_regions
from toolkit.street.merge import merge_segments
from toolkit.street.normals import build_tree, coordinate_columns, open3d_normals
from toolkit.street.order import prepare
from toolkit.street.outline import boundary_points, diameters, relabel_by_size
from toolkit.street.split import split_terraces
from toolkit.street.vertical import Vertical, estimate_up
from toolkit.types import Scene, StreetSegments

log = logging.getLogger("crossview.street")
WHO = "steps.street (street.region_growing)"
DEBUG_POINTS = 200_000
GROUND_STATS_POINTS = 500_000  # per-segment ground medians from at most about this many points
COARSE_POINTS = 1_000_000  # first levelling (voxel mode): from about this many input points
# percent of the stage's time each step (a lap of _Clock) takes, measured on campus (3.5 M points,
# 20 s): the progress bar advances by these, so it moves about evenly in time
STEP_SHARES = {"order": 13, "normals": 32, "vertical": 2, "facade": 31, "growing": 10, "associate": 8, "output": 4}


class RegionGrowingParams(StageParams):
    knn: int = Field(20, ge=3, le=200, description="neighbours for PCA normals and the façade neighbour test")
    multiscale_knn: list[int] | None = Field(
        None, description="optional several k (e.g. [10, 20, 30]): façade when ≥ multiscale_min_votes scales agree")
    multiscale_min_votes: int = Field(2, ge=1, description="scales that must call a point façade")
    facade_angle_deg: float = Field(75.0, gt=0, lt=90, description="façade: normal more than this from vertical (degrees)")
    facade_neighbour_fraction: float = Field(
        0.75, ge=0, lt=1, description="façade: more than this share of the k neighbours pass the angle test")
    ground_angle_deg: float = Field(15.0, gt=0, lt=90, description="ground: normal within this of vertical (degrees)")
    graph_knn: int = Field(
        10, ge=1, description="region growing links each façade point to at most its nearest graph_knn (≤ knn)")
    smooth_angle_deg: float = Field(10.0, gt=0, lt=90, description="region growing: max angle between neighbour normals (degrees)")
    seed_curvature_max: float = Field(
        0.1, gt=0, le=1 / 3, description="region growing: points with surface variation above this do not propagate")
    bend_split_angle_deg: float = Field(
        30.0, gt=0, le=180, description="split segments whose horizontal normals spread "
                                        "more than this (degrees; 180 = off)")
    split_window_m: float = Field(
        0.0, ge=0, description="terrace split: length compared either side of each place along a "
                               "façade top (m; 0 = no split; 2.0 for terraced cities)")
    split_bin_m: float = Field(0.5, gt=0, description="terrace split: profile bin length along the façade (m)")
    split_top_step_m: float = Field(
        0.3, ge=0, description="terrace split: cut where the façade top (eaves) steps by at least this (m; 0 = off)")
    split_setback_m: float = Field(
        0.0, ge=0, description="terrace split: cut where the façade plane steps back by at least this (m; 0 = off)")
    split_turn_deg: float = Field(
        0.0, ge=0, description="terrace split: cut where the façade direction "
                               "turns by at least this (degrees; 0 = off)")
    split_min_end_m: float = Field(
        5.0, ge=0, description="terrace split: no cut closer than this to a "
                               "segment's end, where façade tops droop (m)")
    split_min_gap_m: float = Field(
        5.0, ge=0, description="terrace split: cuts at least this far apart (m; the stronger step wins)")
    merge_contact_m: float = Field(
        1.0, ge=0, description="merge segments whose façade points come this close (2D) at equal wall height (0 = off)")
    merge_gap_m: float = Field(
        0.0, ge=0, description="merge pieces of one wall (parallel, in line) up to "
                               "this far apart at equal height (m; 0 = off)")
    merge_height_tol_m: float = Field(1.0, gt=0, description="max difference of wall-top heights where segments meet (m)")
    merge_min_corner_deg: float = Field(
        45.0, ge=0, le=90, description="merge only segments whose façades turn by at least this (degrees; a corner)")
    min_diameter_m: float = Field(5.0, ge=0, description="drop segments narrower than this horizontally (m)")
    min_height_m: float = Field(
        2.5, ge=0, description="drop segments whose points span less than this vertically (cars, fences)")
    min_points: int = Field(30, ge=1, description="drop segments with fewer analysis points")
    absorb_hops: int = Field(
        3, ge=0, description="leftover façade points join a neighbour segment whose normal "
                             "agrees, through up to this many graph links (0 = off)")
    absorb_link_m: float = Field(
        1.0, gt=0, description="absorption follows graph links no longer than this (3D, metres)")
    absorb_angle_deg: float = Field(
        10.0, gt=0, lt=90, description="max angle between the normals of a leftover point and its absorbing neighbour")
    association_radius_m: float = Field(
        50.0, gt=0, description="points farther than this (2D) from every segment get carrier -1")
    voxel_m: float = Field(0.3, ge=0, description="voxel size of the analysis cloud (0 = every point); "
                                                  "labels are carried back to every input point")
    vertical_bin_deg: float = Field(2.0, gt=0, le=10, description="sphere histogram bin size for the vertical (degrees)")
    vertical_min_support: float = Field(
        0.2, ge=0, le=1, description="min share of normals parallel or perpendicular (±5°) to the found vertical")
    vertical_cell_m: float = Field(4.0, gt=0, description="cell size of the façade-above-ground sign test (m)")
    vertical_sample: int = Field(100_000, ge=1000, description="normals sampled for the vertical (count)")
    boundary_cell_m: float = Field(0.25, gt=0, description="boundary points: one mean point per cell of this size")
    boundary_max_points: int = Field(2000, ge=10, description="boundary points kept per segment at most")
    keep_normals: bool = Field(True, description="return per-point normals (N,3) float32")
    seed: int = Field(0, description="seed of the random subsampling")

    @model_validator(mode="after")
    def _scales(self) -> RegionGrowingParams:
        if self.multiscale_knn is not None:
            if len(self.multiscale_knn) == 0 or min(self.multiscale_knn) < 3:
                raise ValueError("multiscale_knn must list k values ≥ 3")
            if self.multiscale_min_votes > len(self.multiscale_knn):
                raise ValueError("multiscale_min_votes exceeds the number of scales")
        return self


class RegionGrowing(Stage):
    """Street-view building segments by normals, vertical histogram and region growing.

    Output (``StreetSegments``): ``origin`` the median of the cloud; ``up_rotation`` levels it
    (minimal rotation, so the levelled yaw follows the input's); ``point_labels`` segment index /
    -1 ground / -2 other, in input order (points of one voxel share their voxel's label);
    ``carrier`` the segment every point moves with (-1 beyond ``association_radius_m``);
    ``boundary_xy`` façade points in the levelled frame at z = 0, one per ``boundary_cell_m`` cell,
    at most ``boundary_max_points``; ``normals`` upward-oriented unit normals in the input frame
    (the voxel's), or None with ``keep_normals: false``.

    Bad inputs: an empty cloud, one whose points are all non-finite, fewer points than knn + 1,
    all points on a line, or normals with no dominant orientation (support below
    ``vertical_min_support``) raise ``StageError`` (one line). Non-finite rows are ignored with a
    warning (label -2, carrier -1, NaN normal). A cloud that can be levelled but has no façade
    segment (e.g. only ground) gives an empty ``StreetSegments`` and a warning.
    """

    kind = "street"
    name = "region_growing"
    Params = RegionGrowingParams

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, scene: Scene, obs: Any) -> StreetSegments:
        return self.segment(load_points(scene, "street_cloud", who=WHO), obs)

    def segment(self, points: np.ndarray, obs: Any) -> StreetSegments:
        """Segment an (N,3) cloud given as an array (the scene-free entry point).

        After a call, ``self.timings`` (seconds per step) and ``self.vertical`` (the vertical
        estimate) describe it, for benchmarks.
        """
        # The stage's BLAS calls are tall-skinny (N,3) @ (3,3) products: multi-threaded OpenBLAS
        # gains nothing on them and, on a loaded machine, loses ~25x to thread synchronisation.
        from threadpoolctl import threadpool_limits

        with threadpool_limits(1, user_api="blas"), contextlib.closing(_Clock(obs)) as clock:
            return self._segment(points, obs, clock)

    def _segment(self, points: np.ndarray, obs: Any, clock: _Clock) -> StreetSegments:
        p: RegionGrowingParams = self.params  # type: ignore[assignment]
        pts, finite = _valid_points(points, obs)
        scales = sorted(set(p.multiscale_knn)) if p.multiscale_knn else [p.knn]
        k_max = max(scales + [p.knn])
        if len(pts) <= k_max:
            raise StageError(f"{WHO}: only {len(pts)} finite street points, need more than knn={k_max}")
        rng = np.random.default_rng(p.seed)
        sample = pts[np.sort(rng.choice(len(pts), min(len(pts), 100_000), replace=False))]
        _check_not_collinear(sample)
        origin = np.median(sample, axis=0)
        del sample
        # A voxel grid tilted against the vertical biases voxel-centroid normals towards its axes
        # (0.3° at 0.4 m on the campus scene): level a coarser grid first, then voxelise levelled.
        pre = np.eye(3)
        if p.voxel_m > 0:
            coarse = prepare(pts[::max(1, len(pts) // COARSE_POINTS)], origin, 2 * p.voxel_m, WHO)
            pre = _rotation_to_z(self._vertical(coarse.points, open3d_normals(coarse.points, p.knn)).up)
            del coarse
        cloud = prepare(pts, origin, p.voxel_m, WHO, rotation=pre if p.voxel_m > 0 else None)
        del pts
        analysis = cloud.points  # (p - origin) @ pre.T
        clock.lap("order")
        normals = open3d_normals(analysis, p.knn)
        per_scale = [normals if k == p.knn else open3d_normals(analysis, k) for k in scales]
        clock.lap("normals")
        vertical = self._vertical(analysis, normals)
        up = vertical.up
        if vertical.cells == 0:  # nothing tells up from down: prefer the input +z
            up = up if (pre.T @ up)[2] >= 0 else -up
            obs.warn("no cell holds both ground and façade points: up/down sign taken from the input +z")
        rot = _rotation_to_z(up)  # analysis frame → levelled
        clock.lap("vertical")
        tree = build_tree(analysis)
        facade = facade_points(analysis, tree, coordinate_columns(analysis), per_scale, scales, p.knn, up,
                               p.facade_angle_deg, p.facade_neighbour_fraction,
                               p.multiscale_min_votes if p.multiscale_knn else 1, min(p.graph_knn, p.knn))
        del tree, per_scale
        clock.lap("facade")
        fac_xyz = analysis[facade.index] @ rot.T
        fac_lab = self._segments(facade, fac_xyz, normals[facade.index] @ rot.T.astype(np.float32), len(analysis))
        clock.lap("growing")
        n_seg = int(fac_lab.max()) + 1 if len(fac_lab) and fac_lab.max() >= 0 else 0
        in_seg = fac_lab >= 0
        seg_idx, seg_lab, seg_xy = facade.index[in_seg], fac_lab[in_seg], fac_xyz[in_seg, :2]
        del facade, fac_xyz
        up32 = rot[2].astype(np.float32)
        normals *= np.where(normals @ up32 < 0, np.float32(-1), np.float32(1))[:, None]  # oriented upwards
        ground = normals @ up32 > np.cos(np.radians(p.ground_angle_deg))
        labels = np.full(len(analysis), -2, dtype=np.int32)
        labels[ground] = -1
        labels[seg_idx] = seg_lab
        is_seg_point = np.zeros(len(analysis), dtype=bool)
        is_seg_point[seg_idx] = True  # they carry themselves: no search
        carrier = nearest_segment(analysis, rot[:2], seg_xy, seg_lab, p.association_radius_m,
                                  skip=is_seg_point)
        carrier[seg_idx] = seg_lab
        del is_seg_point
        g_idx = np.flatnonzero(ground)[::max(1, int(ground.sum()) // GROUND_STATS_POINTS)]
        ground_z, ground_normal = ground_statistics(analysis[g_idx] @ rot[2], normals[g_idx] @ rot.T.astype(np.float32),
                                                    carrier[g_idx], n_seg)
        counts = np.maximum(np.bincount(seg_lab, minlength=n_seg), 1)
        centroids = np.stack([np.bincount(seg_lab, weights=seg_xy[:, i], minlength=n_seg) for i in range(2)],
                             axis=1).reshape(n_seg, 2) / counts[:, None]
        clock.lap("associate")
        if n_seg == 0:
            obs.warn(f"no façade segment found (none ≥ min_diameter_m={p.min_diameter_m}, "
                     f"min_height_m={p.min_height_m}); street segments are empty")
        if obs.wants_debug:
            _debug(obs, analysis, rot, labels, p.seed)
        n_analysed, inverse = len(analysis), cloud.inverse
        del cloud, analysis, ground, g_idx  # the outputs below are the stage's largest arrays
        out_normals = None
        if p.keep_normals:
            normals = normals @ pre.astype(np.float32)  # back to the input frame
            out_normals = _to_input(normals, inverse, finite, np.nan)
        segments = StreetSegments(
            origin=origin, up_rotation=rot @ pre, point_labels=_to_input(labels, inverse, finite, -2),
            carrier=_to_input(carrier, inverse, finite, -1), ids=np.arange(n_seg, dtype=np.int64),
            boundary_xy=boundary_points(seg_xy, seg_lab, n_seg, p.boundary_cell_m, p.boundary_max_points),
            centroids=centroids, extent_m=diameters(seg_xy, seg_lab, n_seg), ground_z=ground_z,
            ground_normal=ground_normal, normals=out_normals)
        clock.lap("output")
        log.debug("street.region_growing: %d points (%d analysed), %d segments; %s",
                  len(points), n_analysed, n_seg, clock)
        self.timings, self.vertical = clock.laps, vertical
        return segments

    def _segments(self, facade, fac_xyz: np.ndarray, fac_normals: np.ndarray, n_points: int) -> np.ndarray:
        """(F,) segment index of each façade point (-1: none): grow, merge, order by size, filter."""
        p: RegionGrowingParams = self.params  # type: ignore[assignment]
        if len(facade.index) == 0:
            return np.zeros(0, dtype=np.int32)
        azimuth = np.arctan2(fac_normals[:, 1], fac_normals[:, 0])
        labels = grow_regions(fac_normals, facade.graph, facade.index, n_points, facade.curvature,
                              p.smooth_angle_deg, p.seed_curvature_max, azimuth, p.bend_split_angle_deg)
        labels = split_terraces(fac_xyz, azimuth, labels, p.split_bin_m, p.split_window_m, p.split_top_step_m,
                                p.split_setback_m, p.split_turn_deg, p.split_min_end_m, p.split_min_gap_m)
        labels = merge_segments(fac_xyz[:, :2], fac_xyz[:, 2], azimuth, labels, p.merge_contact_m, p.merge_gap_m,
                                p.merge_height_tol_m, p.merge_min_corner_deg, p.min_points)
        labels = _drop_small(relabel_by_size(labels), fac_xyz, p.min_diameter_m, p.min_height_m, p.min_points)
        if p.absorb_hops == 0:
            return labels
        labels = absorb_leftovers(labels, facade.graph, facade.index, n_points, fac_xyz, fac_normals,
                                  p.absorb_angle_deg, p.absorb_link_m, p.absorb_hops)
        return relabel_by_size(labels)

    def _vertical(self, points: np.ndarray, normals: np.ndarray) -> Vertical:
        p: RegionGrowingParams = self.params  # type: ignore[assignment]
        vertical = estimate_up(points, normals, bin_deg=p.vertical_bin_deg, cell_m=p.vertical_cell_m,
                               sample=p.vertical_sample, seed=p.seed)
        if vertical is None or vertical.support < p.vertical_min_support:
            support = 0.0 if vertical is None else vertical.support
            raise StageError(f"{WHO}: no vertical structure: normals have no dominant orientation "
                             f"(support {support:.2f} < vertical_min_support {p.vertical_min_support}; "
                             f"a street frame far from metric does this: set street_scale)")
        return vertical


def _valid_points(points: np.ndarray, obs: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """The finite rows of an (N,3) cloud and the (N,) mask of them (None: all finite); one-line errors
    otherwise."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise StageError(f"{WHO}: street cloud must be (N,3), got shape {pts.shape}")
    if len(pts) == 0:
        raise StageError(f"{WHO}: the street cloud has no points")
    if np.isfinite(pts.min()) and np.isfinite(pts.max()):  # two quick passes; the row test is 6x slower
        return pts, None
    finite = np.isfinite(pts).all(axis=1)
    n_ok = int(finite.sum())
    if n_ok == 0:
        raise StageError(f"{WHO}: every street cloud point is NaN or Inf")
    if n_ok < len(pts):
        obs.warn(f"{len(pts) - n_ok} street points with NaN/Inf coordinates ignored (label -2)")
        pts = pts[finite]
    return pts, finite


class _Clock:
    """Seconds per step (``laps``), each lap advancing the stage's progress bar by its ``STEP_SHARES``."""

    def __init__(self, obs: Any) -> None:
        self.laps: dict[str, float] = {}
        self._t = time.perf_counter()
        total = sum(STEP_SHARES.values())
        self._bar = iter(obs.progress(range(total), total=total, desc="street"))
        next(self._bar, None)  # the bar appears at 0 %

    def lap(self, name: str) -> None:
        now = time.perf_counter()
        self.laps[name] = now - self._t
        self._t = now
        for _ in range(STEP_SHARES.get(name, 0)):
            next(self._bar, None)

    def close(self) -> None:
        """Ends the bar when the stage stops early (an error)."""
        getattr(self._bar, "close", lambda: None)()

    def __str__(self) -> str:
        return ", ".join(f"{k} {v:.2f} s" for k, v in self.laps.items())


def _to_input(values: np.ndarray, inverse: np.ndarray, finite: np.ndarray | None,
              fill: float) -> np.ndarray:
    """Analysis values → one row per input point (``fill`` on non-finite rows; ``finite`` None: none)."""
    if finite is None or finite.all():
        return values[inverse]
    out = np.full((len(finite),) + values.shape[1:], fill, dtype=values.dtype)
    out[finite] = values[inverse]
    return out


def _check_not_collinear(sample: np.ndarray) -> None:
    s = np.linalg.svd(sample - sample.mean(axis=0), compute_uv=False)
    if s[0] == 0 or s[1] < 1e-6 * s[0]:
        raise StageError(f"{WHO}: all street points lie on a line or a point; nothing to segment")


def _rotation_to_z(up: np.ndarray) -> np.ndarray:
    """The smallest rotation R with R @ up = +z (Rodrigues)."""
    up = up / np.linalg.norm(up)
    v = np.cross(up, [0.0, 0.0, 1.0])
    c = float(up[2])
    if np.linalg.norm(v) < 1e-12:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def _drop_small(labels: np.ndarray, xyz: np.ndarray, min_diameter_m: float, min_height_m: float,
                min_points: int) -> np.ndarray:
    ok = labels >= 0
    if not ok.any():
        return labels
    n = int(labels.max()) + 1
    lo, hi = group_min_max(xyz[ok, 2], labels[ok], n)
    big = ((diameters(xyz[ok, :2], labels[ok], n) >= min_diameter_m) & (hi - lo >= min_height_m)
           & (np.bincount(labels[ok], minlength=n) >= min_points))
    remap = np.full(n, -1, dtype=np.int32)
    remap[big] = np.arange(int(big.sum()), dtype=np.int32)
    out = labels.copy()
    out[ok] = remap[labels[ok]]
    return out


def _debug(obs: Any, analysis: np.ndarray, rot: np.ndarray, labels: np.ndarray, seed: int) -> None:
    rng = np.random.default_rng(seed)
    pick = np.sort(rng.choice(len(analysis), min(len(analysis), DEBUG_POINTS), replace=False))
    levelled = (analysis[pick] @ rot.T).astype(np.float32)
    lab = labels[pick]
    obs.debug("raw", DebugPoints(levelled, radius_m=0.05))
    centre = levelled.mean(axis=0)
    obs.debug("vertical", DebugLines([np.stack([centre, centre + np.float32([0.0, 0.0, 20.0])])], radius_m=0.3))
    obs.debug("facade", DebugPoints(levelled[lab >= 0], radius_m=0.05))
    obs.debug("segments", DebugPoints(levelled[lab >= 0], class_ids=lab[lab >= 0], radius_m=0.05))
    # the 2D boundaries are logged from the StreetSegments output itself (street/boundaries)
