"""Candidates of the data term: the centre lines of every (street edge, label) pair and the tests
that prune pairs before any pose search.

For a street edge (j, k) and a label mapping j→p, k→q, each edge is abstracted as the line between
its two segment centres. Scale is known, so the centre-line lengths must agree within
``length_tolerance_m + length_tolerance_fraction·len + centroid_slack·(ρ_p + ρ_q)`` (ρ: the largest
centroid-to-outline distance, which bounds how far a façade centre can sit from its building
centre), and each façade must fit on its segment (extent ≤ diameter + ``extent_tolerance_m``).
With a prior (street/gps.csv or the route placement) the edge midpoint must also land within the
prior radius (+ the reach of its segments' outlines, (ρ_p + ρ_q)/2) of its prior position, the
anchored hypotheses must put it within that radius of the prior position and within (ρ_p + ρ_q)/2
of the over-view midpoint (without a prior: within the offset window, capped at ``offset_cap_m``,
which a façade of a large block, far from the block's centre, never reaches), and the pose search
only tries rotations within ``angle_deg`` of the prior heading. Same-segment labels (p, p) (graph.knn
``same_segment_labels``) are scored once: label 2f+1 is a twin of 2f, copied at the end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from toolkit.errors import StageError
from toolkit.matching.chamfer import Pairs
from toolkit.matching.config import MatchingConfig
from toolkit.matching.gps import GpsPrior, PruningPrior
from toolkit.matching.mrf import wrap_angle
from toolkit.types import ConjugateGraphs, Grid, OverviewSegments, StreetSegments


# an anchored hypothesis is refined by up to a few pixels and a degree afterwards (the search levels),
# so it may start this far outside the prior radius and still end inside it
HYPOTHESIS_SLACK_M = 2.0


class PruneConfig(MatchingConfig):
    """The length and extent tests that prune candidates before any pose search."""

    length_tolerance_m: float = Field(3.0, ge=0, description="absolute centre-line length tolerance (metres)")
    length_tolerance_fraction: float = Field(
        0.05, ge=0, description="relative centre-line length tolerance (0-1; SfM scale drift)")
    centroid_slack: float = Field(1.0, ge=0, description="share of ρ_p + ρ_q added to the length tolerance (1 = "
                                                         "the exact bound for façades on their building's outline)")
    extent_tolerance_m: float = Field(8.0, ge=0, description="prune a candidate when the façade is longer than "
                                                             "the candidate segment's diameter plus this (m)")


@dataclass(frozen=True)
class PairGeometry:
    """The frames and centre lines of the data term.

    origin: world x, y of pixel (0, 0), the local metric origin; A (2,2): local metres → pixel
    offsets, A_inv its inverse, px0 the origin's pixel. Per over-view segment: rho (largest
    centroid-to-outline distance) and diam (bounding-box diagonal), metres. Per street edge (j, k):
    s_vec, s_len, s_mid of the line between the segment centroids s_cent; per label (p, q): o_vec,
    o_len, o_mid (local metres) of the line between the over-view centroids.
    """

    grid: Grid
    origin: np.ndarray
    A: np.ndarray
    A_inv: np.ndarray
    px0: np.ndarray
    rho: np.ndarray
    diam: np.ndarray
    s_cent: np.ndarray
    edges: np.ndarray
    s_vec: np.ndarray
    s_len: np.ndarray
    s_mid: np.ndarray
    label_pairs: np.ndarray
    o_vec: np.ndarray
    o_len: np.ndarray
    o_mid: np.ndarray

    @property
    def j(self) -> np.ndarray:
        return self.edges[:, 0]

    def translation(self, edge: np.ndarray, theta: np.ndarray, pixel: np.ndarray) -> np.ndarray:
        """(P,2) t of T̂ = (θ, t), x_scene = R(θ)x + t, for edges whose midpoint a pose puts at ``pixel``
        (P,2, row/col: pivot + offset) turned by ``theta`` (P,)."""
        c, s = np.cos(theta), np.sin(theta)
        m = self.s_mid[edge]
        rot_m = np.stack([c * m[:, 0] - s * m[:, 1], s * m[:, 0] + c * m[:, 1]], axis=1)
        return (pixel - self.px0) @ self.A_inv.T - rot_m + self.origin

    @property
    def k(self) -> np.ndarray:
        return self.edges[:, 1]


@dataclass(frozen=True)
class Candidates:
    """The (edge, label) pairs to search, row-major: edge, label (P,); pairs: their centre-line
    pose (``Pairs``: angle θ0, pivot at the over-view midpoint, offset window in px); theta_prior (P,)
    prior heading (NaN: none); reach_m (P,): how far from the over-view midpoint an anchored
    hypothesis may put the street-edge midpoint ((ρ_p + ρ_q)/2 with a prior, else the offset
    window); prior_mid (P,2) local metres and prior_radius_m (P,): within what distance of where the
    prior puts it (inf: no prior); twin_edge, twin_label: same-segment twins, copied at the end."""

    edge: np.ndarray
    label: np.ndarray
    pairs: Pairs
    theta_prior: np.ndarray
    reach_m: np.ndarray
    prior_mid: np.ndarray
    prior_radius_m: np.ndarray
    twin_edge: np.ndarray
    twin_label: np.ndarray
    stats: dict


def check_inputs(graphs: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments) -> None:
    if len(graphs.street_edges) and graphs.street_edges.max() >= len(street.boundary_xy):
        raise StageError(f"unary.distance_map: the conjugate graph names street segment "
                         f"{int(graphs.street_edges.max())} but the street has {len(street.boundary_xy)}")
    if len(graphs.label_pairs) and graphs.label_pairs.max() >= len(overview.boundary_px):
        raise StageError(f"unary.distance_map: the conjugate graph names over-view segment "
                         f"{int(graphs.label_pairs.max())} but the over-view has {len(overview.boundary_px)}")


def pair_geometry(graphs: ConjugateGraphs, street: StreetSegments, overview: OverviewSegments) -> PairGeometry:
    grid = overview.grid
    o_world = grid.pixel_to_world(np.array([0.0]), np.array([0.0]))[0]  # local origin
    px0 = grid.world_to_pixel(o_world[None])[0]
    A = np.stack([grid.world_to_pixel(o_world[None] + d)[0] - px0 for d in np.eye(2)], axis=1)
    A_inv = np.linalg.inv(A)
    o_cent = np.asarray(overview.centroids, dtype=np.float64) - o_world
    rho, diam = segment_radii(overview, o_cent, A_inv, px0)
    s_cent = np.asarray(street.centroids, dtype=np.float64)
    edges = np.asarray(graphs.street_edges, dtype=np.int64)
    lp = np.asarray(graphs.label_pairs, dtype=np.int64)
    j, k = edges[:, 0], edges[:, 1]
    s_vec = s_cent[k] - s_cent[j]
    o_vec = o_cent[lp[:, 1]] - o_cent[lp[:, 0]]
    return PairGeometry(grid, o_world, A, A_inv, px0, rho, diam, s_cent, edges, s_vec, np.linalg.norm(s_vec, axis=1),
                        (s_cent[j] + s_cent[k]) / 2, lp, o_vec, np.linalg.norm(o_vec, axis=1),
                        (o_cent[lp[:, 0]] + o_cent[lp[:, 1]]) / 2)


def select_candidates(geo: PairGeometry, street: StreetSegments, prior: PruningPrior, prune: PruneConfig, *,
                      offset_cap_m: float, offset_window_scale: float, same_segment: bool,
                      angle_deg: float | None) -> Candidates:
    """The pairs passing the length, extent and prior tests, at their centre-line pose; the offset
    window of a label is offset_window_scale·(ρ_p + ρ_q)/2, capped by offset_cap_m. same_segment:
    keep (p, p) labels (the centre-line angle is undefined for them: any rotation is searched)."""
    lp, j, k = geo.label_pairs, geo.j, geo.k
    reach_of_label = offset_window_scale * (geo.rho[lp[:, 0]] + geo.rho[lp[:, 1]]) / 2
    window_of_label = np.minimum(offset_cap_m, reach_of_label)
    near = None
    if prior.prior is not None:  # only labels near each edge's prior midpoint can pass its test below
        near = near_gps_midpoint(prior.prior, prior.radius_m, j, k, geo.o_mid + geo.origin, reach_of_label)
    pe, pl = prune_pairs(geo.s_len, geo.o_len, street, lp, j, k, geo.rho, geo.diam, near, prune=prune)
    loop = lp[:, 0] == lp[:, 1]           # same-segment labels (p, p): 2f and 2f+1 coincide
    if not same_segment:
        pe, pl = pe[~loop[pl]], pl[~loop[pl]]
    twin = loop & (np.arange(len(lp)) % 2 == 1)
    is_twin = twin[pl]
    twin_e, twin_l = pe[is_twin], pl[is_twin]   # scored once, copied at the end
    pe, pl = pe[~is_twin], pl[~is_twin]
    n_len = len(pe)
    theta0 = wrap_angle(np.arctan2(geo.o_vec[pl, 1], geo.o_vec[pl, 0]) - np.arctan2(geo.s_vec[pe, 1], geo.s_vec[pe, 0]))
    theta0[loop[pl]] = 0.0  # no over-view centre line: a fixed angle, whichever end comes first
    window = window_of_label[pl]
    reach, prior_mid, prior_radius = window, np.zeros((len(pe), 2)), np.full(len(pe), np.inf)
    if prior.prior is not None:
        # the edge midpoint, on its segments' outlines, lies within (ρ_p + ρ_q)/2 of the over-view
        # midpoint, and within the prior radius of its prior position
        g_mid = (prior.prior.position[j[pe]] + prior.prior.position[k[pe]]) / 2
        edge_radius = np.maximum(prior.radius_m[j[pe]], prior.radius_m[k[pe]])
        ok = np.linalg.norm(geo.o_mid[pl] + geo.origin - g_mid, axis=1) <= edge_radius + reach_of_label[pl]
        pe, pl, theta0, window = pe[ok], pl[ok], theta0[ok], window[ok]
        reach = reach_of_label[pl]
        prior_mid, prior_radius = g_mid[ok] - geo.origin, edge_radius[ok] + HYPOTHESIS_SLACK_M
    # Prior heading of each pair (circular mean of its two segments' local fits), NaN without a prior.
    # The search only tries rotations within angle_deg of it: the final pose test would reject any
    # other, and a same-segment label, which has no centre line, otherwise settles on the
    # building's outline turned by 90° or 180° (rectangles fit that way too).
    theta_prior = np.full(len(pe), np.nan)
    if prior.prior is not None and angle_deg is not None:
        a = prior.prior.angle
        theta_prior = np.arctan2(np.sin(a[j[pe]]) + np.sin(a[k[pe]]), np.cos(a[j[pe]]) + np.cos(a[k[pe]]))
        theta0 = np.where(loop[pl], theta_prior, theta0)
    stats = {"pairs_total": len(geo.edges) * len(lp), "after_length": n_len, "after_gps": len(pe)}
    if near is not None:  # the length test then ran only on the pairs near the prior midpoints
        stats["near_gps"] = len(near[0])
    pairs = Pairs(edge=pe, crops=lp[pl], theta=theta0, pivot_px=geo.o_mid[pl] @ geo.A.T + geo.px0,
                  offset=np.zeros((len(pe), 2), np.int64), window_px=window / geo.grid.gsd_m)
    return Candidates(pe, pl, pairs, theta_prior, reach, prior_mid, prior_radius, twin_e, twin_l, stats)


def prune_pairs(s_len, o_len, street, lp, j, k, rho, diam, among=None, *, prune: PruneConfig,
                rows_per_block: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """(edge, label) pairs passing the length and extent tests, in row-major order; only
    among the given (edge, label) pairs (row-major) when ``among`` is set, else among all."""
    tol = (prune.length_tolerance_m + prune.length_tolerance_fraction * o_len
           + prune.centroid_slack * (rho[lp[:, 0]] + rho[lp[:, 1]]))
    ext = np.asarray(street.extent_m, dtype=np.float64)
    ext_j, ext_k = ext[j], ext[k]
    room_0, room_1 = diam[lp[:, 0]] + prune.extent_tolerance_m, diam[lp[:, 1]] + prune.extent_tolerance_m
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


def near_gps_midpoint(prior: GpsPrior, seg_radius: np.ndarray, j: np.ndarray, k: np.ndarray,
                      o_mid_world: np.ndarray, window_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def segment_radii(overview: OverviewSegments, o_cent_local: np.ndarray, A_inv: np.ndarray,
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
