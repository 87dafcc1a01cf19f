"""``evaluate.chamfer``'s scores against the truth (per-point errors, segment matches, camera
centres) and metrics.json's per-segment table (schema: toolkit.metrics_model)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from toolkit.evaluation import metrics as M
from toolkit.evaluation import truth as T
from toolkit.evaluation.pointwise import PointErrors, truth_rows
from toolkit.scene import load_array
from toolkit.types import AdjustedCameras, Matches, OverviewSegments, Registration, Scene, StreetSegments

TRUTH_KEYS = ("truth_street_points", "truth_street_labels", "truth_cameras")


@dataclass(frozen=True)
class TruthScores:
    """metrics.json's truth, matching and cameras entries (``values``; empty: no truth), the (N,) 3D
    error of every point (None: no truth points) and segment_match_scores' result (None: not scored)."""

    values: dict[str, Any]
    per_point: np.ndarray | None = None
    matching: dict | None = None


def truth_scores(scene: Scene, registration: Registration, cameras: AdjustedCameras | None,
                 matches: Matches | None, street: StreetSegments | None, overview: OverviewSegments | None,
                 errors: PointErrors | None, cutoff_m: float, hist_bin_m: float,
                 notes: list[str]) -> TruthScores:
    """Per-point errors, segment-match scores and camera-centre errors (when truth exists)."""
    if not any(scene.has(k) for k in TRUTH_KEYS):
        notes.append("scene has no truth: per-point, segment-match and camera errors skipped")
        return TruthScores({})
    out: dict[str, Any] = {"truth": None, "matching": None, "cameras": None}
    if errors is not None:
        out["truth"] = point_truth(errors, cutoff_m, hist_bin_m)
    else:
        notes.append("no truth.street_points: per-point error skipped")
    seg_scores = match_scores(scene, matches, street, overview, notes, registration.rows)
    if seg_scores is not None:
        out["matching"] = {k: v for k, v in seg_scores.items() if not k.startswith("_")}
    if scene.has("truth_cameras"):
        out["cameras"] = camera_scores(scene, registration, cameras)
    else:
        notes.append("no truth.cameras: camera-centre error skipped")
    # per-point errors of other rows than the registration's (a truth subset, an analysis cloud) have no
    # per-segment table: the segments know the registration's rows only
    aligned = errors is not None and errors.rows is None and registration.rows is None
    if errors is not None and not aligned:
        notes.append(f"per-point errors on the {len(errors.error_3d):,} street points with truth; "
                     "no per-segment errors")
    return TruthScores(out, errors.error_3d if aligned else None, seg_scores)


def point_truth(errors: PointErrors, cutoff_m: float, hist_bin_m: float) -> dict[str, Any]:
    """The truth entry: error statistics and the 3D error histogram (last bin: beyond cutoff_m)."""
    out = M.point_error_summary(errors.error_3d, errors.horizontal)
    edges = np.append(np.arange(0.0, cutoff_m + 1e-9, hist_bin_m), np.inf)
    counts, _ = np.histogram(errors.error_3d, bins=edges)
    out["histogram"] = {"edges_m": [round(float(e), 6) for e in edges[:-1]] + [None],
                        "counts": counts.astype(int).tolist()}
    return out


def match_scores(scene: Scene, matches: Matches | None, street: StreetSegments | None,
                 overview: OverviewSegments | None, notes: list[str],
                 rows: np.ndarray | None = None) -> dict | None:
    """T.segment_match_scores against the true labels and buildings (None, with a note: not scored).
    ``rows``: the input rows of the street points (``Registration.rows``; None: every row)."""
    if matches is not None and street is not None and overview is not None \
            and scene.has("truth_street_labels") and scene.has("truth_buildings"):
        labels = load_array(scene, "truth_street_labels")
        truth_at = truth_rows(scene, len(labels))
        if truth_at is not None or rows is not None:  # score on the rows both hold
            mine = np.arange(len(street.point_labels)) if rows is None else np.asarray(rows)
            i_mine, i_truth = common_rows(mine, truth_at, len(labels))
            if not len(i_mine):
                notes.append("segment-match precision/recall skipped: no street point of the analysis has a "
                             "true label")
                return None
            street, labels = replace(street, point_labels=np.asarray(street.point_labels)[i_mine]), labels[i_truth]
        ids, geoms = T.read_true_buildings(scene.files.truth_buildings, scene.crs)
        return T.segment_match_scores(matches, street, overview, labels, ids, geoms)
    missing = [n for n, v in (("matches", matches), ("street segments", street),
                              ("over-view segments", overview)) if v is None]
    missing += [f"truth.{k}" for k in ("street_labels", "buildings") if not scene.has(f"truth_{k}")]
    notes.append(f"segment-match precision/recall skipped: no {', '.join(missing)}")
    return None


