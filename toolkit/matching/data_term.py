"""The steps of the data term D (paper §3.3.1) around its pose search: the prior it prunes with,
the free-space probes, and the costs a search's poses give.

Prior: street/gps.csv fixes (``toolkit.matching.gps``), else, with street/sparse, the route placed
by its façades (``toolkit.matching.route_prior``), else none (every over-view pair is searched).
The final pose must put both centres within their radii and turn within angle_deg of the prior's
local fit; ``cost_weight`` adds a soft penalty growing with the distance from the prior positions.

Free space (with street/sparse): a façade's coarse points moved ``probe_offset_m`` towards the side
its cameras saw it from; a pose putting them inside the candidate building costs ``weight``, which
tells a façade from the building's back wall.

Costs: the best pose is folded into T̂ = (θ, t); costs are rescaled by ``raw_cost_at_null`` and
clipped to [0, 1]; D(null) = 1; pruned candidates are +inf (θ, t NaN).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.matching import anchors as AN
from toolkit.matching import chamfer as CH
from toolkit.matching.candidates import Candidates, PairGeometry
from toolkit.matching.config import MatchingConfig
from toolkit.matching.pose_search import PriorTerm
from toolkit.matching.gps import (
    GpsConfig,
    GpsPrior,
    PruningPrior,
    gps_predict,
    gps_prior,
    prior_penalty,
    prior_radii,
)
from toolkit.matching.mrf import wrap_angle
from toolkit.matching.pose_search import Scored, StreetSamples
from toolkit.matching.route_prior import GpsTrack, RoutePlacement, RoutePriorConfig, capture_order, place_route
from toolkit.observe import DebugPoints2D, DebugText
from toolkit.types import DataCosts, OverviewSegments, SparseModel, StreetSegments


class FreeSpaceConfig(MatchingConfig):
    """With street/sparse: the free-space term that tells a façade's front from its back wall."""

    flat_names = {"weight": "free_space_weight"}

    weight: float = Field(0.5, ge=0, le=1, description="weight of the free-space term in the pose cost (0: chamfer only)")
    probe_offset_m: float = Field(2.0, gt=0, description="distance of the free-space probes from the façade (m)")

    def used_with(self, capture: StreetCapture | None) -> bool:
        return self.weight > 0 and capture is not None and capture.sparse_path is not None


def null_costs(n_edges: int, n_labels: int) -> DataCosts:
    """D(null) = 1, every other candidate pruned (+inf, θ and t NaN)."""
    cost = np.full((n_edges, n_labels), np.inf)
    cost[:, n_labels - 1] = 1.0
    return DataCosts(cost, np.full((n_edges, n_labels - 1), np.nan), np.full((n_edges, n_labels - 1, 2), np.nan))


def choose_prior(capture: StreetCapture | None, street: StreetSegments, overview: OverviewSegments, gps: GpsConfig,
                 route: RoutePriorConfig, obs) -> PruningPrior:
    """GPS fixes, else the route placed by its façades (``route.enabled``, street/sparse), else none.
    With both (``route.with_gps``), the placement runs near the fixes' track and each segment it puts
    near its GPS position, tighter than the fixes, takes its prior (``gated_prior``)."""
    prior, source, figures = None, None, None
    has_sparse = capture is not None and capture.sparse_path is not None
    if capture is not None and capture.gps_path is not None:
        prior = gps_prior(capture, street, n_local=gps.fit_fixes, warn=obs.warn)
        source = "gps" if prior is not None else None
    if prior is not None and route.enabled and route.with_gps and has_sparse and _may_tighten(prior, route, gps):
        track = gps_track(capture, street, gps)
        placed = place_route_by_facades(street, overview, capture.sparse, route, obs, track)
        return gated_prior(prior, placed, len(street.centroids), gps, route.gps_agree_sigmas * track.tolerance_m)
    if prior is None and route.enabled and has_sparse:
        placed = place_route_by_facades(street, overview, capture.sparse, route, obs)
        prior, figures = placed.prior, placed.figures()
        source = "route_placement" if prior is not None else None
    radius = prior_radii(prior, len(street.centroids), gps) if prior is not None else None
    return PruningPrior(prior, radius, source, figures)


