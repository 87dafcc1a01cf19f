"""metrics.json as one pydantic model: what a run writes there and what its readers read.

``RunMetrics`` describes the file as ``toolkit.outputs.write_outputs`` writes it, in its key order:
the self-assessment (``toolkit.status``, docs/status.md), then the evaluation (``evaluate.chamfer``:
``plugins/evaluate_chamfer.py``, ``toolkit/evaluation/``), then what the runner adds. Distances are
in metres; a value is null when it cannot be computed (the evaluation's ``notes`` say why).

Every field is optional: a recipe without an evaluate step writes no evaluation entries, a scene
without truth has ``truth`` / ``matching`` / ``cameras`` null, and a metrics.json of an older run
loads with the keys it has. An unknown key is kept (``extra="allow"``): it loads, and is written
again after the known keys of its entry. ``to_json`` gives back exactly the keys that were given
(absent stays absent, null stays null), so a loaded file is written again as the same bytes.

The end-of-run summary, ``crossview batch``, ``crossview compare`` and report.html read the
evaluation through ``RunMetrics.of(metrics)`` and take their numbers from ``key_figures()``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

from pydantic import BaseModel, ConfigDict, Field

if TYPE_CHECKING:
    from toolkit.types import Metrics


class Entry(BaseModel):
    """Base of metrics.json's entries: unknown keys kept, immutable, "3d"-like keys by alias."""

    model_config = ConfigDict(extra="allow", frozen=True, validate_by_name=True, validate_by_alias=True)


# --- the evaluation's entries ----------------------------------------------------------------------
class StreetCount(Entry):
    """The registered street cloud: its points, and those used after subsampling."""

    n_points: int | None = None
    n_used: int | None = None


class ReferenceCloud(Entry):
    """The Chamfer metric's reference cloud (source null: the scene has none)."""

    source: str | None = None  # "truth_lidar" | "overview_cloud" | the path as given
    path: str | None = None
    n_points: int | None = None
    n_used: int | None = None


class Histogram(Entry):
    """Distances in ``hist_bin_m`` bins up to ``cutoff_m``; the truth's last edge is null: "beyond"."""

    edges_m: list[float | None] | None = None
    counts: list[int] | None = None


class ChamferStats(Entry):
    """The paper's metric over the mutually nearest pairs within ``cutoff_m``. Misplaced points
    stop pairing, so read the mean together with the paired fractions."""

    mean_m: float | None = None
    std_m: float | None = None
    median_m: float | None = None
    p95_m: float | None = None
    n_pairs: int | None = None
    paired_fraction: float | None = None  # n_pairs / the street cloud's n_used
    paired_fraction_reference: float | None = None
    histogram: Histogram | None = None


class Chamfer(Entry):
    """3D, and 2D: both clouds projected on (x, y), pairs found in 2D."""

    d3: ChamferStats | None = Field(None, alias="3d")
    d2: ChamferStats | None = Field(None, alias="2d")


class ErrorStats(Entry):
    mean_m: float | None = None
    median_m: float | None = None
    p90_m: float | None = None
    p95_m: float | None = None
    max_m: float | None = None
    n: int | None = None


class WithinShare(Entry):
    """Share of the points within a distance of their true position."""

    horizontal: float | None = None
    d3: float | None = Field(None, alias="3d")


class TruthErrors(Entry):
    """Registered street points vs truth/street_points.npy, every point."""

    error_3d: ErrorStats | None = None
    horizontal: ErrorStats | None = None
    within_m: dict[str, WithinShare] | None = None  # by distance: "0.5", "1", "2"
    histogram: Histogram | None = None  # of the 3D errors


class MatchScores(Entry):
    """Street → over-view segment matches against the true buildings (evaluate.chamfer says how)."""

    precision: float | None = None
    recall: float | None = None
    precision_iou: float | None = None
    recall_iou: float | None = None
    n_street_segments: int | None = None
    n_matched: int | None = None
    n_correct: int | None = None
    n_with_counterpart: int | None = None
    n_overview_segments: int | None = None
    n_overview_with_building: int | None = None