def common_rows(a: np.ndarray, b: np.ndarray | None, n_b: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices into the increasing row numbers ``a`` and ``b`` (None: rows 0..n_b−1) of the rows both
    hold: what ``np.intersect1d(..., return_indices=True)`` gives, without its sort of both (0.5 GB on
    17 M rows)."""
    if b is None:
        hit = a < n_b
        return np.flatnonzero(hit), a[hit]
    at = np.searchsorted(b, a)
    hit = at < len(b)
    hit[hit] = b[at[hit]] == a[hit]
    return np.flatnonzero(hit), at[hit]


def camera_scores(scene: Scene, registration: Registration,
                  cameras: AdjustedCameras | None) -> dict[str, Any]:
    """The cameras entry: centre errors of the registered (and adjusted) poses vs truth/cameras.txt."""
    poses = T.read_images_txt(scene.files.truth_cameras)
    cam: dict[str, Any] = {"registered": T.camera_centre_errors(
        registration.image_names, registration.R, registration.t, poses), "adjusted": None}
    if cameras is not None:
        m = cameras.model
        cam["adjusted"] = T.camera_centre_errors(m.image_names, m.R, m.t, poses)
    src = "adjusted" if cam["adjusted"] is not None else "registered"
    e3, eh = cam[src]["error_3d"], cam[src]["horizontal"]
    return {"source": src, "centre_error_mean_m": e3["mean_m"], "centre_error_median_m": e3["median_m"],
            "centre_error_p95_m": e3["p95_m"], "centre_error_horizontal_median_m": eh["median_m"], **cam}


@dataclass(frozen=True)
class SegmentErrors:
    """Per street segment: its number of points and the mean / median of their errors (None: none)."""

    n_points: np.ndarray
    mean: list | None = None
    median: list | None = None


def segment_errors(street: StreetSegments, per_point: np.ndarray | None) -> SegmentErrors:
    S = len(street)
    labels = np.asarray(street.point_labels)
    n_points = np.bincount(labels[labels >= 0], minlength=S)[:S] if S else np.zeros(0, int)
    if per_point is None or not S:
        return SegmentErrors(n_points)
    sel = labels >= 0
    keys = labels[sel]
    if len(keys) and keys.max() < 2 ** 15:
        # A stable sort is unique: int16 keys give the same order by numpy's radix sort, ~2x faster
        # than the comparison sort of wider keys.
        keys = keys.astype(np.int16)
    order = np.argsort(keys, kind="stable")
    groups = np.split(per_point[sel][order], np.cumsum(n_points)[:-1])
    return SegmentErrors(n_points, [float(g.mean()) if len(g) else None for g in groups],
                         [float(np.median(g)) if len(g) else None for g in groups])


def segments_table(street: StreetSegments | None, matches: Matches | None, transforms,
                   overview: OverviewSegments | None, per_point: np.ndarray | None,
                   seg_scores: dict | None) -> list[dict]:
    """metrics.json's segments entry: one row per street segment, fields None when unknown."""
    if street is None:
        return []
    err = segment_errors(street, per_point)
    per = seg_scores["_per_segment"] if seg_scores else None
    rows = []
    for s in range(len(street)):
        m = int(matches.segment_match[s]) if matches is not None else None
        rows.append({
            "index": s, "id": int(street.ids[s]), "n_points": int(err.n_points[s]),
            "overview_match": m if m is not None and m >= 0 else None,
            "overview_id": int(overview.ids[m]) if (m is not None and m >= 0 and overview is not None)
            else None,
            "match_cost": _num(matches.cost[s]) if matches is not None else None,
            "match_confidence": _num(matches.confidence[s]) if matches is not None else None,
            "refine_valid": bool(transforms.valid[s]) if transforms is not None else None,
            "refine_cost": _num(transforms.cost[s]) if transforms is not None else None,
            "true_building": int(per["true_building"][s]) if per is not None else None,
            "matched_building": int(per["matched_building"][s]) if per is not None else None,
            "correct": bool(per["correct"][s]) if (per is not None and m is not None and m >= 0) else None,
            "error_mean_m": _num(err.mean[s]) if err.mean is not None else None,
            "error_median_m": _num(err.median[s]) if err.median is not None else None,
        })
    return rows


def _num(x) -> float | None:
    if x is None:
        return None
    x = float(x)
    return round(x, 6) if np.isfinite(x) else None