def _may_tighten(fixes: GpsPrior, route: RoutePriorConfig, gps: GpsConfig) -> bool:
    """Whether any segment's GPS radius exceeds the least radius a placement can have (its σ alone):
    if none does, ``gated_prior`` would keep every GPS prior and the placement need not run."""
    if gps.radius_m is not None:
        return False
    floor = gps.radius_sigmas * route.sigma_m + gps.radius_margin_m
    return bool(np.any(prior_radii(fixes, len(fixes.position), gps) > floor))


def gps_track(capture: StreetCapture, street: StreetSegments, gps: GpsConfig) -> GpsTrack:
    """Where the fixes put each COLMAP camera (capture order), and how far they may be trusted."""
    model = capture.sparse
    fit = gps_predict(capture, street, street.level(model.centres[capture_order(model.image_names)])[:, :2],
                      n_local=gps.fit_fixes)
    return GpsTrack(fit.position, max(fit.sigma_m, float(np.median(fit.fit_rms_m))))


def gated_prior(fixes: GpsPrior, placed: RoutePlacement, n_seg: int, cfg: GpsConfig,
                agree_m: float) -> PruningPrior:
    """The GPS prior, where the route placement agrees with it and is the tighter the placement's: a
    segment whose placed centre lies within ``agree_m`` of its GPS position, and whose placement
    radius is below its GPS radius, takes the placement's position, heading and radius. The GPS
    keeps the placement from sliding to a look-alike block."""
    radius = prior_radii(fixes, n_seg, cfg)
    if placed.prior is None:
        return PruningPrior(fixes, radius, "gps", {"gated_share": 0.0})
    route = placed.prior
    route_radius = prior_radii(route, n_seg, cfg)
    # where both agree, the tighter of the two (with fixes as good as the placement, the fixes' fit)
    agree = (np.linalg.norm(route.position - fixes.position, axis=1) <= agree_m) & (route_radius < radius)
    figures = {"gated_share": round(float(agree.mean()), 4) if n_seg else 0.0}
    prior = GpsPrior(position=np.where(agree[:, None], route.position, fixes.position),
                     angle=np.where(agree, route.angle, fixes.angle), n_fixes=fixes.n_fixes, sigma_m=fixes.sigma_m,
                     fit_rms_m=fixes.fit_rms_m)
    return PruningPrior(prior, np.where(agree, route_radius, radius), "gps", figures)


def place_route_by_facades(street: StreetSegments, overview: OverviewSegments, model: SparseModel,
                           cfg: RoutePriorConfig, obs, track: GpsTrack | None = None) -> RoutePlacement:
    """The route of the COLMAP cameras placed by its façades (``toolkit.matching.route_prior``), near
    their GPS ``track`` when given; a warning when unused."""
    cams = street.level(model.centres[capture_order(model.image_names)])[:, :2]
    placed = place_route(street, overview, cams, cfg, track=track)
    obs.debug("route_placement", DebugText(placed.describe()))
    if placed.prior is None:
        obs.warn(f"route placement not used ({placed.reason}): every over-view pair is searched")
    return placed


def free_space_probes(model: SparseModel, street: StreetSegments, samples: StreetSamples, geo: PairGeometry,
                      cfg: FreeSpaceConfig, stats: dict) -> CH.SegmentPoints:
    """Each segment's coarse points moved probe_offset_m towards the side the cameras of ``model``
    saw it from."""
    cams = street.level(model.centres)[:, :2]
    outward = AN.observer_sides(cams, samples.walls[0], samples.walls[1])
    known = np.any(outward != 0, axis=1)
    stats["observer_side_known"] = f"{int(known.sum())}/{len(known)}"
    probe_pts = [c + o * cfg.probe_offset_m if ok else c[:0] for c, o, ok in zip(samples.coarse, outward, known)]
    return CH.segment_points(probe_pts, None, geo.s_cent, geo.edges)


