"""evaluate.chamfer — the paper's metric (§4.1) plus ground-truth errors when the scene has truth.

``Metrics.values`` schema (written as metrics.json; distances in metres; a value is ``null`` when
it cannot be computed, and ``notes`` says why)::

    schema: "crossview.metrics/1"
    cutoff_m: float                      # pairs farther than this are ignored (paper: 10 m)
    reference: {source: "truth_lidar" | "overview_cloud" | <path> | null, path, n_points, n_used}
    street: {n_points, n_used}           # registered street cloud (n_used after subsampling)
    chamfer: null | {                    # the paper's metric; null when there is no reference cloud
      3d | 2d: {                         # 2d: both clouds projected on (x, y), pairs found in 2D
        mean_m, std_m, median_m, p95_m,  # over mutually nearest pairs within cutoff_m
        n_pairs,
        paired_fraction,                 # n_pairs / street n_used: misplaced points stop pairing,
        paired_fraction_reference,       #   so read the mean together with these fractions
        histogram: {edges_m: [..], counts: [..]}}}   # pair distances, hist_bin_m (0.1 m) bins to cutoff_m
    truth: null | {                      # registered vs truth/street_points.npy, every point
      error_3d | horizontal: {mean_m, median_m, p90_m, p95_m, max_m, n},
      within_m: {"0.5" | "1" | "2": {horizontal: fraction, 3d: fraction}},
      histogram: {edges_m: [.., null], counts}}      # 3D errors; the last bin is "beyond cutoff_m"
    matching: null | {precision, recall, precision_iou, recall_iou, n_street_segments, n_matched, n_correct,
                      n_with_counterpart, n_overview_segments, n_overview_with_building}
    cameras: null | {                    # camera centres vs truth/cameras.txt, matched by image name
      source: "adjusted" | "registered", # which poses the centre_error_* fields describe
      centre_error_mean_m, centre_error_median_m, centre_error_p95_m, centre_error_horizontal_median_m,
      registered: {n, n_missing, error_3d: stats, horizontal: stats},
      adjusted: same | null}             # after the adjust step, when the recipe has one
    segments: [ {index, id, n_points, overview_match, overview_id, match_cost, match_confidence,
                 refine_valid, refine_cost, true_building, matched_building, correct,
                 error_mean_m, error_median_m} ]   # one per street segment; fields null when unknown
                                                   # (correct is null for unmatched segments)
    notes: [str]                         # what was skipped and why

The runner adds ``warnings``; timings go to ``timings.json`` so metrics.json is reproducible. ``Metrics.per_point_error_m`` is the (N,) 3D error of
every street point when truth exists. Segment-match scoring maps each street segment to the true
building most of its points lie on (truth/street_labels.npy; none when most are ground/clutter).
A match is correct when the over-view segment covers at least half of that building's true
footprint (truth/buildings.geojson rasterised on the over-view grid), so a segment merging several
buildings is the counterpart of each; precision = correct / matched, recall = correct / street
segments whose building some over-view segment covers. ``precision_iou``/``recall_iou`` use the
stricter one-to-one rule (the over-view segment's best-IoU building, IoU ≥ 0.5, must be it).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from toolkit.errors import SceneError
from toolkit.evaluation import metrics as M
from toolkit.evaluation import truth as T
from toolkit.scene import load_array, load_points
from toolkit.stage import Stage, StageParams
from toolkit.threads import thread_budget
from toolkit.types import (
    AdjustedCameras,
    Matches,
    Metrics,
    OverviewSegments,
    Registration,
    Scene,
    SegmentTransforms,
    StreetSegments,
)

SCHEMA = "crossview.metrics/1"
REFERENCE_KEYS = ("truth_lidar", "overview_cloud")


@dataclass(frozen=True)
class PointMetrics:
    """What needs only the registered points: metrics.json's street, reference and chamfer entries,
    the notes made on the way, and the (3D, horizontal) errors vs truth (None: no truth points)."""

    values: dict[str, Any]
    notes: list[str]
    errors: tuple[np.ndarray, np.ndarray] | None


class Chamfer(Stage):
    """The paper's metric (mutual-NN Chamfer, 3D and 2D) plus errors against the truth when present."""

    kind = "evaluate"
    name = "chamfer"

    class Params(StageParams):
        cutoff_m: float = Field(10.0, gt=0, description="ignore mutually nearest pairs farther than this (paper: 10 m)")
        reference: str = Field(
            "auto", description="reference cloud: 'truth_lidar', 'overview_cloud', a file "
                                "path, or 'auto' (the first of those the scene has)")
        max_points: int = Field(1_000_000, ge=0, description="subsample each cloud to at most this many "
                                "points (deterministic; 0 = all) for the Chamfer metric")
        seed: int = Field(0, description="seed of the deterministic subsampling")
        hist_bin_m: float = Field(0.1, gt=0, description="bin width of the distance histograms (m)")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return (params.reference,) if params.reference in REFERENCE_KEYS else ()

    def prefetch(self, registration: Registration, scene: Scene) -> PointMetrics:
        """The Chamfer metrics and per-point errors, which need only the registered points: the
        runner computes them beside the adjust step, whose cameras only the camera errors need."""
        return self._point_metrics(registration, scene)

    def __call__(self, registration: Registration, scene: Scene, obs: Any,
                 cameras: AdjustedCameras | None = None, matches: Matches | None = None,
                 street: StreetSegments | None = None, overview: OverviewSegments | None = None,
                 transforms: SegmentTransforms | None = None, prefetched: PointMetrics | None = None) -> Metrics:
        point = prefetched if prefetched is not None else self._point_metrics(registration, scene)
        values: dict[str, Any] = {"schema": SCHEMA, "cutoff_m": self.params.cutoff_m, **point.values}
        notes = list(point.notes)
        per_point, truth_values, seg_scores = self._truth(scene, registration, cameras, matches, street,
                                                          overview, notes, point.errors)
        values.update({"truth": None, "matching": None, "cameras": None, **truth_values})
        values["segments"] = _segments_table(street, matches, transforms, overview, per_point, seg_scores)
        values["notes"] = notes
        return Metrics(values=values, per_point_error_m=per_point)

    # --- pieces -------------------------------------------------------------------------------
    def _point_metrics(self, registration: Registration, scene: Scene) -> PointMetrics:
        p = self.params
        notes: list[str] = []
        pts = np.asarray(registration.points, np.float64)
        values: dict[str, Any] = {}
        ref_source, ref_path = self._reference(scene, notes)
        street_idx = M.subsample(pts, p.max_points, p.seed)
        values["street"] = {"n_points": len(pts), "n_used": len(street_idx)}
        pair: tuple[np.ndarray, np.ndarray] | None = None
        if ref_path is None:
            values["reference"] = {"source": None, "path": None, "n_points": 0, "n_used": 0}
        else:
            ref = _read_reference(scene, ref_source, ref_path)
            ref_idx = M.subsample(ref, p.max_points, p.seed + 1)
            values["reference"] = {"source": ref_source, "path": str(ref_path), "n_points": len(ref),
                                   "n_used": len(ref_idx)}
            pair = (pts[street_idx], ref[ref_idx])
        dims = ("3d", "2d") if pair is not None else ()
        # with two threads the 3D and 2D metrics run beside the per-point errors (independent
        # computations: the same values either way)
        with ThreadPoolExecutor(2) if dims and thread_budget() >= 2 else nullcontext() as pool:
            pending = {d: pool.submit(self._chamfer, *pair, d) for d in dims} if pool is not None else {}
            errors = _truth_errors(registration, scene)
            chamfer = {d: pending[d].result() if pending else self._chamfer(*pair, d) for d in dims}
        values["chamfer"] = chamfer if pair is not None else None
        return PointMetrics(values, notes, errors)

    def _chamfer(self, a: np.ndarray, b: np.ndarray, dims: str) -> dict[str, Any]:
        p = self.params
        cols = slice(None) if dims == "3d" else slice(0, 2)
        return M.mutual_nn_chamfer(a[:, cols], b[:, cols], p.cutoff_m).summary(p.hist_bin_m, p.cutoff_m)

    def _reference(self, scene: Scene, notes: list[str]) -> tuple[str | None, Path | None]:
        ref = self.params.reference
        if ref == "auto":
            for key in REFERENCE_KEYS:
                if scene.has(key):
                    return key, getattr(scene.files, key)
            notes.append("no reference cloud (scene has neither truth.lidar nor overview.cloud): Chamfer skipped")
            return None, None
        if ref in REFERENCE_KEYS:
            if not scene.has(ref):
                raise SceneError(f"evaluate.chamfer: reference {ref!r} is not named by {scene.root / 'scene.yaml'}")
            return ref, getattr(scene.files, ref)
        path = Path(ref).expanduser()
        if not path.is_absolute() and not path.exists():
            path = scene.root / path
        if not path.is_file():
            raise SceneError(f"{ref}: reference cloud for evaluate.chamfer not found")
        return ref, path.resolve()

    def _truth(self, scene, registration, cameras, matches, street, overview, notes, errors):
        """Per-point errors, segment-match scores and camera-centre errors (when truth exists)."""
        if not any(scene.has(k) for k in ("truth_street_points", "truth_street_labels", "truth_cameras")):
            notes.append("scene has no truth: per-point, segment-match and camera errors skipped")
            return None, {}, None
        out: dict[str, Any] = {"truth": None, "matching": None, "cameras": None}
        per_point = None
        if errors is not None:
            e3, eh = errors
            per_point = e3
            out["truth"] = M.point_error_summary(e3, eh)
            edges = np.append(np.arange(0.0, self.params.cutoff_m + 1e-9, self.params.hist_bin_m), np.inf)
            counts, _ = np.histogram(e3, bins=edges)
            out["truth"]["histogram"] = {"edges_m": [round(float(e), 6) for e in edges[:-1]] + [None],
                                         "counts": counts.astype(int).tolist()}
        else:
            notes.append("no truth.street_points: per-point error skipped")

        seg_scores = None
        if matches is not None and street is not None and overview is not None \
                and scene.has("truth_street_labels") and scene.has("truth_buildings"):
            labels = load_array(scene, "truth_street_labels")
            ids, geoms = T.read_true_buildings(scene.files.truth_buildings, scene.crs)
            seg_scores = T.segment_match_scores(matches, street, overview, labels, ids, geoms)
            out["matching"] = {k: v for k, v in seg_scores.items() if not k.startswith("_")}
        else:
            missing = [n for n, v in (("matches", matches), ("street segments", street),
                                      ("over-view segments", overview)) if v is None]
            missing += [f"truth.{k}" for k in ("street_labels", "buildings") if not scene.has(f"truth_{k}")]
            notes.append(f"segment-match precision/recall skipped: no {', '.join(missing)}")

        if scene.has("truth_cameras"):
            poses = T.read_images_txt(scene.files.truth_cameras)
            cam: dict[str, Any] = {"registered": T.camera_centre_errors(
                registration.image_names, registration.R, registration.t, poses), "adjusted": None}
            if cameras is not None:
                m = cameras.model
                cam["adjusted"] = T.camera_centre_errors(m.image_names, m.R, m.t, poses)
            src = "adjusted" if cam["adjusted"] is not None else "registered"
            e3, eh = cam[src]["error_3d"], cam[src]["horizontal"]
            out["cameras"] = {"source": src, "centre_error_mean_m": e3["mean_m"],
                              "centre_error_median_m": e3["median_m"], "centre_error_p95_m": e3["p95_m"],
                              "centre_error_horizontal_median_m": eh["median_m"], **cam}
        else:
            notes.append("no truth.cameras: camera-centre error skipped")
        return per_point, out, seg_scores


