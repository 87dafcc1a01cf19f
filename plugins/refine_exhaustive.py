"""refine.exhaustive — the paper's fine registration (§3.3.2, Eq. 5), one street segment at a time.

For every matched segment:
1. 3D tilt: the segment's street ground normal (ground normals within [15°] of vertical,
   median-filtered) is rotated onto the over-view ground normal around it (a plane fitted to the
   DSM / over-view cloud heights under the street ground points; level when neither exists).
2. 2D: exhaustive search of rotation within ±[10°] at [1°] and of every one-pixel offset that keeps
   the footprint inside the over-view segment's window (its bounding box plus a margin), on the
   chamfer distance to the over-view segment's outline; then sub-pixel refinement
   (``toolkit.refine.search2d``). A small penalty per metre of shift keeps the match's position
   where the outline cannot fix it (a single straight wall slides along itself at equal cost).
3. Height: t_z = robust difference between over-view and street ground heights (10–60 % slice).
4. Eq. 5: T = [[R2d, 0], [0, 1]]·R_Z, t = [t2d | t_z] (R_Z about the segment's ground centre),
   composed with the levelling so that T maps the INPUT street frame to the scene CRS.
Then a segment whose transform disagrees strongly with its neighbours' is rejected
(``toolkit.refine.consistency``) and left to the warp to carry with its neighbours; with the route
position of each segment (from the COLMAP model, ``toolkit.refine.route``) neighbours are those
near in space AND along the route, and a run of wrong matches is outvoted along the route.
Beyond the paper: segments left without a match (or whose match was rejected) are placed by their
registered neighbours and searched against every over-view outline around them
(``toolkit.refine.propagate``); they must pass the same inlier and consistency tests. Then every
segment is searched once more, seeded by its neighbours (``neighbour_passes``): along a single
straight wall the outline cannot place a segment, its neighbours can.
Finally (``joint_window_m`` > 0, route-aware), each segment's 2D transform is re-estimated by
registering together the footprints of all segments captured within that distance along the route
(``toolkit.refine.joint``): the per-building errors of the over-view outlines (OSM digitising
offsets, label-map edges) average out over several buildings, and other buildings' corners fix the
position along straight walls. With ``rotation_window_m`` > 0, each segment's rotation is then the
mean of its route neighbours' (``toolkit.refine.rotation``), turned about its own footprint centre:
a compact façade fixes its rotation weakly, and the ground it carries far from it follows that error.
Before the neighbour passes, each segment gets a scale (``scale``, ``toolkit.refine.scale``): the
ratio of its registered to its input distance from the segments captured near it along the route,
within 1 ± ``scale.max_deviation``; the later passes search its footprint at that scale, so the
transforms are similarities (monocular SfM drifts slowly in scale, which rigid segments cannot follow).
"""

from __future__ import annotations

from functools import partial
from typing import Literal

import numpy as np
from pydantic import Field
from scipy import ndimage

from toolkit.forked import map_chunks_forked
from toolkit.observe import DebugPoints2D
from toolkit.refine.blas import single_threaded_blas
from toolkit.refine.finish import ConsistencyParams, compose, consistent, warn_heights, warn_rejected
from toolkit.refine.ground3d import GroundParams, ground_step, height_source, prepare_ground
from toolkit.refine.joint import JointParams, joint_transforms
from toolkit.refine.propagate import footprint_window, predict_seed
from toolkit.refine.route import neighbour_keys, route_positions
from toolkit.refine.scale import ScaleConfig, route_scales, scaling_about
from toolkit.refine.rotation import smoothed_rotations
from toolkit.refine.search2d import AllOutlines, SearchParams, search_segments
from toolkit.refine.transforms import apply_each
from toolkit.refine.segments import SegmentPoints, input_anchors
from toolkit.stage import Stage, StageParams
from toolkit.types import Matches, OverviewSegments, Scene, SegmentTransforms, StreetSegments