def prior_term(cand: Candidates, geo: PairGeometry, prior: PruningPrior, gps: GpsConfig) -> PriorTerm | None:
    """None without a prior, else (pair index (H,), θ (H,), pixel (H,2)) → the prior's soft term of
    each pose (``prior_penalty`` without its exact test, which the final pose takes)."""
    if prior.prior is None:
        return None

    def term(pair: np.ndarray, theta: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        pe = cand.edge[pair]
        t_hat = geo.translation(pe, theta, pixel)
        return prior_penalty(np.zeros(len(pe)), theta, t_hat, geo.s_cent, geo.j[pe], geo.k[pe], prior, gps,
                             exact=False)

    return term


def fill_costs(costs: DataCosts, cand: Candidates, final: Scored, geo: PairGeometry, prior: PruningPrior,
               gps: GpsConfig, raw_cost_at_null: float) -> DataCosts:
    """``costs`` with the candidates' poses T̂ and rescaled costs, after the prior's test on the final pose."""
    pe, pl = cand.edge, cand.label
    theta = final.pairs.theta
    t_hat = geo.translation(pe, theta, final.pairs.pivot_px + final.pairs.offset)
    f_cost = final.cost
    if prior.prior is not None:  # the exact test on the final pose, then the soft prior term
        f_cost = prior_penalty(f_cost, theta, t_hat, geo.s_cent, geo.j[pe], geo.k[pe], prior, gps)
    cost, theta_out, t_out = costs.cost, costs.theta_rad, costs.t
    # pruned stays +inf (np.clip would turn it into 1, a tie with null that greedy then picks)
    cost[pe, pl] = np.where(np.isfinite(f_cost), np.clip(f_cost / raw_cost_at_null, 0.0, 1.0), np.inf)
    kept = np.isfinite(f_cost)  # a pose the prior's test rejected is pruned like any other: NaN
    theta_out[pe[kept], pl[kept]] = wrap_angle(theta[kept])
    t_out[pe[kept], pl[kept]] = t_hat[kept]
    # twins of same-segment labels (label 2f+1 = label 2f when f is a self-loop)
    twin_e, twin_l = cand.twin_edge, cand.twin_label
    cost[twin_e, twin_l] = cost[twin_e, twin_l - 1]
    theta_out[twin_e, twin_l] = theta_out[twin_e, twin_l - 1]
    t_out[twin_e, twin_l] = t_out[twin_e, twin_l - 1]
    return DataCosts(cost, theta_out, t_out, prior.source, prior.figures)


def debug_costs(obs, stats: dict, costs: DataCosts, geo: PairGeometry, fine: list) -> None:
    """The search's figures and every edge's best candidate, placed on the over-view."""
    obs.debug("stats", DebugText("\n".join(f"- {k}: {v}" for k, v in stats.items())))
    cost, theta, t, edges = costs.cost, costs.theta_rad, costs.t, geo.edges
    best = np.argmin(cost[:, :-1], axis=1)
    ok = np.isfinite(cost[np.arange(len(cost)), best])
    pts, cls = [], []
    for e in np.nonzero(ok)[0]:  # one iteration per street edge
        c, s = np.cos(theta[e, best[e]]), np.sin(theta[e, best[e]])
        xy = np.concatenate([fine[edges[e, 0]], fine[edges[e, 1]]])
        w = xy @ np.array([[c, s], [-s, c]]) + t[e, best[e]]
        pts.append(geo.grid.world_to_pixel(w)[:, ::-1])
        cls.append(np.full(len(w), e))
    if pts:
        obs.debug("best_candidates", DebugPoints2D(np.concatenate(pts), class_ids=np.concatenate(cls),
                                                   radius_m=0.5))
