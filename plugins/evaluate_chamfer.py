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

from typing import Any

from pydantic import Field

from toolkit.evaluation.pointwise import REFERENCE_KEYS, ChamferConfig, PointMetrics, point_metrics
from toolkit.evaluation.scoring import segments_table, truth_scores
from toolkit.stage import Stage, StageParams
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


class Chamfer(Stage):
    """The paper's metric (mutual-NN Chamfer, 3D and 2D) plus errors against the truth when present."""

    kind = "evaluate"
    name = "chamfer"

    class Params(StageParams):
        cutoff_m: float = Field(10.0, gt=0, description="ignore mutually nearest pairs farther than this (paper: 10 m)")
        reference: str = Field("auto", description="reference cloud: 'truth_lidar', 'overview_cloud', a file "
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
        return point_metrics(registration, scene, self._config())

    def _config(self) -> ChamferConfig:
        p = self.params
        return ChamferConfig(reference=p.reference, cutoff_m=p.cutoff_m, max_points=p.max_points,
                             seed=p.seed, hist_bin_m=p.hist_bin_m)

    def __call__(self, registration: Registration, scene: Scene, obs: Any,
                 cameras: AdjustedCameras | None = None, matches: Matches | None = None,
                 street: StreetSegments | None = None, overview: OverviewSegments | None = None,
                 transforms: SegmentTransforms | None = None, prefetched: PointMetrics | None = None) -> Metrics:
        p = self.params
        # 1. what needs only the points (usually computed beside the adjust step): Chamfer, errors
        point = prefetched if prefetched is not None else point_metrics(registration, scene, self._config())
        values: dict[str, Any] = {"schema": SCHEMA, "cutoff_m": p.cutoff_m, **point.values}
        notes = list(point.notes)
        # 2. scores against the truth: per-point errors, segment matches, camera centres
        scores = truth_scores(scene, registration, cameras, matches, street, overview, point.errors,
                              p.cutoff_m, p.hist_bin_m, notes)
        values.update({"truth": None, "matching": None, "cameras": None, **scores.values})
        # 3. one row per street segment
        values["segments"] = segments_table(street, matches, transforms, overview, scores.per_point,
                                            scores.matching)
        values["notes"] = notes
        return Metrics(values=values, per_point_error_m=scores.per_point)
