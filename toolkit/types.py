"""Typed, frozen containers for every arrow of the data flow (see docs/ARCHITECTURE.md).

Conventions
- Scene CRS coordinates are float64 and may be large (UTM easting/northing); stages subtract a
  local origin internally, never truncate.
- The *levelled street frame* is the street cloud rotated so that up = +z:
  ``levelled = (points - StreetSegments.origin) @ StreetSegments.up_rotation.T``.
- Segment *indices* (0..S-1) address arrays; segment *ids* are the labels written out.
- 2D rigid transforms are (3,3) homogeneous matrices acting on column vectors [x, y, 1].
- Camera poses follow COLMAP: world-to-camera ``x_cam = R @ X + t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

if TYPE_CHECKING:
    from toolkit.capture import StreetCapture

Array = np.ndarray


@dataclass(frozen=True)
class Grid:
    """A north-up raster grid in the scene CRS.

    transform: GDAL/rasterio affine coefficients (a, b, c, d, e, f):
        x = a*col + b*row + c, y = d*col + e*row + f  (col, row at pixel corners).
    """

    transform: tuple[float, float, float, float, float, float]
    width: int
    height: int
    crs: str

    @property
    def gsd_m(self) -> float:
        a, b, _, d, e, _ = self.transform
        return float(np.sqrt(abs(a * e - b * d)))

    def pixel_to_world(self, rows: Array, cols: Array) -> Array:
        """Centres of pixels (rows, cols) → (N,2) world x, y."""
        a, b, c, d, e, f = self.transform
        r = np.asarray(rows, dtype=np.float64) + 0.5
        q = np.asarray(cols, dtype=np.float64) + 0.5
        return np.stack([a * q + b * r + c, d * q + e * r + f], axis=-1)

    def world_to_pixel(self, xy: Array) -> Array:
        """(N,2) world x, y → (N,2) fractional (row, col) with pixel centres at integers."""
        a, b, c, d, e, f = self.transform
        xy = np.asarray(xy, dtype=np.float64)
        det = a * e - b * d
        dx, dy = xy[..., 0] - c, xy[..., 1] - f
        col = (e * dx - b * dy) / det - 0.5
        row = (-d * dx + a * dy) / det - 0.5
        return np.stack([row, col], axis=-1)


@dataclass(frozen=True)
class Raster:
    """A raster read from a GeoTIFF. data: (bands, H, W); nodata mask: (H, W) bool, True = no data."""

    data: Array
    grid: Grid
    nodata_mask: Array
    band_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class Camera:
    """A pinhole camera of a COLMAP model (intrinsics only)."""

    camera_id: int
    model: str
    width: int
    height: int
    params: Array  # model-specific, COLMAP order


@dataclass(frozen=True)
class SparseModel:
    """A COLMAP model in memory.

    cameras: camera_id → Camera; image_names: (C,) in file order; image_ids, camera_ids: (C,) int;
    R: (C,3,3), t: (C,3) world-to-camera; points3d_ids: (P,) int, points3d: (P,3) float64,
    points3d_rgb: (P,3) uint8; observations: (K,4) float64 rows (image index, point3d index, u, v).
    points3d_error_px: (P,) float64 mean reprojection error of each point over its track (px, COLMAP's
        ERROR column; -1: no observation); None when unknown (written as 0).
    qvec: (C,4) w,x,y,z as read from a file (kept so an unchanged model round-trips byte-exact);
        None when the poses were computed. ``R`` is authoritative.
    """

    cameras: Mapping[int, Camera]
    image_names: tuple[str, ...]
    image_ids: Array
    camera_ids: Array
    R: Array
    t: Array
    points3d_ids: Array
    points3d: Array
    points3d_rgb: Array
    observations: Array
    qvec: Array | None = None
    points3d_error_px: Array | None = None

    @property
    def centres(self) -> Array:
        """(C,3) camera centres: -R^T t."""
        return -np.einsum("cji,cj->ci", self.R, self.t)


@dataclass(frozen=True)
class SceneFiles:
    """Absolute paths of the files a scene manifest names (None when absent)."""

    dsm: Path | None = None
    ortho: Path | None = None
    footprints: Path | None = None
    osm: Path | None = None
    labels: Path | None = None
    overview_cloud: Path | None = None
    street_cloud: Path | None = None
    sparse: Path | None = None
    gps: Path | None = None
    dem: Path | None = None
    truth_lidar: Path | None = None
    truth_street_points: Path | None = None
    truth_street_labels: Path | None = None
    truth_street_rows: Path | None = None   # rows of the street cloud the truth arrays hold (None: every row)
    truth_buildings: Path | None = None
    truth_cameras: Path | None = None


@dataclass(frozen=True)
class StreetScale:
    """value: street-frame units per metre the run works at; source: 'scene', 'recipe', 'gps',
    'matching' (no GPS: the route's façades against the over-view, ``toolkit.street_scale``) or
    'assumed' (1: no GPS, no COLMAP model); pairs: fix pairs behind a GPS estimate.
    matching: the scan's figures (JSON-able); settled: False while the matching is still to check
    value (the runner's street passes)."""

    value: float
    source: str
    pairs: int = 0
    estimate: float | None = None   # the GPS or matching estimate (value is 1 when it is within 2 % of 1)
    matching: dict[str, Any] | None = None
    settled: bool = True

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"value": round(self.value, 6), "source": self.source}
        if self.source == "gps":
            out["gps_estimate"] = round(float(self.estimate), 6)
            out["gps_pairs"] = self.pairs
            if self.matching and "estimate" in self.matching:
                out["matching_estimate"] = self.matching["estimate"]
            if self.matching and self.matching.get("passes"):
                out["matching"] = self.matching
        if self.source == "matching":
            out["matching_estimate"] = None if self.estimate is None else round(float(self.estimate), 6)
            out["matching"] = self.matching
        return out


@dataclass(frozen=True)
class Scene:
    """A validated scene folder. Loading is lazy: use ``toolkit.scene`` readers (cached).
    street_scale: the street frame's units per metre (``toolkit.street_scale``; set by the runner)."""

    root: Path
    name: str
    crs: str
    files: SceneFiles
    manifest: Mapping[str, Any] = field(default_factory=dict)
    street_scale: StreetScale = field(default_factory=lambda: StreetScale(1.0, "assumed"))

    def has(self, key: str) -> bool:
        return getattr(self.files, key) is not None


@dataclass(frozen=True)
class OverviewSegments:
    """Building segments on the over-view grid.

    label_image: (H,W) int32, segment index or -1.  ids: (S,) int64 segment ids.
    boundary_px: S arrays (Bi,2) int32 (row, col) boundary pixels of each segment.
    centroids: (S,2) float64 world x, y.  polygons: S shapely Polygons/MultiPolygons (world).
    ground_height: (S,) float64 terrain height around each segment (NaN when unknown).
    ground_normal: (S,3) unit terrain normal around each segment (0,0,1 when unknown).
    source: stage key that made them.
    """

    grid: Grid
    label_image: Array
    ids: Array
    boundary_px: tuple[Array, ...]
    centroids: Array
    polygons: tuple[Any, ...]
    ground_height: Array
    ground_normal: Array
    source: str = ""

    def __len__(self) -> int:
        return len(self.ids)

    def boundary_world(self, i: int) -> Array:
        b = self.boundary_px[i]
        return self.grid.pixel_to_world(b[:, 0], b[:, 1])


@dataclass(frozen=True)
class StreetSegments:
    """Building (façade) segments of the street cloud, in the levelled street frame.

    origin: (3,) local origin in the input street frame; up_rotation: (3,3) rotation; see module doc.
    point_labels: (N,) int32 segment index, -1 ground, -2 unassigned.
    carrier: (N,) int32 the segment index each point moves with (-1: none found).
    ids: (S,) int64.  boundary_xy: S arrays (Bi,2) float64 façade points projected to z = 0.
    centroids: (S,2) float64; extent_m: (S,) horizontal diameter.
    ground_z: (S,) median levelled height of the segment's ground points (NaN if none).
    ground_normal: (S,3) unit normal of the segment's ground points (levelled frame).
    normals: (N,3) float32 point normals in the input frame, or None.
    """

    origin: Array
    up_rotation: Array
    point_labels: Array
    carrier: Array
    ids: Array
    boundary_xy: tuple[Array, ...]
    centroids: Array
    extent_m: Array
    ground_z: Array
    ground_normal: Array
    normals: Array | None = None

    def __len__(self) -> int:
        return len(self.ids)

    def level(self, points: Array) -> Array:
        """Input street frame (N,3) → levelled frame (N,3)."""
        # a contiguous right operand: (N,3) @ (3,3) is ~2.5x faster than with the transposed view
        return (np.asarray(points, dtype=np.float64) - self.origin) @ np.ascontiguousarray(self.up_rotation.T)

    @property
    def levelling(self) -> Array:
        """(4,4) homogeneous matrix of ``level``."""
        m = np.eye(4)
        m[:3, :3] = self.up_rotation
        m[:3, 3] = -self.up_rotation @ self.origin
        return m


@dataclass(frozen=True)
class ConjugateGraphs:
    """K-NN segment graphs of both views and their conjugate graph.

    street_graph / overview_graph: networkx.Graph on segment indices.
    street_edges: (E,2) int street segment indices (j, k); each is one conjugate node.
    overview_edges: (F,2) int over-view segment indices (p, q).
    label_pairs: (L-1,2) int: non-null label l maps (j, k) → (label_pairs[l,0], label_pairs[l,1]);
        label 2f is edge f in order (p, q), label 2f+1 in order (q, p).
    null_label: L-1 (the last label).
    conj_edges: (C,2) int conjugate node pairs (a < b) whose street edges share a segment.
    conj_shared: (C,) int that shared street segment index.
    conjugate_graph: networkx.Graph on conjugate node indices.
    """

    street_graph: Any
    overview_graph: Any
    street_edges: Array
    overview_edges: Array
    label_pairs: Array
    conj_edges: Array
    conj_shared: Array
    conjugate_graph: Any

    @property
    def n_nodes(self) -> int:
        return len(self.street_edges)

    @property
    def n_labels(self) -> int:
        return len(self.label_pairs) + 1

    @property
    def null_label(self) -> int:
        return len(self.label_pairs)


@dataclass(frozen=True)
class DataCosts:
    """Unary costs of the conjugate nodes.

    cost: (E,L) float64 in [0,1]; pruned candidates are +inf; cost[:, null] = 1.
    theta_rad: (E,L-1) rotation of the fitted 2D rigid transform (levelled street → scene CRS).
    t: (E,L-1,2) its translation: x_scene = R(theta) @ x_street + t.
    prior: where the candidates were pruned from: "gps", "route_placement" or None (every pair searched);
    prior_figures: truth-free figures of that prior (route placement: window scores, disagreement of
    neighbouring windows), for the run's self-assessment.
    """

    cost: Array
    theta_rad: Array
    t: Array
    prior: str | None = None
    prior_figures: Mapping[str, Any] | None = None

    def released(self) -> DataCosts:
        """These costs without their (E,L) arrays (1.2 GB on the district scene): what the run keeps once
        no later step needs them, for its self-assessment (prior, prior_figures)."""
        from dataclasses import replace

        return replace(self, cost=np.zeros((0, 0)), theta_rad=np.zeros((0, 0)), t=np.zeros((0, 0, 2)))


@dataclass(frozen=True)
class Matches:
    """Result of inference.

    edge_label: (E,) int label chosen for each conjugate node.
    segment_match: (S,) int over-view segment index matched to each street segment, -1 = null.
    confidence: (S,) float in [0,1] (share of incident-edge votes agreeing).
    T2d: (S,3,3) 2D rigid transform (levelled street xy → scene xy) per street segment
        (identity where unmatched).
    cost: (S,) mean unary cost of the agreeing edges (1 where unmatched).
    energy: final energy; energy_trace: (iters,) per iteration; iterations: count;
    lower_bound: dual bound when the solver has one (else None); converged: bool.
    """

    edge_label: Array
    segment_match: Array
    confidence: Array
    T2d: Array
    cost: Array
    energy: float
    energy_trace: Array
    iterations: int
    converged: bool
    lower_bound: float | None = None


@dataclass(frozen=True)
class SegmentTransforms:
    """Per street segment 3D rigid transform, input street frame → scene CRS.

    T: (S,4,4); valid: (S,) bool (False: unmatched or rejected, carried by neighbours);
    cost: (S,) refinement cost; confidence: (S,).
    """

    T: Array
    valid: Array
    cost: Array
    confidence: Array


@dataclass(frozen=True)
class Registration:
    """The registered street cloud and camera poses, in the scene CRS.

    points: (N,3) float64, row i = input street point i.
    image_names: (C,); R: (C,3,3), t: (C,3) world-to-camera poses after warping.
    point_segment: (N,) int carrier segment used (-1: none).
    camera_spread_m: (C,) spread of the segment transforms blended at each camera centre (the
    weighted RMS distance of their placements from the blended one, metres), or None (unknown).
    warp: the point warp that moved ``points`` (``toolkit.warp.model.PointWarp``, with the points'
    carriers), stored as ``warp.npz`` for ``crossview apply``; None when the stage gives none.
    rows: (N,) input row of each point when the run analysed every k-th point of a large cloud
    (``toolkit.stream``); None: row i is input point i.
    camera_bridged: (C,) bool, the camera's pose follows the street trajectory across a route gap
    (``toolkit.warp.bridge``), or None (no bridge ran).
    camera_gap_m: (C,) route distance from the camera to the nearest one that sees a registered
    façade (``toolkit.warp.bridge.ground_gap_m``; inf: none in its sequence), or None (no bridge ran).
    """

    points: Array
    image_names: tuple[str, ...]
    R: Array
    t: Array
    point_segment: Array
    camera_spread_m: Array | None = None
    warp: Any = None
    rows: Array | None = None
    camera_bridged: Array | None = None
    camera_gap_m: Array | None = None


@dataclass(frozen=True)
class AdjustedCameras:
    """Camera poses after constrained bundle adjustment (COLMAP convention, scene CRS).

    model: the adjusted SparseModel (same image names and order as the input).
    rms_before_px / rms_after_px: reprojection RMS; iterations: solver iterations.
    registration: the registration with its street points re-made from the adjusted poses
    (``toolkit.adjust.remake``), which the steps after this one see; None: the warp's stands.
    """

    model: SparseModel
    rms_before_px: float
    rms_after_px: float
    iterations: int
    registration: Registration | None = None


@dataclass(frozen=True)
class Metrics:
    """Evaluation results: a JSON-able nested mapping (schema in plugins/evaluate_chamfer.py)."""

    values: Mapping[str, Any]
    per_point_error_m: Array | None = None  # (N,) 3D error per street point when truth exists


@dataclass(frozen=True)
class RunOutputs:
    """What a run has made so far: its inputs (``scene``, ``capture``) and one field per stage kind's
    output, named as in ``toolkit.stage.KIND_OUTPUT`` (None: not made; the recipe has no such step
    or it has not run yet). The runner passes a stage its inputs from here by name."""

    scene: Scene | None = None
    capture: StreetCapture | None = None
    overview: OverviewSegments | None = None
    street: StreetSegments | None = None
    graphs: ConjugateGraphs | None = None
    costs: DataCosts | None = None
    matches: Matches | None = None
    transforms: SegmentTransforms | None = None
    registration: Registration | None = None
    cameras: AdjustedCameras | None = None
    metrics: Metrics | None = None

    def has(self, name: str) -> bool:
        return getattr(self, name) is not None

    def made(self) -> tuple[str, ...]:
        """The names of the fields that are set, in field order."""
        return tuple(f.name for f in fields(self) if getattr(self, f.name) is not None)
