"""unary.distance_map — the data term D of the conjugate nodes (paper §3.3.1, Fig. 4).

For a street edge (j, k) and a label mapping j→p, k→q: each edge is abstracted as the line between
its two segment centres, and T = the 2D rigid transform (no scale) putting the street line's
midpoint and direction onto the over-view line. T is applied to the street boundary points of j
and k, scored by a truncated chamfer on the distance maps of p's and q's outlines respectively
(cost = mean(min(d, truncate)) / truncate; released code counts points beyond 5 px, a truncated
mean keeps a gradient near the optimum); offsets (and rotations) within the candidate's window
absorb the gap between façade centres and building centres; the best pose is folded into
T̂ = (θ, t). Costs are rescaled by ``raw_cost_at_null`` and clipped to [0, 1]; D(null) = 1; pruned
candidates are +inf (θ, t NaN).

Pruning (scale is known): centre-line lengths must agree within ``length_tolerance_m +
length_tolerance_fraction·len + centroid_slack·(ρ_p + ρ_q)`` (ρ: the largest centroid-to-outline
distance, which bounds how far a façade centre can sit from its building centre); each façade must
fit on its segment (extent ≤ diameter + tolerance). With street/gps.csv: the edge midpoint must land
within the GPS radius (+ the offset window) of its GPS-implied position, and the final pose must put
both centres within their radii (per segment: wider where the local GPS fit's residual is large)
and turn within gps_angle_deg of the local GPS fit; the pose search itself only tries rotations
within gps_angle_deg of the GPS heading, and ``gps_cost_weight`` adds a soft penalty growing with
the distance from the GPS-implied positions (relative to each segment's radius).

Search, vectorised over all candidate pairs (``search``):
- ``window`` (the paper): every rotation of ±rotation_window_deg × a coarse offset grid over the
  candidate's window, on eroded maps with a few points per segment;
- ``anchor`` (default): only poses that put the midpoint of a street segment's dominant wall on an
  outline sample of its candidate segment, along the outline's tangent, and the other segment's
  wall near its own candidate's outline (``toolkit.matching.anchors``). The centre-line angle is
  off by 20–35° for short edges between large buildings (measured on the campus scene), which a
  dense window search covers only at many times the cost.
Then the ``refine_top_k`` best pairs of each edge are refined (rotation and offset steps halved per
level, all points, exact map last); the others keep their coarse pose, re-scored on the exact map.

With street/sparse, a free-space term (``free_space_weight``) penalises poses that put a façade's
camera side inside its building: it tells a façade from the building's back wall.
Same-segment labels (p, p) (graph.knn ``same_segment_labels``) are scored once, with any rotation.
"""

from __future__ import annotations

import time
from typing import Literal

import numpy as np
from pydantic import Field

from toolkit.errors import StageError
from toolkit.matching import anchors as AN
from toolkit.matching import chamfer as CH
from toolkit.matching.atlas import CropAtlas, build_atlas
from toolkit.matching.route_prior import RoutePriorConfig
from toolkit.observe import DebugPoints2D, DebugText
from toolkit.stage import Stage, StageParams
from toolkit.threads import map_in_order
from toolkit.types import ConjugateGraphs, DataCosts, OverviewSegments, Scene, StreetSegments


