"""Common tail of the refine stages: fill missing heights, compose Eq. 5, reject inconsistent ones."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from toolkit.params import ParamGroup
from toolkit.refine.consistency import reject_inconsistent, reject_minor_components, reject_route_minorities
from toolkit.refine.segments import input_anchors
from toolkit.refine.transforms import compose_eq5
from toolkit.types import SegmentTransforms, StreetSegments


class ConsistencyParams(ParamGroup):
    """The neighbour-consistency check (``steps.refine.params.consistency``; old flat keys in flat_names)."""

    flat_names: ClassVar[dict[str, str]] = {
        "enabled": "check_consistency", "k": "neighbours_k", "tol_m": "consistency_tol_m",
        "tol_ratio": "consistency_tol_ratio", "groups": "reject_groups", "route_window_m": "route_window_m"}

    enabled: bool = Field(True, description="reject segments whose transform disagrees with their neighbours'")
    k: int = Field(4, ge=1, description="neighbours compared in the consistency check and for filling missing heights (count)")
    tol_m: float = Field(3.0, gt=0, description="allowed gap between neighbouring transforms at their segment centres (metres) ...")
    tol_ratio: float = Field(0.05, ge=0, description="... plus this fraction of the distance between the segments (drift grows with distance)")
    min_neighbours: int = Field(2, ge=0, description="a segment is judged only with more valid segments than this (count)")
    groups: bool = Field(False, description="also reject groups of mutually consistent segments that disagree with the best-supported group")
    route_window_m: float = Field(150.0, ge=0, description="reject a segment disagreeing with over half the segments within this route distance "
                                                         "(m; route-aware only; 0: off)")


def fill_heights(t_z: np.ndarray, valid: np.ndarray, centroids: np.ndarray, k: int,
                 centres: np.ndarray) -> np.ndarray:
    """Segments without a height offset take the median of their k nearest segments that have one;
    when none has one (no height source), each segment's ground centre goes to 0 m (relative heights)."""
    t_z = t_z.copy()
    known = np.isfinite(t_z) & valid
    missing = np.flatnonzero(~np.isfinite(t_z))
    if len(missing) == 0:
        return t_z
    if not known.any():
        t_z[missing] = -np.asarray(centres, np.float64)[missing, 2]
        return t_z
    src = np.flatnonzero(known)
    _, nn = cKDTree(centroids[src]).query(centroids[missing], k=min(k, len(src)))
    t_z[missing] = np.median(t_z[src][np.reshape(nn, (len(missing), -1))], axis=1)
    return t_z


def warn_heights(t_z: np.ndarray, valid: np.ndarray, obs, uncovered: np.ndarray | None = None,
                 source: str = "") -> None:
    """One warning when no registered segment had an over-view ground height (relative heights), or
    when the height ``source`` does not cover some registered segments (``uncovered``: (S,) bool)."""
    n = int(valid.sum())
    if n == 0:
        return
    if not (valid & np.isfinite(t_z)).any():
        obs.warn("no over-view ground height (no DSM, terrain model or over-view cloud under the street): "
                 "heights are relative, the street ground at 0 m")
    elif uncovered is not None and (missing := int((valid & uncovered).sum())):
        obs.warn(f"the {source or 'height source'} does not cover {missing} of {n} registered segments "
                 f"({missing / n:.0%}): their heights follow their neighbours'")


def compose(street: StreetSegments, T2d: np.ndarray, R_z: np.ndarray, t_z: np.ndarray, centres: np.ndarray,
            valid: np.ndarray, k: int, obs, levelled_override: dict[int, np.ndarray] | None = None,
            scaling: np.ndarray | None = None) -> np.ndarray:
    """(S,4,4) INPUT street frame → scene transforms (Eq. 5 after the levelling).

    ``levelled_override``: complete levelled → scene transforms for some segments (used as given).
    ``scaling``: (S,4,4) maps of the levelled frame applied before Eq. 5 (per-segment scale).
    """
    S = len(street)
    if S == 0:
        return np.zeros((0, 4, 4))
    cent = np.asarray(street.centroids, np.float64).reshape(-1, 2)
    t_z = fill_heights(t_z, valid, cent, k, centres)
    override = levelled_override or {}
    pre = [np.eye(4)] * S if scaling is None else scaling
    return np.stack([(override[i] if i in override else compose_eq5(T2d[i], R_z[i], t_z[i], centres[i]) @ pre[i])
                     @ street.levelling for i in range(S)])


def consistent(T: np.ndarray, valid: np.ndarray, street: StreetSegments, cp: ConsistencyParams, graphs,
               support: np.ndarray | None = None, keys: np.ndarray | None = None,
               protected: np.ndarray | None = None, route_s: np.ndarray | None = None) -> np.ndarray:
    """``valid`` without the segments that disagree with their neighbours (when enabled): single
    outliers, then runs of wrong ones outvoted along the route (when ``route_s`` is known), then
    (``cp.groups``) groups that disagree with the best-supported consistent component."""
    if not cp.enabled or valid.sum() <= cp.min_neighbours:
        return valid.copy()
    extra = None
    if graphs is not None and getattr(graphs, "street_graph", None) is not None:
        g = graphs.street_graph
        extra = [set(g.neighbors(i)) if i in g else set() for i in range(len(street))]
    anchors = input_anchors(street)
    new_valid, _ = reject_inconsistent(T, valid, anchors, cp.k, cp.tol_m, cp.tol_ratio, cp.min_neighbours, extra,
                                       keys, protected)
    if support is None:
        support = np.bincount(np.asarray(street.carrier)[np.asarray(street.carrier) >= 0], minlength=len(street))
    if route_s is not None and np.isfinite(route_s).any() and cp.route_window_m > 0:
        new_valid = reject_route_minorities(T, new_valid, anchors, route_s, np.asarray(support, np.float64),
                                            cp.route_window_m, cp.tol_m, cp.tol_ratio, protected)
    if not cp.groups:
        return new_valid
    return reject_minor_components(T, new_valid, anchors, np.asarray(support, np.float64), cp.k, cp.tol_m,
                                   cp.tol_ratio, extra, keys)


def warn_rejected(street: StreetSegments, before: np.ndarray, after: np.ndarray, obs) -> None:
    dropped = np.flatnonzero(before & ~after)
    if len(dropped):
        obs.warn(f"rejected {len(dropped)} segment(s) inconsistent with their neighbours: "
                 f"{', '.join(str(int(street.ids[i])) for i in dropped[:10])}")


def finish(street: StreetSegments, T2d: np.ndarray, R_z: np.ndarray, t_z: np.ndarray, centres: np.ndarray,
           valid: np.ndarray, cost: np.ndarray, confidence: np.ndarray, cp: ConsistencyParams, graphs, obs,
           levelled_override: dict[int, np.ndarray] | None = None) -> SegmentTransforms:
    """Compose, check consistency, package (input street frame → scene CRS)."""
    T = compose(street, T2d, R_z, t_z, centres, valid, cp.k, obs, levelled_override)
    new_valid = consistent(T, valid, street, cp, graphs)
    warn_heights(t_z, new_valid, obs)
    warn_rejected(street, valid, new_valid, obs)
    if not new_valid.any():
        obs.warn("no street segment could be registered (no match survived refinement)")
    return SegmentTransforms(T=T, valid=new_valid, cost=cost, confidence=np.where(new_valid, confidence, 0.0))