class CameraErrors(Entry):
    """Camera centres vs truth/cameras.txt, matched by image name."""

    n: int | None = None
    n_missing: int | None = None
    error_3d: ErrorStats | None = None
    horizontal: ErrorStats | None = None


class CameraScores(Entry):
    source: str | None = None  # "adjusted" | "registered": the poses the centre_error_* describe
    centre_error_mean_m: float | None = None
    centre_error_median_m: float | None = None
    centre_error_p95_m: float | None = None
    centre_error_horizontal_median_m: float | None = None
    registered: CameraErrors | None = None
    adjusted: CameraErrors | None = None  # after the adjust step, when the recipe has one


class SegmentRow(Entry):
    """One street segment; a field is null when unknown (``correct``: null when unmatched)."""

    index: int | None = None
    id: int | None = None
    n_points: int | None = None
    overview_match: int | None = None
    overview_id: int | None = None
    match_cost: float | None = None
    match_confidence: float | None = None
    refine_valid: bool | None = None
    refine_cost: float | None = None
    true_building: int | None = None
    matched_building: int | None = None
    correct: bool | None = None
    error_mean_m: float | None = None
    error_median_m: float | None = None


# --- the runner's entries --------------------------------------------------------------------------
class Coverage(Entry):
    """How much of the street cloud its own segment's transform registered (no truth needed)."""

    n_street_segments: int | None = None
    n_matched: int | None = None
    n_registered: int | None = None
    registered_share: float | None = None
    points_on_registered_segments_share: float | None = None
    points_without_carrier_share: float | None = None


class StreetScaleEntry(Entry):
    """The street frame's units per metre and where it came from (``toolkit.street_scale``)."""

    value: float | None = None
    source: str | None = None  # "gps" | "matching" | "assumed" | "scene" | "recipe"
    gps_estimate: float | None = None
    gps_pairs: int | None = None
    matching_estimate: float | None = None
    matching: dict[str, Any] | None = None  # the scan's figures (toolkit.street_scale.scale_from_matching)


class TryEntry(Entry):
    """One registration of a run that ran again at another street scale: the scale, where it came from, verdict."""

    street_scale: float | None = None
    scale_from: str | None = None  # "run" | "first guess"
    status: str | None = None
    confidence: float | None = None
    reason: str | None = None


class StreetCloudEntry(Entry):
    """How much of the street cloud the run analysed (``toolkit.stream``)."""

    points: int | None = None           # points of the input street cloud, every one in the registered clouds
    analysis_step: int | None = None    # the analysis took one point in this many (1: every point)
    analysis_points: int | None = None


class SegmentScale(Entry):
    """5th, 50th and 95th percentile of the valid segment transforms' scales."""

    p5: float | None = None
    median: float | None = None
    p95: float | None = None


