"""The data term's pose search: every candidate pair's best 2D rigid pose on the distance atlas.

A pair starts at its centre-line pose (``toolkit.matching.candidates``): the street line's
midpoint and direction put onto the over-view line. Offsets (and rotations) within the
candidate's window absorb the gap between façade centres and building centres. The coarse search
runs over all candidate pairs, vectorised (``search``):

- ``window`` (the paper): every rotation of ±rotation_window_deg × a coarse offset grid over the
  candidate's window, on eroded maps with a few points per segment;
- ``anchor`` (default): only poses that put the midpoint of a street segment's dominant wall on an
  outline sample of its candidate segment, along the outline's tangent, and the other segment's
  wall near its own candidate's outline (``toolkit.matching.anchors``). The centre-line angle is
  off by 20–35° for short edges between large buildings (measured on the campus scene), which a
  dense window search covers only at many times the cost.

Then the ``refine_top_k`` best pairs of each edge are refined (rotation and offset steps halved
per level, all points, exact map last); the others keep their coarse pose, re-scored on the exact
map.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np
from pydantic import Field

from toolkit.matching import anchors as AN
from toolkit.matching import chamfer as CH
from toolkit.matching.atlas import CropAtlas, build_atlas
from toolkit.matching.candidates import Candidates, PairGeometry
from toolkit.matching.config import MatchingConfig
from toolkit.threads import map_in_order
from toolkit.types import OverviewSegments, StreetSegments

# (pair index (H,), θ (H,), pixel (H,2)) → the prior's soft term of each pose (H,)
PriorTerm = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


class PoseSearchConfig(MatchingConfig):
    """Windows, steps and point counts of the pose search."""

    max_points_per_segment: int = Field(
        200, ge=4, description="street boundary points per segment in the fine search (released code: 200)")
    coarse_points_per_segment: int = Field(
        24, ge=2, description="points per segment in the coarse search over all candidates (count)")
    offset_cap_m: float = Field(20.0, ge=0, description="cap on the offset search radius (metres; with a prior, "
                                                        "anchored poses go past it within the prior radius)")
    offset_window_scale: float = Field(
        1.0, ge=0, description="offset radius = scale·(ρ_p + ρ_q)/2 (unitless; ρ from the candidate "
                               "segments' extents), capped by offset_cap_m")
    coarse_offset_step_px: int = Field(
        8, ge=1, description="offset step of the coarse search (halved per refinement level down to 1 px)")
    rotation_window_deg: float = Field(
        30.0, ge=0, description="rotations searched around the centre-line angle: ±this (degrees)")
    rotation_step_deg: float = Field(
        5.0, gt=0, description="rotation step of the coarse search (degrees; halved per refinement level)")
    refine_top_k: int = Field(12, ge=1, description="candidates per street edge refined after the coarse search (count)")
    rescore_budget: int = Field(
        200_000_000, ge=0, description="look-ups for scoring unrefined candidates with all points; "
                                       "beyond it the coarse points are used (count)")


@dataclass(frozen=True)
class Level:
    """One search level: rotation step (radians), offset step (px) and map erosion (px)."""

    rotation_rad: float
    offset_px: int
    erosion_px: int


@dataclass(frozen=True)
class SearchLevels:
    """offset_steps: the coarse offset step (px) halved down to 1; levels: coarse first."""

    offset_steps: tuple[int, ...]
    levels: tuple[Level, ...]


@dataclass(frozen=True)
class StreetSamples:
    """Street boundary points per segment: fine (≤ max_points_per_segment) and a nested coarse
    subset, as ``SegmentPoints`` of the street edges, and each segment's dominant wall
    (``anchors.segment_walls``: anchor, direction, share)."""

    fine: list
    coarse: list
    fine_pts: CH.SegmentPoints
    coarse_pts: CH.SegmentPoints
    walls: tuple


@dataclass(frozen=True)
class Scored:
    """cost (P,) of each pair at its pose (pairs: theta, pivot_px, offset)."""

    cost: np.ndarray
    pairs: CH.Pairs


@dataclass(frozen=True)
class Scorer:
    """``chamfer.search`` on the atlas with the run's free-space probes, memory bound and threads."""

    atlas: CropAtlas
    A: np.ndarray
    max_elements: int
    probes: CH.SegmentPoints | None
    probe_weight: float
    workers: int

    def __call__(self, erosion: int, pts: CH.SegmentPoints, pairs: CH.Pairs, d_theta: np.ndarray,
                 d_off: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return CH.search(self.atlas, erosion, self.A, pts, pairs, d_theta, d_off, self.max_elements,
                         probes=self.probes, probe_weight=self.probe_weight, workers=self.workers)

    def at_pose(self, erosion: int, pts: CH.SegmentPoints, pairs: CH.Pairs) -> np.ndarray:
        """The cost of each pair at its own pose."""
        return self(erosion, pts, pairs, np.zeros(1), np.zeros((1, 2)))[0]


def search_levels(search: Literal["anchor", "window"], pose: PoseSearchConfig) -> SearchLevels:
    steps = halvings(pose.coarse_offset_step_px)
    rot = np.deg2rad(pose.rotation_step_deg)
    if search == "window":
        return SearchLevels(tuple(steps), tuple(Level(rot / 2 ** i, s, s // 2) for i, s in enumerate(steps)))
    # anchored hypotheses are within an anchor spacing of the optimum: two local levels
    return SearchLevels(tuple(steps), (Level(rot, 0, 1), Level(np.deg2rad(1.0), 2, 1), Level(np.deg2rad(0.5), 1, 0)))


def distance_atlas(overview: OverviewSegments, levels: SearchLevels, offset_cap_m: float,
                   chamfer: CH.ChamferConfig, with_inside: bool) -> CropAtlas:
    """The distance maps every search level reads (it needs only the over-view)."""
    step = levels.offset_steps[0]
    reach = int(np.ceil(offset_cap_m / overview.grid.gsd_m)) + step + 4
    return build_atlas(overview.label_image, overview.boundary_px, chamfer.truncate_px, reach,
                       erosions=tuple(sorted({lv.erosion_px for lv in levels.levels} | {0, step // 2})),
                       n_bins=chamfer.orientation_bins if chamfer.directional else 1,
                       orientation_weight_px_per_rad=chamfer.orientation_weight_px_per_rad,
                       with_inside=with_inside)


def street_samples(street: StreetSegments, geo: PairGeometry, pose: PoseSearchConfig,
                   directional: bool) -> StreetSamples:
    fine, coarse, f_ang, c_ang = [], [], [], []
    for xy in street.boundary_xy:  # one iteration per street segment
        f = CH.subsample_segment(xy, cell_m=geo.grid.gsd_m / 2, max_points=pose.max_points_per_segment)
        sel = CH.even_indices(len(f), pose.coarse_points_per_segment)
        fine.append(f)
        coarse.append(f[sel])
        if directional:
            a = CH.point_directions(f)
            f_ang.append(a)
            c_ang.append(a[sel])
    return StreetSamples(fine, coarse, CH.segment_points(fine, f_ang if directional else None, geo.s_cent, geo.edges),
                         CH.segment_points(coarse, c_ang if directional else None, geo.s_cent, geo.edges),
                         AN.segment_walls(fine))


def window_search(score: Scorer, pts: CH.SegmentPoints, pairs: CH.Pairs, step: int,
                  pose: PoseSearchConfig) -> Scored:
    """Paper: every rotation of the window × a coarse offset grid, on eroded maps."""
    d_off = CH.grid_offsets(int(np.ceil(pairs.window_px.max())), step)
    n_rot = int(np.floor(pose.rotation_window_deg / pose.rotation_step_deg + 1e-9))
    rotations = np.arange(-n_rot, n_rot + 1) * np.deg2rad(pose.rotation_step_deg)
    cost, theta, off = score(step // 2, pts, pairs, rotations, d_off)
    return Scored(cost, CH.Pairs(pairs.edge, pairs.crops, theta, pairs.pivot_px, off))


def anchor_search(score: Scorer, geo: PairGeometry, cand: Candidates, samples: StreetSamples, anchors: AN.Anchors,
                  step: int, stats: dict, *, anchor: AN.AnchorConfig, pose: PoseSearchConfig,
                  angle_deg: float | None, prior_term: PriorTerm | None = None) -> Scored:
    """Anchored hypotheses, each scored at its pose; pairs without one fall back to the window
    search (both façades curved) or to the centre-line pose (no consistent anchoring).
    Hypotheses turned farther than angle_deg from the prior heading are dropped before the best
    max_hypotheses are kept. ``prior_term(pair index, θ, pixel)``: the prior's soft term of a pose,
    added to the chamfer cost when a pair's best hypothesis is chosen (as the final cost adds it)."""
    pairs, edges = cand.pairs, geo.edges
    usable = samples.walls[2] >= anchor.min_wall_share
    best = _best_hypotheses(score, geo, cand, samples, anchors, usable, stats, anchor=anchor,
                            rotation_window_deg=pose.rotation_window_deg, angle_deg=angle_deg, prior_term=prior_term)
    cost, theta, pivot = best.cost, best.pairs.theta, best.pairs.pivot_px  # fresh arrays, completed below
    offset = np.zeros((len(pairs.edge), 2), np.int64)
    none = ~np.isfinite(cost)
    both_curved = (none & ~usable[edges[pairs.edge, 0]] & ~usable[edges[pairs.edge, 1]]
                   & (pairs.crops[:, 0] != pairs.crops[:, 1]))
    stats.update(no_hypothesis=int(none.sum()), window_fallback=int(both_curved.sum()))
    if both_curved.any():
        i = np.nonzero(both_curved)[0]
        w = window_search(score, samples.coarse_pts, pairs.take(i), step, pose)
        cost[i], theta[i], offset[i] = w.cost, w.pairs.theta, w.pairs.offset
    rest = np.nonzero(none & ~both_curved)[0]
    if len(rest):
        cost[rest] = score.at_pose(1, samples.coarse_pts, pairs.take(rest))
    return Scored(cost, CH.Pairs(pairs.edge, pairs.crops, theta, pivot, offset))


def _rotation_windows(geo: PairGeometry, cand: Candidates, anchor: AN.AnchorConfig, rotation_window_deg: float,
                      angle_deg: float | None) -> np.ndarray:
    """(P,) allowed |θ − θ0| of each pair's hypotheses (radians)."""
    crops = cand.pairs.crops
    rot_window = np.full(len(crops), np.deg2rad(rotation_window_deg))
    if anchor.rotation_window_from_extent:
        # each centre may sit up to ρ from where the centre line assumes: the line turns by up to
        # asin((ρ_p + ρ_q) / length) (any angle when that exceeds 1)
        ratio = (geo.rho[crops[:, 0]] + geo.rho[crops[:, 1]]) / np.maximum(geo.o_len[cand.label], 1e-9)
        bound = np.where(ratio < 1, np.arcsin(np.minimum(ratio, 1.0)), np.pi)
        rot_window = np.maximum(rot_window, np.minimum(bound, np.deg2rad(anchor.rotation_window_max_deg)))
    # same-segment labels have no over-view centre line: any rotation
    same = crops[:, 0] == crops[:, 1]
    rot_window[same] = np.pi
    if angle_deg is not None:  # same-segment labels are centred on the prior heading
        rot_window[same & np.isfinite(cand.theta_prior)] = np.deg2rad(angle_deg)
    return rot_window


@dataclass(frozen=True)
class _ChunkBest:
    """The best hypothesis of the pairs ``dst`` of one chunk, and how many were scored."""

    dst: np.ndarray
    cost: np.ndarray
    theta: np.ndarray
    pivot: np.ndarray
    n: int


def _best_hypotheses(score: Scorer, geo: PairGeometry, cand: Candidates, samples: StreetSamples,
                     anchors: AN.Anchors, usable: np.ndarray, stats: dict, *, anchor: AN.AnchorConfig,
                     rotation_window_deg: float, angle_deg: float | None, prior_term: PriorTerm | None = None) -> Scored:
    """Each pair at its best anchored hypothesis (cost +inf and the centre-line pose: none)."""
    pairs = cand.pairs
    s_anchor, s_dir, _ = samples.walls
    rot_window = _rotation_windows(geo, cand, anchor, rotation_window_deg, angle_deg)
    prior_window = np.deg2rad(angle_deg) if angle_deg is not None else np.pi
    o_mid = geo.o_mid[cand.label]
    P = len(pairs.edge)
    chunk = max(1, score.max_elements // 400)

    def best_hypothesis(start: int) -> _ChunkBest | None:
        idx = np.arange(start, min(P, start + chunk))
        hp, hyp = AN.hypotheses(score.atlas, geo.A, geo.px0, anchors, pairs.take(idx), s_anchor, s_dir, usable,
                                geo.edges, geo.s_mid, o_mid[idx], cand.reach_m[idx], rot_window[idx], anchor.tolerance_px,
                                anchor.max_hypotheses, cand.theta_prior[idx], prior_window, cand.prior_mid[idx],
                                cand.prior_radius_m[idx])
        if len(hp) == 0:
            return None
        h_cost, h_theta, _ = score(1, samples.coarse_pts, hyp, np.zeros(1), np.zeros((1, 2)))
        rank = h_cost if prior_term is None else h_cost + prior_term(idx[hp], h_theta, hyp.pivot_px)
        # ties broken by the pose itself, not by which end of the edge anchored it
        order = np.lexsort((hyp.pivot_px[:, 1].round(6), hyp.pivot_px[:, 0].round(6), rank, hp))
        first = order[np.r_[True, hp[order][1:] != hp[order][:-1]]]
        return _ChunkBest(idx[hp[first]], h_cost[first], h_theta[first], hyp.pivot_px[first], len(hp))

    cost = np.full(P, np.inf)
    theta, pivot = pairs.theta.copy(), pairs.pivot_px.copy()
    n_hyp = 0
    for res in map_in_order(best_hypothesis, range(0, P, chunk), score.workers):
        if res is not None:
            cost[res.dst], theta[res.dst], pivot[res.dst] = res.cost, res.theta, res.pivot
            n_hyp += res.n
    stats["hypotheses"] = n_hyp
    return Scored(cost, CH.Pairs(pairs.edge, pairs.crops, theta, pivot, pairs.offset))


def refine_best(score: Scorer, coarse: Scored, samples: StreetSamples, levels: SearchLevels,
                pose: PoseSearchConfig, stats: dict) -> Scored:
    """The refine_top_k best pairs of each edge refined level by level with all points; the others
    at their coarse pose on the exact map, with all points within the look-up budget."""
    c_pairs, pts_f = coarse.pairs, samples.fine_pts
    top = top_k_per_group(c_pairs.edge, coarse.cost, pose.refine_top_k, c_pairs.pivot_px + c_pairs.offset)
    ref = c_pairs.take(top)
    r_cost = coarse.cost[top]
    for lv in levels.levels[1:]:
        r_cost, r_theta, r_off = score(lv.erosion_px, pts_f, ref, np.array([-1.0, 0.0, 1.0]) * lv.rotation_rad,
                                       CH.grid_offsets(lv.offset_px, lv.offset_px))
        ref = CH.Pairs(ref.edge, ref.crops, r_theta, ref.pivot_px, r_off)
    if len(levels.levels) == 1:  # nothing to refine: score the best on the exact map with all points
        r_cost = score.at_pose(0, pts_f, ref)
    P = len(c_pairs.edge)
    rest = np.setdiff1d(np.arange(P), top)
    cost = np.empty(P)
    cost[top] = r_cost
    theta, offset = c_pairs.theta.copy(), c_pairs.offset.copy()
    theta[top], offset[top] = ref.theta, ref.offset
    if len(rest):
        all_points = len(rest) * 2 * pts_f.xy.shape[1] <= pose.rescore_budget
        stats["rescored_with_all_points"] = all_points
        cost[rest] = score.at_pose(0, pts_f if all_points else samples.coarse_pts, c_pairs.take(rest))
    stats["refined"] = len(top)
    return Scored(cost, CH.Pairs(c_pairs.edge, c_pairs.crops, theta, c_pairs.pivot_px, offset))


def halvings(step: int) -> list[int]:
    """[step, step/2, ..., 1] with step rounded down to a power of two."""
    s = 1 << int(np.floor(np.log2(max(1, step))))
    out = []
    while s >= 1:
        out.append(s)
        s //= 2
    return out


def top_k_per_group(group: np.ndarray, score: np.ndarray, k: int, tie: np.ndarray) -> np.ndarray:
    """Indices of the k lowest scores within each group, sorted; ties broken by ``tie`` (P,2)."""
    order = np.lexsort((tie[:, 1].round(6), tie[:, 0].round(6), score, group))
    g = group[order]
    first = np.searchsorted(g, g, side="left")
    rank = np.arange(len(g)) - first
    return np.sort(order[rank < k])