class Exhaustive(Stage):
    """Paper §3.3.2: exhaustive 2D rotation/offset search + 3D ground normal and height step (Eq. 5)."""

    kind = "refine"
    name = "exhaustive"

    class Params(StageParams):
        rotation_range_deg: float = Field(10.0, ge=0, le=45, description="Rotation searched either side of the match (paper: 10°).")
        rotation_step_deg: float = Field(1.0, gt=0, le=10, description="Rotation step of the search (paper: 1°).")
        margin_m: float = Field(5.0, ge=0, description="Offsets keep the footprint centre within the over-view segment's bounding box grown by this (metres).")
        truncate_m: float = Field(3.0, gt=0, description="Chamfer distances are truncated at this (metres), so parts missing from the over-view do not dominate.")
        inlier_m: float = Field(1.0, gt=0, description="Footprint points closer than this to the outline are inliers (metres; sub-pixel step and inlier ratio).")
        shift_penalty: float = Field(0.03, ge=0, description="Added cost per metre of shift from the match (metres of chamfer per metre), a tie-breaker along straight walls.")
        subpixel: bool = Field(True, description="Refine the grid optimum below one pixel (parabola + Gauss-Newton on the signed outline distance).")
        footprint_cell_m: float = Field(0.25, gt=0, description="Façade points are thinned to one per cell of this size before the search (metres).")
        max_footprint_points: int = Field(4000, ge=10, description="At most this many footprint points per segment.")
        normal_max_angle_deg: float = Field(15.0, gt=0, lt=90, description="Ground normals within this angle of vertical define the street ground normal (paper: 15°).")
        min_ground_points: int = Field(30, ge=3, description="Fewer ground points than this: no tilt, height from the neighbours.")
        max_tilt_deg: float = Field(5.0, ge=0, description="A tilt correction larger than this is distrusted and skipped (degrees).")
        min_inlier_ratio: float = Field(0.2, ge=0, le=1, description="A segment whose footprint has a smaller inlier share after the search is rejected.")
        check_consistency: bool = Field(True, description="Reject segments whose transform disagrees with their neighbours'.")
        neighbours_k: int = Field(4, ge=1, description="Neighbours compared in the consistency check and "
                                                       "for filling missing heights (count).")
        consistency_tol_m: float = Field(3.0, gt=0, description="Allowed gap between neighbouring transforms at their segment centres (metres) ...")
        consistency_tol_ratio: float = Field(0.05, ge=0, description="... plus this fraction of the distance between the segments (drift grows with distance).")
        route_aware: bool = Field(
            True, description="Find neighbours by position and by position along the route (from "
                              "COLMAP), so another pass's segments are not neighbours")
        route_window_m: float = Field(
            150.0, ge=0, description="Reject a segment disagreeing with over half the segments within "
                                     "this route distance (m; route-aware only; 0: off)")
        reject_groups: bool = Field(
            False, description="Also reject groups of mutually consistent segments "
                               "that disagree with the best-supported group")
        propagate: bool = Field(True, description="Also register unmatched segments, seeded by registered neighbours' transforms, against every outline near them")
        propagated_confidence: float = Field(0.5, ge=0, le=1, description="Confidence factor of a segment registered by propagation (times its inlier share).")
        neighbour_passes: int = Field(1, ge=0, le=5, description="Extra passes re-searching every registered segment from its neighbours' blended transforms (count; 0: the paper's one)")
        prior_k: int = Field(8, ge=1, description="Neighbours blended into that seed (count; weights 1/log d).")
        joint_window_m: float = Field(
            50.0, ge=0, description="Re-fit each 2D transform jointly with the segments within "
                                    "this route distance (m; route-aware only; 0: off)")
        joint_rotation_deg: float = Field(2.0, ge=0, description="Joint pass: rotation searched either side of the segment's own (degrees).")
        joint_shift_m: float = Field(2.0, ge=0, description="Joint pass: offsets searched either side of the segment's own (metres).")
        joint_segment_points: int = Field(
            0, ge=0, description="Joint pass: cap on footprint points (0.5 m cells) per segment (count; 0: all)")
        joint_outline_points: int = Field(
            0, ge=0, description="Joint pass: cap on footprint points (0.5 m cells) "
                                 "per over-view outline (count; 0: all)")
        joint_kernel: Literal["box", "tricube"] = Field(
            "box", description="Joint pass weighting by route distance Δs: 'box' (all "
                               "equal) or 'tricube' ((1 − (Δs/window)³)³)")

        rotation_window_m: float = Field(
            0.0, ge=0, description="Set each rotation to the weighted mean rotation of segments "
                                   "within this route distance (m; route-aware only; 0: off)")
        scale: ScaleConfig = Field(default_factory=ScaleConfig,
                                   description="per-segment scale from the route neighbours (route-aware only)")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("street_cloud",)

    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 obs, graphs=None) -> SegmentTransforms:
        with single_threaded_blas():
            return self._run(matches, street, overview, scene, obs, graphs)

    def _run(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
             obs, graphs=None) -> SegmentTransforms:
        from toolkit.scene import load_points

        p = self.params
        sp = SearchParams(p.rotation_range_deg, p.rotation_step_deg, p.margin_m, p.truncate_m, p.inlier_m,
                          p.shift_penalty, p.subpixel)
        gp = GroundParams(normal_max_angle_deg=p.normal_max_angle_deg, min_ground_points=p.min_ground_points,
                          max_tilt_deg=p.max_tilt_deg)
        cp = ConsistencyParams(p.check_consistency, p.neighbours_k, p.consistency_tol_m, p.consistency_tol_ratio,
                               groups=p.reject_groups, route_window_m=p.route_window_m)
        S = len(street)
        pts = SegmentPoints(street, scene)
        heights = height_source(scene, overview)
        boxes = ndimage.find_objects(np.asarray(overview.label_image) + 1, max_label=len(overview))
        st = _State(S, obs.wants_debug)
        st.outlines = AllOutlines(overview.grid, overview.label_image, p.truncate_m)
        anchors = input_anchors(street)
        route_s = route_positions(street, scene, load_points(scene, "street_cloud")) if p.route_aware \
            else np.full(S, np.nan)
        st.keys = neighbour_keys(anchors, route_s)
        st.route_s = route_s
        matched = []
        for i in obs.progress(range(S), total=S, desc="refine segments"):
            o = int(matches.segment_match[i])
            if o < 0 or o >= len(overview) or boxes[o] is None:
                continue
            matched.append((i, np.asarray(matches.T2d[i], np.float64), o, boxes[o], overview.ground_normal[o],
                            float(overview.ground_height[o]), float(matches.confidence[i])))
        self._register(matched, pts, overview, heights, sp, gp, st)
        T = compose(street, st.T2d, st.R_z, st.t_z, st.centres, st.valid, cp.k, obs, scaling=st.scaling)
        carrier = np.asarray(street.carrier)
        st.points = np.bincount(carrier[carrier >= 0], minlength=S).astype(np.float64)
        valid = consistent(T, st.valid, street, cp, graphs, st.points * st.conf, st.keys, route_s=st.route_s)
        warn_rejected(street, st.valid, valid, obs)
        if p.propagate:
            T, valid = self._propagate(street, overview, graphs, pts, heights, sp, gp, cp, st, T, valid, obs)
        if p.scale.max_deviation > 0 and np.isfinite(route_s).any():
            self._set_scales(street, pts, st, T, valid)
        for _ in range(p.neighbour_passes):
            T, valid = self._neighbour_pass(street, overview, graphs, pts, heights, sp, gp, cp, st, T, valid, obs)
        if p.scale.max_deviation > 0 and p.neighbour_passes and np.isfinite(route_s).any():
            self._set_scales(street, pts, st, T, valid)     # again, from the better placed centres
        if (p.joint_window_m > 0 or p.rotation_window_m > 0) and np.isfinite(route_s).any():
            T = self._route_pass(street, overview, pts, heights, gp, cp, st, valid, obs)
        if not valid.any():
            obs.warn("no street segment could be registered (no match survived refinement)")
        self._warn_heights(street, scene, heights, T, valid, st, obs)
        if obs.wants_debug and st.shown:
            xy = np.concatenate([s for _, s in st.shown])
            ids = np.concatenate([np.full(len(s), i) for i, s in st.shown])
            obs.debug("footprints_registered", DebugPoints2D(xy, class_ids=ids))
        return SegmentTransforms(T=T, valid=valid, cost=st.cost, confidence=np.where(valid, st.conf, 0.0))

    def _register(self, items, pts, overview, heights, sp, gp, st) -> list[bool]:
        """Tilt, exhaustive 2D search and height of segments, each item (i, seed, over-view segment o
        or None: all, window, over-view ground normal, height, match confidence); whether each is
        registered. The items are searched in forked children beside this process when there are
        cores to spare (``toolkit.forked``: these searches keep the GIL, so threads gain nothing)."""
        p = self.params
        for i, _, o, box, o_normal, o_height, match_conf in items:
            st.target[i] = (o, box, o_normal, o_height, match_conf)
            self._prepared_ground(i, pts, gp, st)  # here, so that the cache outlives the children
        found = map_chunks_forked(partial(self._search_items, pts, overview, heights, sp, gp, st), items)
        registered = {}
        for (i, *_, match_conf), fit in zip(items, found):
            if fit is None:
                continue
            st.T2d[i], st.R_z[i], st.t_z[i], st.centres[i], st.cost[i], inlier_ratio, shown = fit
            st.conf[i] = match_conf * inlier_ratio
            st.valid[i] = inlier_ratio >= p.min_inlier_ratio
            if st.debug:
                st.shown.append((i, shown))
            registered[i] = bool(st.valid[i])
        return [registered.get(item[0], False) for item in items]

    def _search_items(self, pts, overview, heights, sp, gp, st, items) -> list[tuple | None]:
        """Per item: (T2d, R_z, t_z, centre, cost, inlier ratio, registered footprint or None), or None
        when its footprint is too small. Reads ``st`` only. The searches' sub-pixel steps run together
        (``search_segments``: the same results as one segment at a time, ~100 → ~25 numpy calls per
        segment and step)."""
        p = self.params
        ready, footprints = [], []
        for item in items:
            i, seed, o, box, o_normal, o_height, match_conf = item
            g0 = self._ground_step(i, seed, pts, heights, o_normal, o_height, gp, st, with_height=False)  # tilt only
            fp = pts.footprint(i, p.footprint_cell_m, p.max_footprint_points, g0.R_z, g0.centre)
            if len(fp) >= 10:
                ready.append(item)
                footprints.append(fp)
        results = search_segments([(fp, item[1], item[2], item[3]) for item, fp in zip(ready, footprints)],
                                  overview.grid, overview.label_image, sp, st.outlines, with_seed_cost=False)
        fits = {}
        for (i, _, _, _, o_normal, o_height, _), fp, res in zip(ready, footprints, results):
            g1 = self._ground_step(i, res.T2d, pts, heights, o_normal, o_height, gp, st)
            shown = fp @ res.T2d[:2, :2].T + res.T2d[:2, 2] if st.debug else None
            fits[i] = (res.T2d, g1.R_z, g1.t_z, g1.centre, res.cost_m, res.inlier_ratio, shown)
        return [fits.get(item[0]) for item in items]

    @staticmethod
    def _prepared_ground(i, pts, gp, st):
        """Segment i's ``prepare_ground`` (its transform-independent ground part), computed once."""
        if i not in st.ground:
            ground, gnormals = pts.ground(i)
            st.ground[i] = prepare_ground(ground, gnormals, gp)
        return st.ground[i]

    @classmethod
    def _ground_step(cls, i, T2d, pts, heights, o_normal, o_height, gp, st, with_height=True):
        """``ground_step`` of segment i, its transform-independent part computed once per segment."""
        ground, gnormals = pts.ground(i)
        return ground_step(ground, gnormals, T2d, heights, o_normal, o_height, gp,
                           prepared=cls._prepared_ground(i, pts, gp, st), with_height=with_height)

    def _placed_by_neighbours(self, i, known, k, street, overview, pts, st, T):
        """(seed transform, over-view window) for segment i as its k nearest ``known`` neighbours place
        it; None when it has none."""
        p = self.params
        fp = pts.footprint(i, p.footprint_cell_m, p.max_footprint_points)
        gz = street.ground_z[i] if np.isfinite(street.ground_z[i]) else 0.0
        seed = predict_seed(fp, gz, street, T, known, i, k, st.keys)
        if seed is None:
            return None
        return seed, footprint_window(fp @ seed[:2, :2].T + seed[:2, 2], overview.grid)

    def _neighbour_pass(self, street, overview, graphs, pts, heights, sp, gp, cp, st, T, valid, obs):
        """Search every registered segment again, seeded where its neighbours put it.

        The outline fixes a segment across its walls; along a single straight wall it cannot, and
        the seed's position stays (shift penalty). The neighbours' transforms, blended at the
        segment (leaving it out), place it better along the wall than the match does: on campus
        seed 0 (DSM) the median along-wall error of straight walls fell from 0.56 m (match) to
        0.28 m and the 90th percentile, all segments, from 2.7 m to 0.8 m.
        """
        p = self.params
        before = valid.copy()
        items = []
        for i in np.flatnonzero(valid):
            others = valid.copy()
            others[i] = False
            placed = self._placed_by_neighbours(i, others, p.prior_k, street, overview, pts, st, T)
            if placed is None:
                continue
            seed, box = placed          # every outline around the predicted place: the match may be wrong
            _, _, o_normal, o_height, conf = st.target[i]
            items.append((i, seed, None, box, o_normal, o_height, conf))
        self._register(items, pts, overview, heights, sp, gp, st)
        T = compose(street, st.T2d, st.R_z, st.t_z, st.centres, before & st.valid, cp.k, obs, scaling=st.scaling)
        valid = consistent(T, before & st.valid, street, cp, graphs, st.points * st.conf, st.keys, route_s=st.route_s)
        warn_rejected(street, before, valid, obs)
        return T, valid

    def _route_pass(self, street, overview, pts, heights, gp, cp, st, valid, obs):
        """Each valid segment's 2D transform re-estimated with its route neighbours' footprints
        (``toolkit.refine.joint``) and its rotation smoothed along the route (``toolkit.refine.rotation``),
        each when its window is > 0, then its tilt and height redone under the new placement."""
        p = self.params
        jp = JointParams(window_m=p.joint_window_m, rotation_deg=p.joint_rotation_deg,
                         rotation_step_deg=min(0.5, p.rotation_step_deg), shift_m=p.joint_shift_m,
                         cell_m=2 * p.footprint_cell_m, max_points=p.max_footprint_points,
                         truncate_m=p.truncate_m, inlier_m=p.inlier_m, segment_points=p.joint_segment_points,
                         outline_points=p.joint_outline_points,
                         kernel=p.joint_kernel)
        idx = np.flatnonzero(valid & np.isfinite(st.route_s))
        fps = {int(i): pts.footprint(i, p.footprint_cell_m, p.max_footprint_points) for i in idx}
        T2d, anchors = st.T2d, input_anchors(street)
        if p.joint_window_m > 0:
            T2d = joint_transforms(fps, T2d, st.route_s, anchors, overview.grid,
                                   np.asarray(overview.label_image), jp, st.outlines,
                                   scale=pts.scale, pivots_xy=pts.pivots[:, :2])
        if p.rotation_window_m > 0:
            centres, sizes = np.zeros((len(street), 2)), np.zeros(len(street))
            for i in idx:
                centres[i], sizes[i] = fps[int(i)].mean(axis=0), len(fps[int(i)])
            T2d = smoothed_rotations(T2d, idx, st.route_s, anchors, centres, np.sqrt(sizes),
                                     p.rotation_window_m)
        level = np.array([0.0, 0.0, 1.0])
        for i in idx:
            _, _, o_normal, o_height, _ = st.target[i] if st.target[i] is not None else (None, None, level, np.nan, 0)
            g = self._ground_step(i, T2d[i], pts, heights, o_normal, o_height, gp, st)
            st.T2d[i], st.R_z[i], st.t_z[i], st.centres[i] = T2d[i], g.R_z, g.t_z, g.centre
        return compose(street, st.T2d, st.R_z, st.t_z, st.centres, valid, cp.k, obs, scaling=st.scaling)

    @staticmethod
    def _warn_heights(street, scene, heights, T, valid, st, obs) -> None:
        """``warn_heights`` with the share of registered segments outside the height source."""
        uncovered = None
        if heights is not None:
            uncovered = ~np.isfinite(heights.sample(apply_each(T, input_anchors(street))[:, :2]))
        source = "DSM" if scene.has("dsm") else "terrain model" if scene.has("dem") else "over-view cloud"
        warn_heights(st.t_z, valid, obs, uncovered, source)

    def _set_scales(self, street, pts, st, T, valid) -> None:
        """Each segment's scale from its route neighbours' registered centres (``toolkit.refine.scale``);
        from here on its points are scaled about its levelled centre."""
        placed = apply_each(T, input_anchors(street))
        lev_xy = np.asarray(street.centroids, np.float64).reshape(-1, 2)
        found = route_scales(placed[:, :2], lev_xy, st.route_s, valid, st.points * st.conf, self.params.scale)
        pivots = np.column_stack([lev_xy, np.nan_to_num(np.asarray(street.ground_z, np.float64), nan=0.0)])
        pts.set_scales(found.scale, pivots)
        st.ground.clear()
        st.scaling = scaling_about(pivots, found.scale)

    def _propagate(self, street, overview, graphs, pts, heights, sp, gp, cp, st, T, valid, obs):
        """Register segments without a surviving match from their registered neighbours' transforms."""
        p = self.params
        level = np.array([0.0, 0.0, 1.0])
        tried = np.zeros(len(street), bool)
        added = 0
        for _ in range(2):          # newly registered segments can seed their own neighbours
            todo = np.flatnonzero(~valid & ~tried & (pts.facade_counts() >= 10))
            if len(todo) == 0 or not valid.any():
                break
            cand = np.zeros(len(street), bool)
            items = []
            for i in todo:
                tried[i] = True
                placed = self._placed_by_neighbours(i, valid, p.neighbours_k, street, overview, pts, st, T)
                if placed is None:
                    continue
                seed, box = placed
                st.valid[i] = False
                items.append((i, seed, None, box, level, np.nan, p.propagated_confidence))
            for (i, *_), registered in zip(items, self._register(items, pts, overview, heights, sp, gp, st)):
                cand[i] = registered
            if not cand.any():
                break
            T = compose(street, st.T2d, st.R_z, st.t_z, st.centres, valid | cand, cp.k, obs, scaling=st.scaling)
            # the newcomers must agree with the accepted segments, never the other way round
            new_valid = consistent(T, valid | cand, street, cp, graphs, st.points * st.conf, st.keys, protected=valid,
                                   route_s=st.route_s)
            added += int((new_valid & cand).sum())
            valid = new_valid
        if added:
            obs.warn(f"registered {added} unmatched segment(s) from their neighbours (propagation)")
        return T, valid


class _State:
    """Per-segment results of the refinement (levelled frame)."""

    def __init__(self, S: int, debug: bool) -> None:
        self.debug = debug
        self.T2d = np.repeat(np.eye(3)[None], S, axis=0)
        self.R_z = np.repeat(np.eye(3)[None], S, axis=0)
        self.t_z, self.centres = np.full(S, np.nan), np.zeros((S, 3))
        self.valid, self.cost, self.conf = np.zeros(S, bool), np.ones(S), np.zeros(S)
        self.shown: list[tuple[int, np.ndarray]] = []
        self.points = np.ones(S)
        self.target: list[tuple | None] = [None] * S
        self.ground: dict[int, object] = {}      # segment → PreparedGround (ground3d.prepare_ground)
        self.keys = np.zeros((S, 1))
        self.route_s = np.full(S, np.nan)
        self.outlines = None                     # search2d.AllOutlines of the over-view
        self.scaling = np.repeat(np.eye(4)[None], S, axis=0)   # levelled-frame pre-maps (segment scales)