class RunMetrics(Entry):
    """metrics.json, field by field in the order the file has them."""

    # the self-assessment first: it is what a user without truth reads
    status: str | None = None  # "ok" | "unreliable"
    confidence: float | None = None
    reasons: list[str] | None = None
    # the truth-free figures by name, as toolkit.status measures and rounds them (prior_<key> ones
    # vary with the unary stage's prior)
    assessment: dict[str, Any] | None = None
    status_rule: dict[str, Any] | None = None  # StatusRule.to_dict(): StatusRule.from_dict re-judges offline
    # the evaluation (evaluate.chamfer)
    schema_id: str | None = Field(None, alias="schema")  # "crossview.metrics/1"
    cutoff_m: float | None = None  # mutually nearest pairs farther than this are ignored (paper: 10 m)
    street: StreetCount | None = None
    reference: ReferenceCloud | None = None
    chamfer: Chamfer | None = None  # null without a reference cloud
    truth: TruthErrors | None = None
    matching: MatchScores | None = None
    cameras: CameraScores | None = None
    segments: list[SegmentRow] | None = None
    notes: list[str] | None = None  # what the evaluation skipped and why
    # the runner's (toolkit.outputs)
    coverage: Coverage | None = None  # absent without street segments, or without matches and transforms
    crs: str | None = None
    street_scale: StreetScaleEntry | None = None
    tries: list[TryEntry] | None = None  # absent unless an unreliable run ran again at another scale (toolkit.runner)
    street_cloud: StreetCloudEntry | None = None  # absent without a street cloud
    heights: str | None = None  # "absolute" | "relative" (docs/scale_and_heights.md)
    segment_scale: SegmentScale | None = None  # absent without transforms, null without a valid one
    warnings: list[str] | None = None
    input_notes: list[str] | None = None  # what the readers noted
    timings_s: dict[str, float] | None = None  # older runs only: timings are in timings.json

    @classmethod
    def checked(cls, entries: Mapping[str, Any]) -> RunMetrics:
        """The model of the JSON-able ``entries`` a run writes. Strict: a value of another type
        than declared (a float for an int, a bool for a number, a string) fails instead of being
        converted, so the file keeps the values its writers give. Pydantic still widens an int
        given for a float (1 → 1.0); the writers give floats there."""
        return cls.model_validate(entries, strict=True)

    @classmethod
    def of(cls, metrics: Metrics | None) -> RunMetrics:
        """The evaluation's entries of a run's ``toolkit.types.Metrics`` (empty without one)."""
        return cls() if metrics is None else cls.model_validate(dict(metrics.values))

    @classmethod
    def load(cls, path: str | Path) -> RunMetrics:
        return cls.model_validate_json(Path(path).read_text())

    def to_json(self) -> dict[str, Any]:
        """metrics.json's content: the keys given, no others, in the file's order."""
        return self.model_dump(by_alias=True, exclude_unset=True)

    def key_figures(self) -> KeyFigures:
        """The figures the summary, batch, compare and the report show."""
        chamfer = self.chamfer or Chamfer()
        c3, c2 = chamfer.d3 or ChamferStats(), chamfer.d2 or ChamferStats()
        truth = self.truth or TruthErrors()
        h, e3 = truth.horizontal or ErrorStats(), truth.error_3d or ErrorStats()
        within_1m = (truth.within_m or {}).get("1") or WithinShare()
        matching, cameras = self.matching or MatchScores(), self.cameras or CameraScores()
        return KeyFigures(
            chamfer_3d_mean_m=c3.mean_m, chamfer_3d_std_m=c3.std_m, chamfer_2d_mean_m=c2.mean_m,
            chamfer_2d_std_m=c2.std_m, paired_fraction=c3.paired_fraction,
            error_h_median_m=h.median_m, error_h_mean_m=h.mean_m, error_3d_median_m=e3.median_m,
            error_3d_mean_m=e3.mean_m, error_3d_p95_m=e3.p95_m, within_1m_h=within_1m.horizontal,
            match_precision=matching.precision, match_recall=matching.recall,
            camera_median_m=cameras.centre_error_median_m)


@dataclass(frozen=True)
class KeyFigures:
    """The evaluation's figures the tables show, None when the metrics do not have them."""

    chamfer_3d_mean_m: float | None = None
    chamfer_3d_std_m: float | None = None
    chamfer_2d_mean_m: float | None = None
    chamfer_2d_std_m: float | None = None
    paired_fraction: float | None = None  # of the 3D Chamfer pairs
    error_h_median_m: float | None = None  # per-point error vs truth, horizontal
    error_h_mean_m: float | None = None
    error_3d_median_m: float | None = None
    error_3d_mean_m: float | None = None
    error_3d_p95_m: float | None = None
    within_1m_h: float | None = None  # share of the points within 1 m horizontally
    match_precision: float | None = None
    match_recall: float | None = None
    camera_median_m: float | None = None  # camera centre error vs truth, median