def _truth_errors(registration: Registration, scene: Scene) -> tuple[np.ndarray, np.ndarray] | None:
    """(3D, horizontal) error of every registered point vs truth/street_points.npy (None: no truth)."""
    if not scene.has("truth_street_points"):
        return None
    true_pts = load_array(scene, "truth_street_points")
    if true_pts.shape != registration.points.shape:
        raise SceneError(f"{scene.files.truth_street_points}: shape {true_pts.shape} does not match "
                         f"the {registration.points.shape} registered street points")
    return M.point_errors(registration.points, true_pts)


def _read_reference(scene: Scene, source: str | None, path: Path) -> np.ndarray:
    if source in REFERENCE_KEYS:
        return load_points(scene, source, who="evaluate.chamfer")
    from toolkit.io.cloud import read_points

    return read_points(path)


def _segments_table(street, matches, transforms, overview, per_point, seg_scores) -> list[dict]:
    if street is None:
        return []
    S = len(street)
    labels = np.asarray(street.point_labels)
    n_points = np.bincount(labels[labels >= 0], minlength=S)[:S] if S else np.zeros(0, int)
    err_mean = err_med = None
    if per_point is not None and S:
        sel = labels >= 0
        keys = labels[sel]
        if len(keys) and keys.max() < 2 ** 15:
            # A stable sort is unique: int16 keys give the same order by numpy's radix sort, ~2x faster
            # than the comparison sort of wider keys.
            keys = keys.astype(np.int16)
        order = np.argsort(keys, kind="stable")
        errs = per_point[sel][order]
        splits = np.cumsum(n_points)[:-1]
        groups = np.split(errs, splits)
        err_mean = [float(g.mean()) if len(g) else None for g in groups]
        err_med = [float(np.median(g)) if len(g) else None for g in groups]
    per = seg_scores["_per_segment"] if seg_scores else None
    rows = []
    for s in range(S):
        m = int(matches.segment_match[s]) if matches is not None else None
        rows.append({
            "index": s, "id": int(street.ids[s]), "n_points": int(n_points[s]),
            "overview_match": m if m is not None and m >= 0 else None,
            "overview_id": int(overview.ids[m]) if (m is not None and m >= 0 and overview is not None) else None,
            "match_cost": _num(matches.cost[s]) if matches is not None else None,
            "match_confidence": _num(matches.confidence[s]) if matches is not None else None,
            "refine_valid": bool(transforms.valid[s]) if transforms is not None else None,
            "refine_cost": _num(transforms.cost[s]) if transforms is not None else None,
            "true_building": int(per["true_building"][s]) if per is not None else None,
            "matched_building": int(per["matched_building"][s]) if per is not None else None,
            "correct": bool(per["correct"][s]) if (per is not None and m is not None and m >= 0) else None,
            "error_mean_m": _num(err_mean[s]) if err_mean is not None else None,
            "error_median_m": _num(err_med[s]) if err_med is not None else None,
        })
    return rows


def _num(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return round(x, 6) if np.isfinite(x) else None
