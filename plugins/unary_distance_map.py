"""unary.distance_map — the data term D of the conjugate nodes (paper §3.3.1, Fig. 4).

For a street edge (j, k) and a label mapping j→p, k→q: each edge is abstracted as the line between
its two segment centres, and T = the 2D rigid transform (no scale) putting the street line's
midpoint and direction onto the over-view line. T is applied to the street boundary points of j
and k, scored by a truncated chamfer on the distance maps of p's and q's outlines respectively
(cost = mean(min(d, truncate)) / truncate; released code counts points beyond 5 px, a truncated
mean keeps a gradient near the optimum); offsets (and rotations) within the candidate's window
absorb the gap between façade centres and building centres.

The steps, in ``toolkit.matching``: ``candidates`` (centre lines, length/extent/prior pruning),
``data_term`` (the prior: GPS or the route placed by its façades; free-space probes; the costs),
``pose_search`` (window or anchored search, refinement of the best), on ``atlas`` maps.
Parameters are grouped by the helper that owns them (``pose``, ``chamfer``, ``anchor``, ``prune``,
``gps``, ``free_space``, ``route_prior``); the old flat keys (``gps_radius_m``) still work.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Literal

from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.matching import data_term as DT
from toolkit.matching import pose_search as PS
from toolkit.matching.anchors import AnchorConfig, outline_anchors
from toolkit.matching.atlas import CropAtlas
from toolkit.matching.candidates import PruneConfig, check_inputs, pair_geometry, select_candidates
from toolkit.matching.chamfer import ChamferConfig
from toolkit.matching.config import GroupedParams
from toolkit.matching.gps import GpsConfig
from toolkit.matching.route_prior import RoutePriorConfig
from toolkit.stage import Handoff, Stage, StageParams
from toolkit.types import ConjugateGraphs, DataCosts, OverviewSegments, Scene, StreetSegments


class DistanceMap(Stage):
    """Data term: centre-line transform + truncated chamfer on distance maps with a pose search (paper §3.3.1)."""

    kind = "unary"
    name = "distance_map"

    class Params(GroupedParams):
        search: Literal["anchor", "window"] = Field(
            "anchor", description="Pose search: 'window' (the paper's rotations × offsets around "
                                  "the centre-line pose) or 'anchor' (façade on outline)")
        pose: PS.PoseSearchConfig = Field(default_factory=PS.PoseSearchConfig,
                                          description="Windows, steps and point counts of the pose search.")
        chamfer: ChamferConfig = Field(default_factory=ChamferConfig,
                                       description="The truncated (directional) chamfer poses are scored with.")
        anchor: AnchorConfig = Field(default_factory=AnchorConfig,
                                     description="search: anchor: outline samples, hypotheses and their rotation windows.")
        prune: PruneConfig = Field(default_factory=PruneConfig,
                                   description="Centre-line length and façade extent tests before any search.")
        raw_cost_at_null: float = Field(
            0.5, gt=0, le=1, description="Raw cost (mean truncated chamfer / truncate_px, 0-1) that "
                                         "equals null: cost = min(1, raw / this); 1: no rescaling")
        free_space: DT.FreeSpaceConfig = Field(
            default_factory=DT.FreeSpaceConfig, description="With street/sparse: the term telling a façade's "
                                                            "front from its back wall.")
        gps: GpsConfig = Field(default_factory=GpsConfig, description="With GPS or the route placement: the "
                                                                      "pruning radius, heading test and soft prior.")
        route_prior: RoutePriorConfig = Field(
            default_factory=RoutePriorConfig,
            description="Without street/gps.csv: place the route by its façades first, then prune as with GPS.")
        workers: int = Field(2, ge=1, le=64, description="Threads for the searches, at most the run's thread "
                                                      "budget (toolkit.threads; results do not depend on it).")
        max_elements: int = Field(
            4_000_000, ge=10_000, description="Look-ups per vectorised batch (count; bounds temporary memory).")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ()  # street/gps.csv is optional: checked with capture.gps_path

    def prefetch_inputs(self) -> tuple[str, ...]:
        return ("overview", "capture")

    def prefetch(self, overview: OverviewSegments, capture: StreetCapture | None) -> Handoff[CropAtlas]:
        """The distance atlas: it needs only the over-view, so the runner builds it while the
        street step runs (in a ``Handoff``: the step frees it before it makes the (E,L) costs). The
        COLMAP model that the free-space term and GPS pruning read is read here too (the scene's
        reader keeps it): 0.3 s of text parsing on campus."""
        uses_probes = self.params.free_space.used_with(capture)
        if capture is not None and capture.sparse_path is not None and (uses_probes or capture.gps_path is not None):
            capture.require_sparse("unary.distance_map")
        return Handoff(self._atlas(overview, uses_probes))

    def _atlas(self, overview: OverviewSegments, with_inside: bool) -> CropAtlas:
        p = self.params
        return PS.distance_atlas(overview, PS.search_levels(p.search, p.pose), p.pose.offset_cap_m, p.chamfer,
                                 with_inside)

    def __call__(self, graphs: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments,
                 scene: Scene, capture: StreetCapture | None, obs,
                 prefetched: Handoff[CropAtlas] | None = None) -> DataCosts:
        p = self.params
        if graphs.n_nodes == 0 or graphs.n_labels == 1:
            return DT.null_costs(graphs.n_nodes, graphs.n_labels)
        check_inputs(graphs, street, overview)
        t0 = time.perf_counter()
        geo = pair_geometry(graphs, street, overview)
        # 1. the prior: GPS fixes, else the route placed by its façades, else none
        prior = DT.choose_prior(capture, street, overview, p.gps, p.route_prior, obs)
        # 2. the candidates passing the length, extent and prior tests, at their centre-line pose
        cand = select_candidates(geo, street, prior, p.prune, offset_cap_m=p.pose.offset_cap_m,
                                 offset_window_scale=p.pose.offset_window_scale,
                                 same_segment=p.search != "window", angle_deg=p.gps.angle_deg)
        stats = dict(cand.stats)
        if len(cand.edge) == 0:
            obs.warn("every candidate was pruned: all street edges get the null label")
            return dataclasses.replace(DT.null_costs(graphs.n_nodes, graphs.n_labels), prior=prior.source,
                                       prior_figures=prior.figures)
        # 3. street points (fine and a nested coarse subset), dominant walls, free-space probes
        samples = PS.street_samples(street, geo, p.pose, p.chamfer.directional)
        probes = None
        if p.free_space.used_with(capture):
            probes = DT.free_space_probes(capture.sparse, street, samples, geo, p.free_space, stats)
        levels = PS.search_levels(p.search, p.pose)
        atlas = prefetched.take() if prefetched is not None else self._atlas(overview, probes is not None)
        score = PS.Scorer(atlas, geo.A, p.max_elements, probes, p.free_space.weight, p.workers)
        t_setup = time.perf_counter() - t0
        # 4. the coarse search over every candidate
        if p.search == "window":
            coarse = PS.window_search(score, samples.coarse_pts, cand.pairs, levels.offset_steps[0], p.pose)
        else:
            anchors = outline_anchors(overview, geo.origin, geo.A_inv, geo.px0, p.anchor.spacing_m)
            coarse = PS.anchor_search(score, geo, cand, samples, anchors, levels.offset_steps[0], stats,
                                      anchor=p.anchor, pose=p.pose, angle_deg=p.gps.angle_deg,
                                      prior_term=DT.prior_term(cand, geo, prior, p.gps))
        # 5. the best of each edge refined level by level, the others re-scored on the exact map
        final = PS.refine_best(score, coarse, samples, levels, p.pose, stats)
        stats["atlas_mb"] = round(atlas.nbytes / 2**20, 1)
        del score, atlas, coarse    # freed before the dense (E,L) arrays: 0.9 + 1.2 GB on the district scene
        # 6. T̂ of each pose, the prior's test on it, costs rescaled to [0, 1]
        costs = DT.fill_costs(DT.null_costs(graphs.n_nodes, graphs.n_labels), cand, final, geo, prior, p.gps,
                              p.raw_cost_at_null)
        stats.update(setup_s=round(t_setup, 2), total_s=round(time.perf_counter() - t0, 2))
        if obs.wants_debug:
            DT.debug_costs(obs, stats, costs, geo, samples.fine)
        return costs