class DistanceMap(Stage):
    """Data term: centre-line transform + truncated chamfer on distance maps with a pose search (paper §3.3.1)."""

    kind = "unary"
    name = "distance_map"

    class Params(StageParams):
        search: Literal["anchor", "window"] = Field(
            "anchor", description="Pose search: 'window' (the paper's rotations × offsets around "
                                  "the centre-line pose) or 'anchor' (façade on outline)")
        max_points_per_segment: int = Field(
            200, ge=4, description="Street boundary points per segment in the fine search (released code: 200).")
        coarse_points_per_segment: int = Field(
            24, ge=2, description="Points per segment in the coarse search over all candidates (count).")
        truncate_px: float = Field(
            5.0, gt=0, description="Chamfer distances are truncated here (released code: 5 px threshold).")
        offset_cap_m: float = Field(
            20.0, ge=0, description="Cap on the offset search radius (metres).")
        offset_window_scale: float = Field(
            1.0, ge=0, description="Offset radius = scale·(ρ_p + ρ_q)/2 (unitless; ρ from the "
                                   "candidate segments' extents), capped by offset_cap_m.")
        coarse_offset_step_px: int = Field(
            8, ge=1, description="Offset step of the coarse search (halved per refinement level down to 1 px).")
        rotation_window_deg: float = Field(
            30.0, ge=0, description="Rotations searched around the centre-line angle: ±this (degrees).")
        rotation_window_from_extent: bool = Field(
            True, description="Anchored search: widen the rotation window per "
                              "candidate to asin((ρ_p + ρ_q) / centre-line length)")
        rotation_window_max_deg: float = Field(
            60.0, ge=0, le=180, description="Cap on that widened window (a straight façade also fits its wall "
                                            "turned by 180°; the cap keeps such flips out).")
        rotation_step_deg: float = Field(
            5.0, gt=0, description="Rotation step of the coarse search (degrees; halved per refinement level).")
        anchor_spacing_m: float = Field(1.0, gt=0, description="Outline sample spacing for anchored hypotheses (m).")
        anchor_tolerance_px: float = Field(
            3.0, gt=0, description="An anchored hypothesis must put the other façade centre "
                                   "this close to its candidate's outline (px).")
        max_hypotheses: int = Field(16, ge=1, description="Anchored hypotheses scored per candidate (count).")
        min_wall_share: float = Field(
            0.3, ge=0, le=1, description="Share of a segment's points its dominant straight "
                                         "wall needs to anchor hypotheses (0-1)")
        rescore_budget: int = Field(
            200_000_000, ge=0, description="Look-ups for scoring unrefined candidates with all points; "
                                           "beyond it the coarse points are used (count)")
        refine_top_k: int = Field(
            12, ge=1, description="Candidates per street edge refined after the coarse search (count).")
        length_tolerance_m: float = Field(
            3.0, ge=0, description="Absolute centre-line length tolerance (metres).")
        length_tolerance_fraction: float = Field(
            0.05, ge=0, description="Relative centre-line length tolerance (0-1; SfM scale drift).")
        centroid_slack: float = Field(
            1.0, ge=0, description="Share of ρ_p + ρ_q added to the length tolerance (1 = the exact bound "
                                   "for façades lying on their building's outline).")
        extent_tolerance_m: float = Field(
            8.0, ge=0, description="Prune a candidate when the façade is longer than the "
                                   "candidate segment's diameter plus this (m)")
        raw_cost_at_null: float = Field(
            0.5, gt=0, le=1, description="Raw cost (mean truncated chamfer / truncate_px, 0-1) that "
                                         "equals null: cost = min(1, raw / this); 1: no rescaling")
        directional: bool = Field(
            False, description="Directional chamfer: add an orientation channel (distance + weight·|Δangle|).")
        orientation_bins: int = Field(
            8, ge=2, le=32, description="Orientation bins over [0, π) when directional (count).")
        orientation_weight_px_per_rad: float = Field(
            10.0, ge=0, description="Directional chamfer weight (px per radian; released code: DT + 10·|Δangle|).")
        free_space_weight: float = Field(
            0.5, ge=0, le=1, description="With street/sparse: weight of the free-space term that tells a "
                                         "façade's front from its back wall (0: chamfer only)")
        probe_offset_m: float = Field(
            2.0, gt=0, description="Distance of the free-space probes from the façade (m).")
        gps_radius_m: float | None = Field(
            None, gt=0, description="With GPS: prune poses putting a segment centre farther than this "
                                    "from its GPS position (m; None: from the fixes' σ)")
        gps_cost_weight: float = Field(
            0.3, ge=0, description="With GPS: weight w of the soft prior w·(d / GPS radius)² "
                                   "added to the raw chamfer cost (0: hard pruning only)")
        gps_radius_sigmas: float = Field(5.0, gt=0, description="GPS radius in fix σ when gps_radius_m is None.")
        gps_radius_fit_sigmas: float | None = Field(
            3.0, gt=0, description="With gps_radius_m None: widen a segment's radius to this "
                                   "many RMS residuals of its local GPS fit (None: off)")
        gps_radius_margin_m: float = Field(
            5.0, ge=0, description="Added to the σ-based GPS radius (pose error of the candidate itself).")
        gps_angle_deg: float | None = Field(
            45.0, gt=0, description="With GPS: prune candidates whose rotation differs more (degrees; None: no test).")
        gps_fit_fixes: int = Field(
            100, ge=3, description="GPS fixes per local rigid fit (count; nearest to the segment).")
        route_prior: RoutePriorConfig = Field(
            default_factory=RoutePriorConfig,
            description="Without street/gps.csv: place the route by its façades first, then prune as with GPS.")
        workers: int = Field(2, ge=1, le=64, description="Threads for the searches, at most the run's thread "
                                                      "budget (toolkit.threads; results do not depend on it).")
        max_elements: int = Field(
            4_000_000, ge=10_000, description="Look-ups per vectorised batch (count; bounds temporary memory).")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ()  # street/gps.csv is optional: checked with scene.has("gps")

    def prefetch_inputs(self) -> tuple[str, ...]:
        return ("overview", "scene")

    def prefetch(self, overview: OverviewSegments, scene: Scene) -> CropAtlas:
        """The distance atlas: it needs only the over-view, so the runner builds it while the
        street step runs. The COLMAP model that the free-space term and GPS pruning read is read
        here too (``load_sparse`` keeps it): 0.3 s of text parsing on campus."""
        if scene is not None and scene.has("sparse") and (self._uses_probes(scene) or scene.has("gps")):
            from toolkit.scene import load_sparse

            load_sparse(scene, who="unary.distance_map")
        return self._atlas(overview, self._uses_probes(scene))

    def _levels(self) -> tuple[list[int], list[tuple[float, int, int]]]:
        """Coarse offset steps (px) and the search levels (rotation step, offset step, erosion)."""
        p = self.params
        steps = _halvings(p.coarse_offset_step_px)
        rot = np.deg2rad(p.rotation_step_deg)
        if p.search == "window":
            return steps, [(rot / 2 ** i, s, s // 2) for i, s in enumerate(steps)]
        # anchored hypotheses are within an anchor spacing of the optimum: two local levels
        return steps, [(rot, 0, 1), (np.deg2rad(1.0), 2, 1), (np.deg2rad(0.5), 1, 0)]

    def _atlas(self, overview: OverviewSegments, with_inside: bool) -> CropAtlas:
        p = self.params
        steps, levels = self._levels()
        reach = int(np.ceil(p.offset_cap_m / overview.grid.gsd_m)) + steps[0] + 4
        return build_atlas(overview.label_image, overview.boundary_px, p.truncate_px, reach,
                           erosions=tuple(sorted({lv[2] for lv in levels} | {0, steps[0] // 2})),
                           n_bins=p.orientation_bins if p.directional else 1,
                           orientation_weight_px_per_rad=p.orientation_weight_px_per_rad,
                           with_inside=with_inside)

    def __call__(self, graphs: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments,
                 scene: Scene, obs, prefetched: CropAtlas | None = None) -> DataCosts:
        p = self.params
        E, L = graphs.n_nodes, graphs.n_labels
        cost = np.full((E, L), np.inf)
        cost[:, L - 1] = 1.0
        theta_out = np.full((E, L - 1), np.nan)
        t_out = np.full((E, L - 1, 2), np.nan)
        if E == 0 or L == 1:
            return DataCosts(cost, theta_out, t_out)
        _check_inputs(graphs, street, overview)
        t0 = time.perf_counter()

        grid = overview.grid
        gsd = grid.gsd_m
        o_world = grid.pixel_to_world(np.array([0.0]), np.array([0.0]))[0]  # local origin
        px0 = grid.world_to_pixel(o_world[None])[0]
        A = np.stack([grid.world_to_pixel(o_world[None] + d)[0] - px0 for d in np.eye(2)], axis=1)
        A_inv = np.linalg.inv(A)
        o_cent = np.asarray(overview.centroids, dtype=np.float64) - o_world
        rho, diam = _segment_radii(overview, o_cent, A_inv, px0)

        s_cent = np.asarray(street.centroids, dtype=np.float64)
        edges = np.asarray(graphs.street_edges, dtype=np.int64)
        lp = np.asarray(graphs.label_pairs, dtype=np.int64)
        j, k = edges[:, 0], edges[:, 1]
        s_vec = s_cent[k] - s_cent[j]
        s_len = np.linalg.norm(s_vec, axis=1)
        s_mid = (s_cent[j] + s_cent[k]) / 2
        o_vec = o_cent[lp[:, 1]] - o_cent[lp[:, 0]]
        o_len = np.linalg.norm(o_vec, axis=1)
        o_mid = (o_cent[lp[:, 0]] + o_cent[lp[:, 1]]) / 2

        window_of_label = np.minimum(p.offset_cap_m, p.offset_window_scale * (rho[lp[:, 0]] + rho[lp[:, 1]]) / 2)
        prior = None
        if scene is not None and scene.has("gps"):
            from toolkit.matching.gps import gps_prior

            prior = gps_prior(scene, street, n_local=p.gps_fit_fixes, warn=obs.warn)
        source, figures = ("gps", None) if prior is not None else (None, None)
        if prior is None and p.route_prior.enabled and scene is not None and scene.has("sparse"):
            placed = self._place_route(street, overview, scene, obs)
            prior, figures = placed.prior, placed.figures()
            source = "route_placement" if prior is not None else None
        seg_radius = self._gps_radii(prior, len(s_cent)) if prior is not None else None
        near = None
        if prior is not None:  # only labels near each edge's GPS midpoint can pass its test below
            near = _near_gps_midpoint(prior, seg_radius, j, k, o_mid + o_world, window_of_label)
        pe, pl = self._prune(s_len, o_len, street, lp, j, k, rho, diam, near)  # kept (edge, label) pairs
        loop = lp[:, 0] == lp[:, 1]           # same-segment labels (p, p): 2f and 2f+1 coincide
        if p.search == "window":               # the centre-line angle is undefined for them
            pe, pl = pe[~loop[pl]], pl[~loop[pl]]
        twin = loop & (np.arange(len(lp)) % 2 == 1)
        is_twin = twin[pl]
        twin_e, twin_l = pe[is_twin], pl[is_twin]   # scored once, copied at the end
        pe, pl = pe[~is_twin], pl[~is_twin]
        n_len = len(pe)
        theta0 = _wrap(np.arctan2(o_vec[pl, 1], o_vec[pl, 0]) - np.arctan2(s_vec[pe, 1], s_vec[pe, 0]))
        theta0[loop[pl]] = 0.0  # no over-view centre line: a fixed angle, whichever end comes first
        window = window_of_label[pl]
        if prior is not None:
            # the edge midpoint lands within the offset window of the over-view midpoint
            g_mid = (prior.position[j[pe]] + prior.position[k[pe]]) / 2
            edge_radius = np.maximum(seg_radius[j[pe]], seg_radius[k[pe]])
            ok = np.linalg.norm(o_mid[pl] + o_world - g_mid, axis=1) <= edge_radius + window
            pe, pl, theta0, window = pe[ok], pl[ok], theta0[ok], window[ok]
        # GPS heading of each pair (circular mean of its two segments' local fits), NaN without GPS.
        # The search only tries rotations within gps_angle_deg of it: the final pose test would
        # reject any other, and a same-segment label, which has no centre line, otherwise settles
        # on the building's outline turned by 90° or 180° (rectangles fit that way too).
        theta_gps = np.full(len(pe), np.nan)
        if prior is not None and p.gps_angle_deg is not None:
            theta_gps = np.arctan2(np.sin(prior.angle[j[pe]]) + np.sin(prior.angle[k[pe]]),
                                   np.cos(prior.angle[j[pe]]) + np.cos(prior.angle[k[pe]]))
            theta0 = np.where(loop[pl], theta_gps, theta0)
        window = window / gsd
        stats = {"pairs_total": E * (L - 1), "after_length": n_len, "after_gps": len(pe)}
        if near is not None:  # the length test then ran only on the pairs near the GPS midpoints
            stats["near_gps"] = len(near[0])
        if len(pe) == 0:
            obs.warn("every candidate was pruned: all street edges get the null label")
            return DataCosts(cost, theta_out, t_out, source, figures)

        # street points: fine (≤ max_points) and a nested coarse subset per segment
        fine, coarse, f_ang, c_ang = self._street_points(street, gsd)
        pts_f = CH.segment_points(fine, f_ang, s_cent, edges)
        pts_c = CH.segment_points(coarse, c_ang, s_cent, edges)
        walls = AN.segment_walls(fine)
        probes = self._probes(scene, street, walls, coarse, s_cent, edges, stats)

        steps, levels = self._levels()
        atlas = prefetched if prefetched is not None else self._atlas(overview, probes is not None)

        def score(erosion, pts, pairs_, d_theta, d_off):
            return CH.search(atlas, erosion, A, pts, pairs_, d_theta, d_off, p.max_elements,
                             probes=probes, probe_weight=p.free_space_weight, workers=p.workers)

        pairs = CH.Pairs(edge=pe, crops=lp[pl], theta=theta0, pivot_px=o_mid[pl] @ A.T + px0,
                         offset=np.zeros((len(pe), 2), np.int64), window_px=window)
        t_setup = time.perf_counter() - t0

        if p.search == "window":
            c_cost, c_pairs = self._window_search(score, pts_c, pairs, steps[0])
        else:
            anchors = AN.outline_anchors(overview, o_world, A_inv, px0, p.anchor_spacing_m)
            c_cost, c_pairs = self._anchor_search(score, atlas, A, px0, anchors, walls, pairs, pts_c, edges,
                                                  s_mid, o_mid[pl], o_len[pl], rho, steps[0], stats, theta_gps)

        # refine the best candidates of each edge, level by level, with all points
        top = _top_k_per_group(pe, c_cost, p.refine_top_k, c_pairs.pivot_px + c_pairs.offset)
        ref = c_pairs.take(top)
        r_cost = c_cost[top]
        for d_rot, step, erosion in levels[1:]:
            r_cost, r_theta, r_off = score(erosion, pts_f, ref, np.array([-1.0, 0.0, 1.0]) * d_rot,
                                           CH.grid_offsets(step, step))
            ref = CH.Pairs(ref.edge, ref.crops, r_theta, ref.pivot_px, r_off)
        if len(levels) == 1:  # nothing to refine: score the best on the exact map with all points
            r_cost, _, _ = score(0, pts_f, ref, np.zeros(1), np.zeros((1, 2)))

        # the others: exact map at their coarse pose, all points within the look-up budget
        rest = np.setdiff1d(np.arange(len(pe)), top)
        f_cost = np.empty(len(pe))
        f_cost[top] = r_cost
        f_theta, f_pivot, f_off = c_pairs.theta.copy(), c_pairs.pivot_px.copy(), c_pairs.offset.copy()
        f_theta[top], f_off[top] = ref.theta, ref.offset
        if len(rest):
            all_points = len(rest) * 2 * pts_f.xy.shape[1] <= p.rescore_budget
            stats["rescored_with_all_points"] = all_points
            f_cost[rest], _, _ = score(0, pts_f if all_points else pts_c, c_pairs.take(rest),
                                       np.zeros(1), np.zeros((1, 2)))

        # T̂: x_scene = R(θ)(x - s_mid) + A⁻¹(pivot + offset - px0) + origin
        c, s_ = np.cos(f_theta), np.sin(f_theta)
        m = s_mid[pe]
        rot_m = np.stack([c * m[:, 0] - s_ * m[:, 1], s_ * m[:, 0] + c * m[:, 1]], axis=1)
        t_hat = (f_pivot + f_off - px0) @ A_inv.T - rot_m + o_world
        if prior is not None:  # the exact test on the final pose, then the soft GPS term
            dist, turn = self._gps_offsets(prior, f_theta, t_hat, s_cent, j[pe], k[pe])
            rel = dist / np.stack([seg_radius[j[pe]], seg_radius[k[pe]]], axis=1)
            bad = rel.max(axis=1) > 1.0
            if p.gps_angle_deg is not None:
                bad |= turn.max(axis=1) > np.deg2rad(p.gps_angle_deg)
            f_cost = f_cost + p.gps_cost_weight * rel.max(axis=1) ** 2
            f_cost[bad] = np.inf
        # pruned stays +inf (np.clip would turn it into 1, a tie with null that greedy then picks)
        cost[pe, pl] = np.where(np.isfinite(f_cost), np.clip(f_cost / p.raw_cost_at_null, 0.0, 1.0), np.inf)
        kept = np.isfinite(f_cost)  # a pose the GPS test rejected is pruned like any other: NaN
        theta_out[pe[kept], pl[kept]] = _wrap(f_theta[kept])
        t_out[pe[kept], pl[kept]] = t_hat[kept]
        # twins of same-segment labels (label 2f+1 = label 2f when f is a self-loop)
        cost[twin_e, twin_l] = cost[twin_e, twin_l - 1]
        theta_out[twin_e, twin_l] = theta_out[twin_e, twin_l - 1]
        t_out[twin_e, twin_l] = t_out[twin_e, twin_l - 1]

        stats.update(refined=len(top), atlas_mb=round(atlas.nbytes / 2**20, 1),
                     setup_s=round(t_setup, 2), total_s=round(time.perf_counter() - t0, 2))
        if obs.wants_debug:
            _debug(obs, stats, cost, theta_out, t_out, edges, fine, grid)
        return DataCosts(cost, theta_out, t_out, source, figures)

    def _rotations(self) -> np.ndarray:
        p = self.params
        n_rot = int(np.floor(p.rotation_window_deg / p.rotation_step_deg + 1e-9))
        return np.arange(-n_rot, n_rot + 1) * np.deg2rad(p.rotation_step_deg)

    def _window_search(self, score, pts_c, pairs: CH.Pairs, step: int):
        """Paper: every rotation of the window × a coarse offset grid, on eroded maps."""
        d_off = CH.grid_offsets(int(np.ceil(pairs.window_px.max())), step)
        cost, theta, off = score(step // 2, pts_c, pairs, self._rotations(), d_off)
        return cost, CH.Pairs(pairs.edge, pairs.crops, theta, pairs.pivot_px, off)

    def _anchor_search(self, score, atlas, A, px0, anchors, walls, pairs: CH.Pairs, pts_c, edges,
                       s_mid, o_mid_pairs, o_len_pairs, rho, step, stats, theta_gps):
        """Anchored hypotheses, each scored at its pose; pairs without one fall back to the window
        search (both façades curved) or to the centre-line pose (no consistent anchoring).
        theta_gps (P,): GPS heading (NaN: none); hypotheses turned farther than gps_angle_deg from
        it are dropped before the best max_hypotheses are kept."""
        p = self.params
        s_anchor, s_dir, share = walls
        usable = share >= p.min_wall_share
        P = len(pairs.edge)
        rot_window = np.full(P, np.deg2rad(p.rotation_window_deg))
        if p.rotation_window_from_extent:
            # each centre may sit up to ρ from where the centre line assumes: the line turns by up to
            # asin((ρ_p + ρ_q) / length) (any angle when that exceeds 1)
            ratio = (rho[pairs.crops[:, 0]] + rho[pairs.crops[:, 1]]) / np.maximum(o_len_pairs, 1e-9)
            bound = np.where(ratio < 1, np.arcsin(np.minimum(ratio, 1.0)), np.pi)
            rot_window = np.maximum(rot_window, np.minimum(bound, np.deg2rad(p.rotation_window_max_deg)))
        # same-segment labels have no over-view centre line: any rotation
        same = pairs.crops[:, 0] == pairs.crops[:, 1]
        has_gps = np.isfinite(theta_gps)
        rot_window[same] = np.pi
        if p.gps_angle_deg is not None:  # same-segment labels are centred on the GPS heading
            rot_window[same & has_gps] = np.deg2rad(p.gps_angle_deg)
        gps_window = np.deg2rad(p.gps_angle_deg) if p.gps_angle_deg is not None else np.pi
        cost = np.full(P, np.inf)
        theta, pivot = pairs.theta.copy(), pairs.pivot_px.copy()
        offset = np.zeros((P, 2), np.int64)
        chunk = max(1, p.max_elements // 400)

        def best_hypothesis(start: int):
            idx = np.arange(start, min(P, start + chunk))
            hp, hyp = AN.hypotheses(atlas, A, px0, anchors, pairs.take(idx), s_anchor, s_dir, usable, edges,
                                    s_mid, o_mid_pairs[idx], rot_window[idx], p.anchor_tolerance_px,
                                    p.max_hypotheses, theta_gps[idx], gps_window)
            if len(hp) == 0:
                return None
            h_cost, h_theta, _ = score(1, pts_c, hyp, np.zeros(1), np.zeros((1, 2)))
            # ties broken by the pose itself, not by which end of the edge anchored it
            order = np.lexsort((hyp.pivot_px[:, 1].round(6), hyp.pivot_px[:, 0].round(6), h_cost, hp))
            first = order[np.r_[True, hp[order][1:] != hp[order][:-1]]]
            return idx[hp[first]], h_cost[first], h_theta[first], hyp.pivot_px[first], len(hp)

        n_hyp = 0
        for res in map_in_order(best_hypothesis, range(0, P, chunk), p.workers):
            if res is not None:
                dst, cost[dst], theta[dst], pivot[dst], n = res
                n_hyp += n
        none = ~np.isfinite(cost)
        both_curved = (none & ~usable[edges[pairs.edge, 0]] & ~usable[edges[pairs.edge, 1]]
                       & (pairs.crops[:, 0] != pairs.crops[:, 1]))
        stats.update(hypotheses=n_hyp, no_hypothesis=int(none.sum()), window_fallback=int(both_curved.sum()))
        if both_curved.any():
            i = np.nonzero(both_curved)[0]
            w_cost, w_pairs = self._window_search(score, pts_c, pairs.take(i), step)
            cost[i], theta[i], offset[i] = w_cost, w_pairs.theta, w_pairs.offset
        rest = np.nonzero(none & ~both_curved)[0]
        if len(rest):
            cost[rest], _, _ = score(1, pts_c, pairs.take(rest), np.zeros(1), np.zeros((1, 2)))
        return cost, CH.Pairs(pairs.edge, pairs.crops, theta, pivot, offset)

    # --- pieces -------------------------------------------------------------------------------
    def _prune(self, s_len, o_len, street, lp, j, k, rho, diam, among=None,
               rows_per_block: int = 64) -> tuple[np.ndarray, np.ndarray]:
        """(edge, label) pairs passing the length and extent tests, in row-major order; only
        among the given (edge, label) pairs (row-major) when ``among`` is set, else among all."""
        p = self.params
        tol = (p.length_tolerance_m + p.length_tolerance_fraction * o_len
               + p.centroid_slack * (rho[lp[:, 0]] + rho[lp[:, 1]]))
        ext = np.asarray(street.extent_m, dtype=np.float64)
        ext_j, ext_k = ext[j], ext[k]
        room_0, room_1 = diam[lp[:, 0]] + p.extent_tolerance_m, diam[lp[:, 1]] + p.extent_tolerance_m
        if among is not None:
            e, lab = among
            keep = np.abs(s_len[e] - o_len[lab]) <= tol[lab]
            keep &= ext_j[e] <= room_0[lab]
            keep &= ext_k[e] <= room_1[lab]
            return e[keep], lab[keep]
        # Row blocks: on a district the full (E, L-1) test arrays take GBs of fresh pages, nearly all False.
        found_e, found_l = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        for r0 in range(0, len(s_len), rows_per_block):
            r1 = min(r0 + rows_per_block, len(s_len))
            keep = np.abs(s_len[r0:r1, None] - o_len[None, :]) <= tol
            keep &= ext_j[r0:r1, None] <= room_0
            keep &= ext_k[r0:r1, None] <= room_1
            e_blk, l_blk = np.nonzero(keep)
            found_e.append(e_blk + r0)
            found_l.append(l_blk)
        return np.concatenate(found_e).astype(np.int64), np.concatenate(found_l).astype(np.int64)

    def _gps_radii(self, prior, n_seg: int) -> np.ndarray:
        """(S,) GPS radius (m) of each street segment (gps_radius_m, or σ- and fit-based; see the Params)."""
        p = self.params
        if p.gps_radius_m is not None:
            return np.full(n_seg, p.gps_radius_m)
        radius = np.full(n_seg, p.gps_radius_sigmas * prior.sigma_m)
        if p.gps_radius_fit_sigmas is not None and prior.fit_rms_m is not None:
            radius = np.maximum(radius, p.gps_radius_fit_sigmas * prior.fit_rms_m)
        return radius + p.gps_radius_margin_m

    @staticmethod
    def _gps_offsets(prior, theta, t, s_cent, sj, sk) -> tuple[np.ndarray, np.ndarray]:
        """(P,2) distances of both segment centres, placed by the poses, from their GPS-implied
        positions, and (P,2) |rotation − the local GPS fit's rotation| (radians)."""
        c, s = np.cos(theta), np.sin(theta)
        dist, turn = [], []
        for seg in (sj, sk):
            x = s_cent[seg]
            placed = np.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1]], 1) + t
            dist.append(np.linalg.norm(placed - prior.position[seg], axis=1))
            turn.append(np.abs(_wrap(theta - prior.angle[seg])))
        return np.stack(dist, axis=1), np.stack(turn, axis=1)

    def _place_route(self, street: StreetSegments, overview: OverviewSegments, scene: Scene, obs):
        """The route placed by its façades (``toolkit.matching.route_prior``); a warning when unused."""
        from toolkit.matching.route_prior import capture_order, place_route
        from toolkit.scene import load_sparse

        model = load_sparse(scene, who="unary.distance_map (route placement)")
        cams = street.level(model.centres[capture_order(model.image_names)])[:, :2]
        placed = place_route(street, overview, cams, self.params.route_prior)
        obs.debug("route_placement", DebugText(placed.describe()))
        if placed.prior is None:
            obs.warn(f"route placement not used ({placed.reason}): every over-view pair is searched")
        return placed

    def _uses_probes(self, scene) -> bool:
        return self.params.free_space_weight > 0 and scene is not None and scene.has("sparse")

    def _probes(self, scene, street: StreetSegments, walls, coarse, s_cent, edges, stats):
        """Free-space probes: each segment's coarse points moved probe_offset_m towards the side
        its cameras saw it from (needs street/sparse); None when unused."""
        p = self.params
        if not self._uses_probes(scene):
            return None
        from toolkit.scene import load_sparse

        cams = street.level(load_sparse(scene, who="unary.distance_map (free space)").centres)[:, :2]
        outward = AN.observer_sides(cams, walls[0], walls[1])
        known = np.any(outward != 0, axis=1)
        stats["observer_side_known"] = f"{int(known.sum())}/{len(known)}"
        probe_pts = [c + o * p.probe_offset_m if ok else c[:0] for c, o, ok in zip(coarse, outward, known)]
        return CH.segment_points(probe_pts, None, s_cent, edges)

    def _street_points(self, street: StreetSegments, gsd: float):
        p = self.params
        fine, coarse, f_ang, c_ang = [], [], [], []
        for xy in street.boundary_xy:  # one iteration per street segment
            f = CH.subsample_segment(xy, cell_m=gsd / 2, max_points=p.max_points_per_segment)
            sel = CH.even_indices(len(f), p.coarse_points_per_segment)
            fine.append(f)
            coarse.append(f[sel])
            if p.directional:
                a = CH.point_directions(f)
                f_ang.append(a)
                c_ang.append(a[sel])
        return fine, coarse, (f_ang if p.directional else None), (c_ang if p.directional else None)


# --- helpers ----------------------------------------------------------------------------------
def _near_gps_midpoint(prior, seg_radius: np.ndarray, j: np.ndarray, k: np.ndarray, o_mid_world: np.ndarray,
                       window_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Row-major (edge, label) pairs whose over-view midpoint lies within the edge's GPS radius plus
    the largest offset window of its GPS midpoint: a superset of the exact per-pair test, found with
    one KD-tree instead of a test over all E × L pairs (40 M on a district)."""
    from scipy.spatial import cKDTree

    g_mid = (prior.position[j] + prior.position[k]) / 2
    finite = window_m[np.isfinite(window_m)]
    reach_m = np.maximum(seg_radius[j], seg_radius[k]) + (finite.max() if len(finite) else 0.0) + 1e-3  # + slack
    hits = cKDTree(o_mid_world).query_ball_point(g_mid, reach_m)
    e = np.repeat(np.arange(len(j), dtype=np.int64), [len(h) for h in hits])
    lab = np.concatenate([np.zeros(0, np.int64), *(np.asarray(h, np.int64) for h in hits)])
    order = np.lexsort((lab, e))
    return e[order], lab[order]


def _wrap(a: np.ndarray) -> np.ndarray:
    return np.mod(np.asarray(a) + np.pi, 2 * np.pi) - np.pi


def _halvings(step: int) -> list[int]:
    """[step, step/2, ..., 1] with step rounded down to a power of two."""
    s = 1 << int(np.floor(np.log2(max(1, step))))
    out = []
    while s >= 1:
        out.append(s)
        s //= 2
    return out


def _top_k_per_group(group: np.ndarray, score: np.ndarray, k: int, tie: np.ndarray) -> np.ndarray:
    """Indices of the k lowest scores within each group, sorted; ties broken by ``tie`` (P,2)."""
    order = np.lexsort((tie[:, 1].round(6), tie[:, 0].round(6), score, group))
    g = group[order]
    first = np.searchsorted(g, g, side="left")
    rank = np.arange(len(g)) - first
    return np.sort(order[rank < k])


def _segment_radii(overview: OverviewSegments, o_cent_local: np.ndarray, A_inv: np.ndarray,
                   px0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """ρ (largest centroid-to-boundary distance) and bounding-box diagonal (≥ diameter), metres."""
    n = len(overview.boundary_px)
    rho, diam = np.zeros(n), np.zeros(n)
    for i, b in enumerate(overview.boundary_px):  # one iteration per over-view segment
        if len(b) == 0:
            continue
        xy = (np.asarray(b, dtype=np.float64) - px0) @ A_inv.T  # pixel centres → local metres
        rho[i] = np.linalg.norm(xy - o_cent_local[i], axis=1).max()
        diam[i] = np.linalg.norm(xy.max(axis=0) - xy.min(axis=0))
    return rho, diam


def _check_inputs(graphs: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments) -> None:
    if len(graphs.street_edges) and graphs.street_edges.max() >= len(street.boundary_xy):
        raise StageError(f"unary.distance_map: the conjugate graph names street segment "
                         f"{int(graphs.street_edges.max())} but the street has {len(street.boundary_xy)}")
    if len(graphs.label_pairs) and graphs.label_pairs.max() >= len(overview.boundary_px):
        raise StageError(f"unary.distance_map: the conjugate graph names over-view segment "
                         f"{int(graphs.label_pairs.max())} but the over-view has {len(overview.boundary_px)}")


def _debug(obs, stats, cost, theta, t, edges, fine, grid) -> None:
    obs.debug("stats", DebugText("\n".join(f"- {k}: {v}" for k, v in stats.items())))
    best = np.argmin(cost[:, :-1], axis=1)
    ok = np.isfinite(cost[np.arange(len(cost)), best])
    pts, cls = [], []
    for e in np.nonzero(ok)[0]:  # one iteration per street edge
        c, s = np.cos(theta[e, best[e]]), np.sin(theta[e, best[e]])
        xy = np.concatenate([fine[edges[e, 0]], fine[edges[e, 1]]])
        w = xy @ np.array([[c, s], [-s, c]]) + t[e, best[e]]
        pts.append(grid.world_to_pixel(w)[:, ::-1])
        cls.append(np.full(len(w), e))
    if pts:
        obs.debug("best_candidates", DebugPoints2D(np.concatenate(pts), class_ids=np.concatenate(cls),
                                                   radius_m=0.5))
