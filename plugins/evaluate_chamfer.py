"""evaluate.chamfer — the paper's metric (§4.1) plus ground-truth errors when the scene has truth.

``Metrics.values`` are metrics.json's evaluation entries (schema, cutoff_m, street, reference,
chamfer, truth, matching, cameras, segments, notes), described field by field by
``toolkit.metrics_model.RunMetrics``; distances in metres, ``null`` where a value cannot be
computed (``notes`` says why). ``chamfer`` is the paper's metric over mutually nearest pairs within
``cutoff_m`` (3D, and 2D on the clouds projected on (x, y)); ``truth``, ``matching`` and ``cameras``
need the scene's truth. ``Metrics.per_point_error_m`` is the (N,) 3D error of every street point
when truth exists.

Segment-match scoring maps each street segment to the true building most of its points lie on
(truth/street_labels.npy; none when most are ground/clutter).
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
