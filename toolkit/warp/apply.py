"""Run a blended warp on the street cloud and the COLMAP cameras → Registration.

A camera is anchored on the segment it looks at: the most frequent valid carrier segment of the
dense street points next to the sparse points it observes. Nearness in the street frame alone is
not enough: after a loop, drift puts the segments of another pass of the route next to the camera.
Nor are the camera's own observations, where the segmentation merged façades of both passes into
one segment: with the pass check on, segments farther along the route than ``pass_gap_m`` from the
camera get no vote. Cameras that see no registered segment fall back to the nearest valid segment
(of their own pass, with the check on).

Points are anchored on their carrier segment (else the nearest valid one); with a COLMAP model and
``pass_gap_m`` set, a point captured on another pass of the route than its anchor segment is
re-anchored on a segment of its own pass (``toolkit.warp.passes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.capture import StreetCapture
from toolkit.matching.route_prior import capture_order
from toolkit.refine.route import camera_route_positions, sparse_segments
from toolkit.threads import map_in_order, single_threaded_blas
from toolkit.types import Registration, SegmentTransforms, SparseModel, StreetSegments
from toolkit.warp.blend import SegmentIndex, blend_rigid
from toolkit.warp.bridge import CameraPoses, bridge_gaps, ground_gap_m, grounded_cameras
from toolkit.warp.cells import levelled_xy
from toolkit.warp.model import PointWarp
from toolkit.warp.passes import point_route_positions, reanchor_other_pass, sparse_route_positions

@dataclass(frozen=True)
class PassCheck:
    """Re-anchoring of points of another pass of the route (see ``toolkit.warp.passes``)."""

    pass_gap_m: float | None = None      # None: off
    max_gap_m: float = 10.0


def camera_anchors(model: SparseModel, dense: np.ndarray, carrier: np.ndarray, valid: np.ndarray,
                   max_gap_m: float = 1.0, seg_of_point: np.ndarray | None = None,
                   same_pass: tuple[np.ndarray, np.ndarray, float] | None = None) -> np.ndarray:
    """(C,) segment each camera observes most (−1: none), via the dense points near its sparse points.

    same_pass: (camera route positions (C,), segment route positions (S,), pass_gap_m): a segment
    farther than pass_gap_m along the route from the camera (another pass) gets no vote from it.
    """
    C = len(model.image_names)
    out = np.full(C, -1, np.int64)
    if len(model.observations) == 0 or len(model.points3d) == 0:
        return out
    if seg_of_point is None:
        seg_of_point = sparse_segments(model, dense, carrier, valid, max_gap_m)
    img = model.observations[:, 0].astype(np.int64)
    seg = seg_of_point[model.observations[:, 1].astype(np.int64)]
    keep = seg >= 0
    if same_pass is not None:
        cam_s, segment_s, gap = same_pass
        with np.errstate(invalid="ignore"):
            keep[keep] = ~(np.abs(cam_s[img[keep]] - segment_s[seg[keep]]) > gap)  # NaN: unknown, kept
    if not keep.any():
        return out
    S = int(max(carrier.max(), seg.max())) + 1
    votes = np.zeros((C, S), np.int64)
    np.add.at(votes, (img[keep], seg[keep]), 1)
    has = votes.sum(axis=1) > 0
    out[has] = votes[has].argmax(axis=1)
    return out


def segment_route_positions(seg_of_point: np.ndarray, sparse_s: np.ndarray, S: int) -> np.ndarray:
    """(S,) lower median route position of the sparse points next to each segment (NaN: none)."""
    ok = (seg_of_point >= 0) & np.isfinite(sparse_s)
    seg, s = seg_of_point[ok], sparse_s[ok]
    order = np.lexsort((s, seg))
    seg, s = seg[order], s[order]
    start = np.searchsorted(seg, np.arange(S))
    count = np.bincount(seg, minlength=S)
    out = np.full(S, np.nan)
    has = count > 0
    out[has] = s[start[has] + (count[has] - 1) // 2]
    return out


def warp_scene(transforms: SegmentTransforms, street: StreetSegments, capture: StreetCapture, k: int, d_min: float,
               agree_tol_m: float = np.inf, agree_ratio: float = 0.0, max_gap_m: float = np.inf,
               cell_m: float = 0.5, passes: PassCheck = PassCheck(), relative: bool = False,
               camera_k: int | None = None, bridge_min_observations: int = 0,
               bridge_min_gap_m: float = 0.0, camera_lever: bool = False) -> Registration:
    """Blend points over their anchor and its k neighbours, cameras over camera_k (None: k); cameras
    that see fewer than ``bridge_min_observations`` registered façade points follow the street path
    between those that do (``toolkit.warp.bridge``; 0: off); ``camera_lever``: ``blend_rigid``'s lever
    weighting for the cameras."""
    with single_threaded_blas():
        return _warp_scene(transforms, street, capture, k, d_min, agree_tol_m, agree_ratio, max_gap_m, cell_m, passes,
                           relative, k if camera_k is None else camera_k, bridge_min_observations,
                           bridge_min_gap_m, camera_lever)


def _warp_scene(transforms: SegmentTransforms, street: StreetSegments, capture: StreetCapture, k: int,
                d_min: float, agree_tol_m: float, agree_ratio: float, max_gap_m: float, cell_m: float,
                passes: PassCheck, relative: bool, camera_k: int, bridge_min_observations: int,
                bridge_min_gap_m: float, camera_lever: bool) -> Registration:
    T = np.asarray(transforms.T, np.float64)
    valid = np.asarray(transforms.valid, bool)
    pts = capture.points
    xy = levelled_xy(street, pts)
    carrier = np.asarray(street.carrier, np.int64)
    model = capture.sparse
    seg_of_point = segment_s = sparse_s = None
    if model is not None and len(model.points3d):
        # the sparse points' segments among the valid carriers (camera anchors) and, for the pass check,
        # among every segment's façade points: a segment is where its façade was captured
        # (toolkit.refine.route), registered or not (a point carried by an unregistered segment takes
        # its pass below). The two searches overlap in threads (their tree builds release the GIL).
        searches = [{"valid": valid}]
        if passes.pass_gap_m is not None:
            searches.append({"valid": np.ones(len(street), bool), "only": np.asarray(street.point_labels) >= 0})
        found = list(map_in_order(lambda kw: sparse_segments(model, pts, carrier, **kw), searches))
        seg_of_point = found[0]
        if passes.pass_gap_m is not None:
            sparse_s = sparse_route_positions(model)
            segment_s = segment_route_positions(found[1], sparse_s, len(street))
            unknown = ~np.isfinite(segment_s)
            segment_s[unknown] = segment_route_positions(seg_of_point, sparse_s, len(street))[unknown]
    # blending neighbours of one pass only (segment_s: None without the pass check)
    index = SegmentIndex.build(street, transforms, max(k, camera_k, 1), agree_tol_m=agree_tol_m,
                               agree_ratio=agree_ratio, max_gap_m=max_gap_m, route_s=segment_s,
                               route_gap_m=np.inf if passes.pass_gap_m is None else passes.pass_gap_m)
    anchors = index.anchors(xy, carrier, valid)
    if segment_s is not None:
        # only points that can be on another pass: anchored off their carrier, or on a segment
        # next to sparse points of several passes (saves most of the 3.5 M nearest-sparse queries)
        ok = (seg_of_point >= 0) & np.isfinite(sparse_s)
        far = np.abs(sparse_s[ok] - segment_s[seg_of_point[ok]]) > passes.pass_gap_m
        multi = np.bincount(seg_of_point[ok][far], minlength=len(street)) > 0
        # (a point whose anchor has no route position is never re-anchored)
        ask = np.flatnonzero(((anchors != carrier) | multi[anchors]) & np.isfinite(segment_s)[anchors])
        point_s = point_route_positions(pts[ask], model.points3d, sparse_s, passes.max_gap_m)
        # no sparse point near it: the point was captured on its carrier's pass (campus seed 5, label
        # map: 35 k points of the route's last metres, their carrier unregistered, had been left on
        # the nearest segment, of the first pass, 21 m off)
        unknown = ~np.isfinite(point_s) & (carrier[ask] >= 0)
        point_s[unknown] = segment_s[carrier[ask][unknown]]
        anchors[ask] = reanchor_other_pass(anchors[ask], xy[ask], point_s, segment_s,
                                           np.asarray(index.all_tree.data), index.all_seg,
                                           passes.pass_gap_m)
    warp = PointWarp(np.asarray(street.origin, np.float64), np.asarray(street.up_rotation, np.float64), T, index,
                     k, d_min, cell_m, relative)
    moved = warp.maps(pts, anchors, xy).apply(pts)
    names: tuple[str, ...] = ()
    R, t, spread = np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0)
    bridged = gap = None
    if model is not None and len(model.image_names):
        names = model.image_names
        C = model.centres
        cxy = street.level(C)[:, :2]
        same_pass = None
        if segment_s is not None:
            cam_s = camera_route_positions(model)
            same_pass = (cam_s, segment_s, passes.pass_gap_m)
        cam_anchor = camera_anchors(model, pts, carrier, valid, seg_of_point=seg_of_point, same_pass=same_pass)
        unseen = cam_anchor < 0
        if unseen.any():
            cam_anchor[unseen] = index.nearest(cxy[unseen])
            if same_pass is not None:  # the nearest segment may be on another pass: as for points
                cam_anchor = reanchor_other_pass(cam_anchor, cxy, np.where(unseen, cam_s, np.nan), segment_s,
                                                 np.asarray(index.all_tree.data), index.all_seg,
                                                 passes.pass_gap_m)
        pos, Rb, spread = blend_rigid(C, cxy, cam_anchor, T, index, camera_k, d_min, relative, camera_lever)
        if bridge_min_observations > 0 and len(model.points3d):
            facade_seg = found[1] if passes.pass_gap_m is not None else sparse_segments(
                model, pts, carrier, np.ones(len(street), bool), only=np.asarray(street.point_labels) >= 0)
            on_registered = (facade_seg >= 0) & valid[np.maximum(facade_seg, 0)]
            grounded = grounded_cameras(model.observations, on_registered, len(C), bridge_min_observations)
            scale = np.cbrt(np.abs(np.linalg.det(T[cam_anchor, :3, :3])))
            seq = capture_order(model.image_names)      # the trajectory in capture order, whatever the model's
            poses, in_gap = bridge_gaps(C[seq], CameraPoses(pos[seq], Rb[seq], scale[seq], spread[seq]),
                                        grounded[seq], bridge_min_gap_m)
            pos, Rb, spread, bridged = pos.copy(), Rb.copy(), spread.copy(), np.zeros(len(C), bool)
            pos[seq], Rb[seq], spread[seq], bridged[seq] = poses.centres, poses.rotations, poses.spread, in_gap
            gap = np.empty(len(C))
            gap[seq] = ground_gap_m(C[seq], grounded[seq])
        R = np.einsum("cab,cdb->cad", model.R, Rb)          # R_wc · R̄ᵀ
        t = -np.einsum("cab,cb->ca", R, pos)
    return Registration(points=moved, image_names=names, R=R, t=t, point_segment=anchors.astype(np.int64, copy=False),
                        camera_spread_m=spread, rows=capture.rows, camera_bridged=bridged, camera_gap_m=gap,
                        warp=warp.with_source(pts, anchors).for_input_frame(capture.scale.value))
