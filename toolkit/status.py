"""Self-assessment of a run without truth: figures a user can compute, and a rule that judges them.

``assess(outputs)`` measures truth-free figures from the run's outputs (nothing under
``truth/`` is read, nor the truth fields of ``Metrics``) and judges them with a ``StatusRule``:
status ``ok`` or ``unreliable``, a confidence in [0, 1] and one-line reasons, most important first.
The figures are rounded (``FIGURE_DIGITS``) before they are judged and are written to metrics.json
as ``assessment``, so ``StatusRule(...).judge(metrics["assessment"])`` re-scores a finished run
offline exactly as the run did. See docs/status.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Iterator, Mapping

import numpy as np

from toolkit.capture import StreetCapture
from toolkit.errors import CrossviewError
from toolkit.io.gps import DEFAULT_SIGMA_M
from toolkit.refine.transforms import apply_each, scale_of
from toolkit.street_scale import camera_height
from toolkit.types import (
    AdjustedCameras,
    ConjugateGraphs,
    DataCosts,
    Matches,
    OverviewSegments,
    Registration,
    RunOutputs,
    SegmentTransforms,
    StreetSegments,
)

FIGURE_DIGITS = 4
OK, UNRELIABLE = "ok", "unreliable"
EXIT_UNRELIABLE = 4  # ``crossview run``: finished, every output written, but the assessment says unreliable


# --- the rule -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Ramp:
    """A per-figure score: 1 at ``good`` (and beyond), 0 at ``bad`` (and beyond), smoothstep between."""

    good: float
    bad: float

    def score(self, value: float) -> float:
        t = min(max((value - self.bad) / (self.good - self.bad), 0.0), 1.0)
        return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True)
class StatusRule:
    """Thresholds that map the figures to status, confidence and reasons (chosen in docs/status.md).

    Confidence is the product of the per-figure scores (``Ramp``s; an absent figure scores 1).
    A run is unreliable when confidence < ``min_confidence`` or any hard limit below is crossed.
    A ramp with a hard limit is centred on it (score 0.5 there), so one figure alone turns a run
    unreliable where its limit says, and several half-bad figures together do too.
    """

    min_confidence: float = 0.55  # chosen leave-one-city-out (bench/status_calibration.py)
    # hard limits
    min_registered_point_share: float = 0.5
    min_facade_support_share: float = 0.4
    max_facade_distance_median_m: float = 1.2
    max_neighbour_disagree_share: float = 0.4
    max_neighbour_gap_median_m: float = 1.5     # drift parts neighbouring transforms by decimetres, not metres
    max_outside_grid_share: float = 0.5
    max_segment_scale_deviation: float = 0.035   # |median segment scale − 1|: drift of ±3 % moves it ≤ 1.5 %
    max_route_links_broken: int = 0     # route placement (no GPS): neighbouring windows placed apart
    # route placement without GPS: windows whose own best placement is elsewhere than the chain's
    # (one window in three is, on accurate short routes); chosen leave-one-city-out
    max_route_overruled_share: float = 0.35
    # the warp bridges route gaps of 100 m or more between cameras that see a registered façade
    # (warp.inverse_log bridge_min_gap_m); a camera inside such a gap is up to half of it from the nearest
    # one, and there the registration rests on the trajectory's own drift
    max_camera_gap_p90_m: float = 50.0
    min_camera_height_m: float = 0.8    # street capture: handheld ~1.5 m, car roof ~2.5 m, mast ~4 m
    max_camera_height_m: float = 6.0
    gps_sigma_factor: float = 3.0       # GPS tolerance = max(gps_sigma_factor · σ, gps_min_tolerance_m)
    gps_min_tolerance_m: float = 15.0
    # confidence ramps
    registered_point_share: Ramp = Ramp(good=0.6, bad=0.0)
    # the matching figures describe the process (refine rejects and re-places wrong matches): gentle
    matched_share: Ramp = Ramp(good=0.4, bad=0.0)
    match_confidence_mean: Ramp = Ramp(good=0.4, bad=0.0)
    facade_support_share: Ramp = Ramp(good=0.6, bad=0.0)
    facade_distance_median_m: Ramp = Ramp(good=0.6, bad=1.8)
    neighbour_disagree_share: Ramp = Ramp(good=0.1, bad=0.9)
    outside_grid_share: Ramp = Ramp(good=0.1, bad=0.9)
    camera_spread_p95_m: Ramp = Ramp(good=3.0, bad=30.0)
    ba_rms_after_px: Ramp = Ramp(good=2.0, bad=10.0)
    gps_residual_ratio: Ramp = Ramp(good=0.5, bad=1.5)  # median GPS residual / GPS tolerance
    bp_unconverged_score: float = 0.8   # the score of a matching that did not converge

    def gps_tolerance_m(self, figures: Mapping[str, Any]) -> float | None:
        sigma = figures.get("gps_sigma_m")
        return None if sigma is None else max(self.gps_sigma_factor * float(sigma), self.gps_min_tolerance_m)

    def scores(self, figures: Mapping[str, Any]) -> dict[str, float]:
        """Score in [0, 1] of every figure the rule uses and the run has."""
        out: dict[str, float] = {}
        for name in SCORED:
            value = _gps_ratio(self, figures) if name == "gps_residual_ratio" else figures.get(name)
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                out[name] = getattr(self, name).score(float(value))
        if figures.get("bp_converged") is False:
            out["bp_converged"] = self.bp_unconverged_score
        return out

    def judge(self, figures: Mapping[str, Any]) -> Verdict:
        """Status, confidence and reasons from the figures alone (e.g. metrics.json's ``assessment``)."""
        scores = self.scores(figures)
        confidence = round(float(np.prod(list(scores.values()))) if scores else 1.0, FIGURE_DIGITS)
        fired = {name: r for name, check in HARD_CHECKS.items() if (r := check(self, figures)) is not None}
        hard = list(fired.values())
        soft = [SOFT_REASONS[n](self, figures) for n, s in sorted(scores.items(), key=lambda kv: kv[1])
                if s < 1.0 and n not in fired]
        reasons = list(hard)
        if confidence < self.min_confidence:
            weakest = f": weakest, {soft[0]}" if soft else ""
            reasons.append(f"confidence {confidence:.2f} below {self.min_confidence:g}{weakest}")
            soft = soft[1:]
        reasons += soft
        if figures.get("registered_share") is None and figures.get("facade_support_share") is None:
            reasons.append("not assessed: the recipe registers nothing (no refine or warp step)")
        status = UNRELIABLE if hard or confidence < self.min_confidence else OK
        return Verdict(status, confidence, tuple(reasons))

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> StatusRule:
        """The inverse of ``to_dict`` (ramps as {good, bad}); missing keys keep their defaults."""
        kw = {k: Ramp(**v) if isinstance(v, Mapping) else v for k, v in values.items()}
        return cls(**kw)


@dataclass(frozen=True)
class Verdict:
    """What ``StatusRule.judge`` says; unpacks as (status, confidence, reasons)."""

    status: str
    confidence: float
    reasons: tuple[str, ...]

    def __iter__(self) -> Iterator[Any]:
        return iter((self.status, self.confidence, self.reasons))


SCORED = ("registered_point_share", "matched_share", "match_confidence_mean", "facade_support_share",
          "facade_distance_median_m",
          "neighbour_disagree_share", "outside_grid_share", "camera_spread_p95_m", "ba_rms_after_px",
          "gps_residual_ratio")


def _gps_ratio(rule: StatusRule, f: Mapping[str, Any]) -> float | None:
    tol, res = rule.gps_tolerance_m(f), f.get("gps_residual_median_m")
    return None if tol is None or res is None else float(res) / tol


def _hard_gps(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    tol, res = rule.gps_tolerance_m(f), f.get("gps_residual_median_m")
    if tol is None or res is None or res <= tol:
        return None
    return f"camera centres lie {res:.0f} m from their GPS fixes (median; tolerance {tol:.0f} m)"


def _hard_facades(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    s = f.get("facade_support_share")
    if s is None or s >= rule.min_facade_support_share:
        return None
    return (f"only {s:.0%} of the façade points lie within {f.get('facade_radius_m', 0):g} m of an over-view "
            f"outline (at least {rule.min_facade_support_share:.0%} expected): façades are off the buildings")


def _hard_facade_distance(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    d = f.get("facade_distance_median_m")
    if d is None or d <= rule.max_facade_distance_median_m:
        return None
    return (f"the registered façades lie {d:.1f} m from the over-view outlines (median; at most "
            f"{rule.max_facade_distance_median_m:g} m expected): the registration is off by metres")


def _hard_outside(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    s = f.get("outside_grid_share")
    if s is None or s <= rule.max_outside_grid_share:
        return None
    return f"{s:.0%} of the registered points fall outside the over-view data"


def _hard_neighbours(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    s = f.get("neighbour_disagree_share")
    if s is None or s <= rule.max_neighbour_disagree_share:
        return None
    return (f"{s:.0%} of neighbouring segments are placed more than {f.get('neighbour_tol_m', 0):g} m apart "
            f"by their own transforms (median {f.get('neighbour_gap_median_m') or 0:.1f} m): wrong matches")


def _hard_neighbour_gap(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    g = f.get("neighbour_gap_median_m")
    if g is None or g <= rule.max_neighbour_gap_median_m:
        return None
    return (f"neighbouring segments' own transforms place each other {g:.1f} m apart (median; at most "
            f"{rule.max_neighbour_gap_median_m:g} m expected): the registration is uncertain by metres")


def _hard_route_chain(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    n = f.get("prior_links_broken")
    if n is None or n <= rule.max_route_links_broken:
        return None
    return (f"the route placement puts {n} of its {f.get('prior_links')} pairs of neighbouring windows apart (by up to "
            f"{f.get('prior_link_max_m') or 0:.0f} m): part of the route may be matched to the wrong buildings")


def _hard_route_overruled(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    s = f.get("prior_overruled_share")
    # GPS fixes may rightly overrule a window; a placement the run did not use did not place anything
    if s is None or s <= rule.max_route_overruled_share or f.get("gps_fixes") or f.get("prior_used") is False:
        return None
    return (f"in {s:.0%} of the route placement's windows the façades alone fit best elsewhere (up to "
            f"{f.get('prior_alone_max_m') or 0:.0f} m away) than the placement chosen with their neighbours "
            f"(at most {rule.max_route_overruled_share:.0%} expected): the route may be matched ambiguously")


def _hard_segment_scale(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    m = f.get("segment_scale_median")
    if m is None or abs(m - 1.0) <= rule.max_segment_scale_deviation:
        return None
    return (f"the registered segments need a median scale of {m:.3f} (at most {rule.max_segment_scale_deviation:.1%}"
            f" from 1 expected): the matches squeeze or stretch the street frame (wrong matches or street scale)")


def _hard_camera_height(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    h = f.get("camera_height_median_m")
    if h is None or rule.min_camera_height_m <= h <= rule.max_camera_height_m:
        return None
    return (f"the cameras sit {h:.1f} m above the street ground (median; {rule.min_camera_height_m:g}-"
            f"{rule.max_camera_height_m:g} m expected): the street scale is likely wrong (set street_scale, or "
            f"give street/gps.csv)")


def _hard_camera_gap(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    g = f.get("camera_gap_p90_m")
    if g is None or g <= rule.max_camera_gap_p90_m:
        return None
    return (f"a tenth of the cameras are {g:.0f} m or more along the route from one that sees a registered façade "
            f"(at most {rule.max_camera_gap_p90_m:g} m expected): there the registration follows the trajectory's "
            f"own drift")


def _hard_registered(rule: StatusRule, f: Mapping[str, Any]) -> str | None:
    s = f.get("registered_point_share")
    if s is None or s >= rule.min_registered_point_share:
        return None
    return (f"only {s:.0%} of the street points are on segments registered by their own transform "
            f"(at least {rule.min_registered_point_share:.0%} expected)")


# figure → its hard limit, most important first: GPS is direct evidence, façades off every outline nearly so
HARD_CHECKS = {"gps_residual_ratio": _hard_gps, "facade_support_share": _hard_facades,
               "facade_distance_median_m": _hard_facade_distance,
               "outside_grid_share": _hard_outside, "neighbour_disagree_share": _hard_neighbours,
               "neighbour_gap_median_m": _hard_neighbour_gap,
               "prior_links_broken": _hard_route_chain, "prior_overruled_share": _hard_route_overruled,
               "camera_height_median_m": _hard_camera_height, "registered_point_share": _hard_registered,
               "segment_scale_median": _hard_segment_scale, "camera_gap_p90_m": _hard_camera_gap}

SOFT_REASONS = {
    "registered_point_share": lambda r, f: f"{f['registered_point_share']:.0%} of the street points on registered "
                                           "segments",
    "matched_share": lambda r, f: f"{f['matched_share']:.0%} of the street segments matched",
    "match_confidence_mean": lambda r, f: f"mean match vote confidence {f['match_confidence_mean']:.2f}",
    "facade_support_share": lambda r, f: f"{f['facade_support_share']:.0%} of the façade points within "
                                         f"{f.get('facade_radius_m', 0):g} m of an over-view outline",
    "neighbour_disagree_share": lambda r, f: f"{f['neighbour_disagree_share']:.0%} of neighbouring segments placed "
                                             f"more than {f.get('neighbour_tol_m', 0):g} m apart",
    "facade_distance_median_m": lambda r, f: f"registered façades {f['facade_distance_median_m']:.2f} m from the "
                                             "over-view outlines (median)",
    "outside_grid_share": lambda r, f: f"{f['outside_grid_share']:.0%} of the registered points outside the "
                                       "over-view data",
    "camera_spread_p95_m": lambda r, f: f"blended transforms spread {f['camera_spread_p95_m']:.1f} m at the "
                                        "cameras (p95)",
    "ba_rms_after_px": lambda r, f: f"bundle adjustment RMS {f['ba_rms_after_px']:.2f} px",
    "gps_residual_ratio": lambda r, f: f"camera centres {f['gps_residual_median_m']:.1f} m from their GPS fixes "
                                       f"(median; tolerance {r.gps_tolerance_m(f):.0f} m)",
    "bp_converged": lambda r, f: f"matching did not converge ({f.get('bp_iterations')} iterations)",
}


# --- the figures --------------------------------------------------------------------------------
@dataclass(frozen=True)
class AssessParams:
    """How the figures are measured (the rule's thresholds are in ``StatusRule``)."""

    facade_radius_m: float = 1.5         # a façade point within this of an over-view outline is supported
    facade_cap_m: float = 50.0           # façade distances are measured up to this (the median is capped)
    neighbour_tol_m: float = 5.0         # neighbouring transforms farther apart than this disagree
    max_points: int = 200_000            # façade / registered points sampled (evenly, deterministic)


@dataclass(frozen=True)
class Assessment:
    """status "ok" | "unreliable"; confidence in [0, 1]; reasons most important first; figures: every
    truth-free figure measured (None when the run's outputs do not allow it)."""

    status: str
    confidence: float
    reasons: tuple[str, ...]
    figures: Mapping[str, Any] = field(default_factory=dict)
    rule: StatusRule = StatusRule()

    @property
    def reliable(self) -> bool:
        return self.status == OK

    @property
    def main_reason(self) -> str:
        return self.reasons[0] if self.reasons else "no reason given"

    def to_json(self) -> dict[str, Any]:
        """metrics.json's leading entries."""
        return {"status": self.status, "confidence": self.confidence, "reasons": list(self.reasons),
                "assessment": dict(self.figures), "status_rule": self.rule.to_dict()}


def assess(outputs: RunOutputs, rule: StatusRule | None = None, params: AssessParams | None = None) -> Assessment:
    """Measure the truth-free figures of a run's outputs and judge them."""
    rule, params = rule or StatusRule(), params or AssessParams()
    figures = measure(outputs, params)
    status, confidence, reasons = rule.judge(figures)
    return Assessment(status, confidence, reasons, figures, rule)


def measure(outputs: RunOutputs, params: AssessParams | None = None) -> dict[str, Any]:
    """Every figure, rounded to ``FIGURE_DIGITS`` (None where the outputs do not allow it)."""
    params = params or AssessParams()
    street, overview, matches = outputs.street, outputs.overview, outputs.matches
    transforms, registration, cameras = outputs.transforms, outputs.registration, outputs.cameras
    figures: dict[str, Any] = {}
    figures.update(registered_share(street, transforms))
    figures["segment_scale_median"] = segment_scale_median(transforms)
    figures.update(matching_figures(matches))
    figures.update(prior_figures(outputs.costs))
    figures.update(neighbour_agreement(outputs.graphs, street, transforms, params.neighbour_tol_m))
    figures.update(facade_support(registration, street, overview, params.facade_radius_m, params.max_points,
                                  params.facade_cap_m))
    figures["outside_grid_share"] = outside_grid_share(registration, overview, params.max_points)
    figures.update(camera_spread(registration))
    figures["bridged_camera_share"] = bridged_camera_share(registration)
    figures["camera_gap_p90_m"] = camera_gap_p90_m(registration)
    figures["camera_height_median_m"] = camera_height_m(registration, street, params.max_points)
    if figures["camera_height_median_m"] is None and registration is None and street is not None and len(street) \
            and outputs.capture is not None and outputs.capture.sparse_path is not None:
        figures["camera_height_median_m"] = camera_height(street, outputs.capture)  # nothing registered
    figures.update(bundle_adjustment(cameras))
    figures.update(gps_residuals(outputs.capture, registration, cameras))
    return {k: _round(v) for k, v in figures.items()}


def registered_share(street: StreetSegments | None, transforms: SegmentTransforms | None) -> dict[str, Any]:
    """Share of street segments valid after refine, and of street points carried by one."""
    out = {"n_street_segments": None if street is None else len(street), "registered_share": None,
           "registered_point_share": None}
    if street is None or transforms is None:
        return out
    valid = np.asarray(transforms.valid, bool)
    carrier = np.asarray(street.carrier)
    on_valid = np.zeros(len(carrier), bool)
    on_valid[carrier >= 0] = valid[carrier[carrier >= 0]]
    out["registered_share"] = float(valid.mean()) if len(valid) else 0.0
    out["registered_point_share"] = float(on_valid.mean()) if len(on_valid) else 0.0
    return out


def segment_scale_median(transforms: SegmentTransforms | None) -> float | None:
    """Median scale (cube root of the determinant) of the valid segment transforms."""
    if transforms is None or not np.asarray(transforms.valid, bool).any():
        return None
    T = np.asarray(transforms.T, np.float64)[np.asarray(transforms.valid, bool)]
    return float(np.median(scale_of(T[:, :3, :3])))


def matching_figures(matches: Matches | None) -> dict[str, Any]:
    """Solver convergence, share of street segments matched and their mean vote confidence."""
    if matches is None:
        return {"bp_converged": None, "bp_iterations": None, "matched_share": None, "match_confidence_mean": None}
    matched = np.asarray(matches.segment_match) >= 0
    conf = np.asarray(matches.confidence, np.float64)[matched]
    return {"bp_converged": bool(matches.converged), "bp_iterations": int(matches.iterations),
            "matched_share": float(matched.mean()) if len(matched) else 0.0,
            "match_confidence_mean": float(conf.mean()) if len(conf) else None}


def prior_figures(costs: DataCosts | None) -> dict[str, Any]:
    """The unary stage's own truth-free figures of the prior it pruned candidates with (DataCosts.prior,
    prior_figures), scalars flattened as ``prior_<key>``; the rule judges ``prior_links_broken``."""
    out: dict[str, Any] = {"prior": getattr(costs, "prior", None)}
    for key, value in _flat(getattr(costs, "prior_figures", None) or {}):
        out[f"prior_{key}"] = value
    return out


def _flat(values: Mapping[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    for key, value in values.items():
        if isinstance(value, Mapping):
            yield from _flat(value, f"{prefix}{key}_")
        elif value is None or isinstance(value, (bool, int, float, str, np.bool_, np.integer, np.floating)):
            yield f"{prefix}{key}", value


def neighbour_agreement(graphs: ConjugateGraphs | None, street: StreetSegments | None,
                        transforms: SegmentTransforms | None, tol_m: float) -> dict[str, Any]:
    """Where the transforms of two valid street-graph neighbours put the midpoint of their centroids.

    Drift makes neighbours differ by decimetres to a metre or two; a wrong match by tens of metres.
    """
    out: dict[str, Any] = {"neighbour_tol_m": tol_m, "neighbour_pairs": None, "neighbour_gap_median_m": None,
                           "neighbour_gap_p90_m": None, "neighbour_disagree_share": None}
    if graphs is None or street is None or transforms is None:
        return out
    edges = np.asarray(graphs.street_edges, np.int64).reshape(-1, 2)
    valid = np.asarray(transforms.valid, bool)
    edges = edges[valid[edges[:, 0]] & valid[edges[:, 1]]] if len(edges) else edges
    out["neighbour_pairs"] = len(edges)
    if not len(edges):
        return out
    i, j = edges[:, 0], edges[:, 1]
    ground = np.nan_to_num(np.asarray(street.ground_z, np.float64), nan=0.0)
    mid = np.column_stack([(street.centroids[i] + street.centroids[j]) / 2, (ground[i] + ground[j]) / 2])
    mid_input = mid @ street.up_rotation + street.origin  # levelled → input street frame
    T = np.asarray(transforms.T, np.float64)
    gap = np.linalg.norm(apply_each(T[i], mid_input) - apply_each(T[j], mid_input), axis=1)
    out.update(neighbour_gap_median_m=float(np.median(gap)), neighbour_gap_p90_m=float(np.percentile(gap, 90)),
               neighbour_disagree_share=float((gap > tol_m).mean()))
    return out


def facade_support(registration: Registration | None, street: StreetSegments | None,
                   overview: OverviewSegments | None, radius_m: float, max_points: int,
                   cap_m: float) -> dict[str, Any]:
    """Share of every street segment's registered façade points within ``radius_m`` of an over-view
    outline, and their median distance to one (capped at ``cap_m``).

    Registered or not, a segment's façade is taken where the output put it (Registration.points),
    so the warp's placement of unregistered segments is judged too.
    """
    out: dict[str, Any] = {"facade_radius_m": radius_m, "facade_points": None, "facade_support_share": None,
                           "facade_distance_median_m": None}
    if registration is None or street is None or overview is None:
        return out
    facade = _even_sample(np.flatnonzero(np.asarray(street.point_labels) >= 0), max_points)
    out["facade_points"] = len(facade)
    if not len(facade):
        return out
    dist = outline_distance_m(overview, registration.points[facade, :2], cap_m)
    out["facade_support_share"] = float((dist <= radius_m).mean())
    out["facade_distance_median_m"] = float(np.median(dist))
    return out


def outline_distance_m(overview: OverviewSegments, xy: np.ndarray, cap_m: float) -> np.ndarray:
    """(N,) distance of each world x, y to the nearest over-view outline pixel centre, capped at ``cap_m``."""
    from scipy.spatial import cKDTree

    boundary = [np.asarray(b).reshape(-1, 2) for b in overview.boundary_px]
    rc = np.concatenate(boundary) if boundary else np.zeros((0, 2), np.int64)
    if not len(rc):
        return np.full(len(xy), cap_m)
    outline = overview.grid.pixel_to_world(rc[:, 0], rc[:, 1])
    origin = outline.min(axis=0)  # local origin: eastings/northings are large
    dist, _ = cKDTree(outline - origin).query(xy - origin, k=1, distance_upper_bound=cap_m)
    return np.minimum(dist, cap_m)


def outside_grid_share(registration: Registration | None, overview: OverviewSegments | None,
                       max_points: int) -> float | None:
    """Share of registered points whose x, y fall outside the over-view grid."""
    if registration is None or overview is None or not len(registration.points):
        return None
    sample = _even_sample(np.arange(len(registration.points)), max_points)
    rc = np.rint(overview.grid.world_to_pixel(registration.points[sample, :2]))
    grid = overview.grid
    inside = (rc[:, 0] >= 0) & (rc[:, 0] < grid.height) & (rc[:, 1] >= 0) & (rc[:, 1] < grid.width)
    return float(1.0 - inside.mean())


def bridged_camera_share(registration: Registration | None) -> float | None:
    """Share of the cameras placed by following the street trajectory across a route gap
    (Registration.camera_bridged); None when no bridge ran."""
    bridged = None if registration is None else registration.camera_bridged
    return None if bridged is None or len(bridged) == 0 else float(np.mean(bridged))


def camera_gap_p90_m(registration: Registration | None) -> float | None:
    """90th percentile over the cameras of the route distance to the nearest camera that sees a
    registered façade (Registration.camera_gap_m): beyond it the registration rests on the
    trajectory's own drift. None when no bridge ran or more than 10 % of the cameras have none."""
    gap = None if registration is None else registration.camera_gap_m
    if gap is None or len(gap) == 0:
        return None
    p90 = float(np.percentile(gap, 90))
    return p90 if np.isfinite(p90) else None


def camera_spread(registration: Registration | None) -> dict[str, Any]:
    """Spread of the segment transforms blended at each camera (Registration.camera_spread_m)."""
    spread = None if registration is None or registration.camera_spread_m is None else \
        np.asarray(registration.camera_spread_m, np.float64)
    if spread is None or not len(spread):
        return {"camera_spread_median_m": None, "camera_spread_p95_m": None}
    return {"camera_spread_median_m": float(np.median(spread)), "camera_spread_p95_m": float(np.percentile(spread, 95))}


def camera_height_m(registration: Registration | None, street: StreetSegments | None, max_points: int,
                    radius_m: float = 5.0) -> float | None:
    """Median height of the registered cameras above the registered street ground points within
    ``radius_m`` of them horizontally (None without cameras or ground under them)."""
    if registration is None or street is None or not len(registration.image_names):
        return None
    ground = np.flatnonzero(np.asarray(street.point_labels) == -1)
    if len(ground) == 0 or len(registration.points) != len(street.point_labels):
        return None
    from scipy.spatial import cKDTree

    g = np.asarray(registration.points)[_even_sample(ground, max_points)]
    centres = _output_cameras(registration, None)[1]
    near = cKDTree(g[:, :2]).query_ball_point(centres[:, :2], radius_m)
    heights = [c[2] - np.median(g[idx, 2]) for c, idx in zip(centres, near) if len(idx) >= 5]
    return float(np.median(heights)) if heights else None


def bundle_adjustment(cameras: AdjustedCameras | None) -> dict[str, Any]:
    if cameras is None:
        return {"ba_rms_before_px": None, "ba_rms_after_px": None, "ba_iterations": None}
    return {"ba_rms_before_px": float(cameras.rms_before_px), "ba_rms_after_px": float(cameras.rms_after_px),
            "ba_iterations": int(cameras.iterations)}


def gps_residuals(capture: StreetCapture | None, registration: Registration | None,
                  cameras: AdjustedCameras | None) -> dict[str, Any]:
    """Horizontal distance of the output camera centres (adjusted, else registered) from street/gps.csv."""
    out: dict[str, Any] = {"gps_fixes": None, "gps_sigma_m": None, "gps_residual_median_m": None,
                           "gps_residual_p90_m": None}
    names, centres = _output_cameras(registration, cameras)
    if capture is None or capture.gps_path is None or not len(names):
        return out
    try:
        gps = capture.gps
        fix_names, sigma = list(gps.names), gps.sigma_m
        fixes = gps.scene_xy(capture.scene.crs)
    except CrossviewError:
        return out  # a figure, not a step: an unreadable optional file must not fail the run
    index = {n: k for k, n in enumerate(names)}
    hit = np.array([n in index for n in fix_names], bool)
    out["gps_fixes"] = int(hit.sum())
    if not hit.any():
        return out
    cam = centres[[index[n] for n, h in zip(fix_names, hit) if h], :2]
    res = np.linalg.norm(cam - fixes[hit], axis=1)
    sig = sigma[hit]
    sig = sig[np.isfinite(sig) & (sig > 0)]
    out.update(gps_sigma_m=float(np.median(sig)) if len(sig) else DEFAULT_SIGMA_M,
               gps_residual_median_m=float(np.median(res)), gps_residual_p90_m=float(np.percentile(res, 90)))
    return out




# --- helpers ------------------------------------------------------------------------------------
def _even_sample(index: np.ndarray, max_points: int) -> np.ndarray:
    """At most ``max_points`` entries of ``index``, evenly spaced (deterministic)."""
    if len(index) <= max_points:
        return index
    return index[np.linspace(0, len(index) - 1, max_points).astype(np.int64)]


def _output_cameras(registration: Registration | None, cameras: AdjustedCameras | None):
    if cameras is not None:
        return cameras.model.image_names, cameras.model.centres
    if registration is not None and len(registration.image_names):
        return registration.image_names, -np.einsum("cji,cj->ci", registration.R, registration.t)
    return (), np.zeros((0, 3))


def _round(v: Any) -> Any:
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        f = float(v)
        return round(f, FIGURE_DIGITS) if np.isfinite(f) else None
    return v


def verdict_line(assessment: Assessment | None) -> str | None:
    """The last line ``crossview run`` prints for an unreliable run (None when reliable)."""
    if assessment is None or assessment.reliable:
        return None
    return f"registration unreliable: {assessment.main_reason}"
