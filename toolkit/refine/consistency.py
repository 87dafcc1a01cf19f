"""Smoothness across neighbouring segments: one bad segment must not fly away.

Neighbouring street segments were distorted by nearly the same drift, so their transforms should
nearly agree where they meet. Two transforms are compared at both segments' centres (the largest
gap between the images of those points); the gap is normalised by a tolerance that grows with the
distance between the segments (drift accumulates along the route): ``tol_m + tol_ratio · d``.
A segment whose (lower) median normalised gap to its valid neighbours exceeds 1 is rejected (it is then
carried by its neighbours' blended transforms in the warp); the worst one goes first and the test
is repeated, so a single outlier cannot make its good neighbours look bad.

A run of wrong matches can agree among itself (e.g. several segments matched one block over) and
survive that test. So, second, when the route position of the segments is known (from the COLMAP
model, ``toolkit.refine.route``): a segment whose transform disagrees with more than half of the
(support-weighted) segments captured within a window along the route is rejected, worst first.
Optionally (``reject_minor_components``): segments linked by agreeing neighbour pairs form components; the
component with the most support (points × confidence) is kept, and any other component that
borders it through disagreeing pairs is rejected. Components that touch the main one only through
agreeing pairs are part of it; components with no neighbour pair to it at all are kept. This
cannot tell a wrong group from the segments of another pass of the route (after a loop the drifted
street frame makes them neighbours whose transforms rightly differ) unless the neighbour keys carry
the route position (``toolkit.refine.route``).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree



def gap_matrix(T: np.ndarray, anchors: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(P,) largest gap between T_i and T_j at anchors i and j, for index pairs (P,2)."""
    i, j = pairs[:, 0], pairs[:, 1]
    out = np.zeros(len(pairs))
    for a in (anchors[i], anchors[j]):
        pi = np.einsum("pab,pb->pa", T[i, :3, :3], a) + T[i, :3, 3]
        pj = np.einsum("pab,pb->pa", T[j, :3, :3], a) + T[j, :3, 3]
        out = np.maximum(out, np.linalg.norm(pi - pj, axis=1))
    return out


def reject_inconsistent(T: np.ndarray, valid: np.ndarray, anchors: np.ndarray, k: int, tol_m: float,
                        tol_ratio: float, min_neighbours: int = 2,
                        extra_neighbours: list[set[int]] | None = None,
                        keys: np.ndarray | None = None,
                        protected: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Greedy rejection; returns (valid, median normalised gap per segment (NaN: not judged)).

    ``anchors``: (S,3) segment centres in the input frame; ``keys``: coordinates for the neighbour
    search (default the anchors; ``toolkit.refine.route.neighbour_keys`` adds the route position);
    ``protected``: segments that are judges only (already accepted), never rejected.
    """
    keys = anchors if keys is None else keys
    valid = valid.copy()
    S = len(valid)
    score = np.full(S, np.nan)
    extra = np.zeros((0, 2), np.int64)
    if extra_neighbours is not None:
        extra = np.array([(i, j) for i in range(S) for j in extra_neighbours[i] if j != i], np.int64).reshape(-1, 2)
    while valid.sum() > min_neighbours:
        idx = np.flatnonzero(valid)
        kk = min(k + 1, len(idx))
        _, nn = cKDTree(keys[idx]).query(keys[idx], k=kk)
        nn = idx[np.atleast_2d(nn)]
        pairs = np.column_stack([np.repeat(idx, nn.shape[1]), nn.ravel()])
        pairs = np.concatenate([pairs, extra[valid[extra[:, 0]] & valid[extra[:, 1]]]])
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        pairs = np.unique(pairs[:, 0] * S + pairs[:, 1])          # each (segment, neighbour) once
        pairs = np.column_stack(np.divmod(pairs, S))
        dist = np.linalg.norm(anchors[pairs[:, 1]] - anchors[pairs[:, 0]], axis=1)
        ratio = gap_matrix(T, anchors, pairs) / (tol_m + tol_ratio * dist)
        # lower median per segment: rejected only when most neighbours disagree, so the good
        # segments bordering a group of wrong ones are not eroded (a tie keeps the segment)
        order = np.lexsort((ratio, pairs[:, 0]))
        seg = pairs[order, 0]
        count = np.bincount(seg, minlength=S)
        start = np.searchsorted(seg, np.arange(S))
        judge = count >= max(min_neighbours, 1)
        score[:] = np.nan
        score[judge] = ratio[order][start[judge] + (count[judge] - 1) // 2]
        judged = valid if protected is None else valid & ~protected
        worst = int(np.nanargmax(np.where(judged, score, np.nan))) if np.isfinite(score[judged]).any() else -1
        if worst < 0 or score[worst] <= 1.0:
            break
        valid[worst] = False
    return valid, score


def reject_route_minorities(T: np.ndarray, valid: np.ndarray, anchors: np.ndarray, route_s: np.ndarray,
                            support: np.ndarray, window_m: float, tol_m: float, tol_ratio: float,
                            protected: np.ndarray | None = None) -> np.ndarray:
    """Greedy, along the route: reject the segment whose transform disagrees with the largest
    support-weighted share (> 1/2) of the valid segments captured within ``window_m`` of it along
    the route; repeat. Unlike the k-nearest test this outvotes a run of several wrong matches."""
    valid = valid.copy()
    s = np.asarray(route_s, np.float64)
    timed = np.isfinite(s)
    while True:
        idx = np.flatnonzero(valid & timed)
        if len(idx) < 3:
            return valid
        near = np.abs(s[idx, None] - s[None, idx]) <= window_m
        np.fill_diagonal(near, False)
        rows, cols = np.nonzero(near)
        pairs = np.column_stack([idx[rows], idx[cols]])
        dist = np.linalg.norm(anchors[pairs[:, 0]] - anchors[pairs[:, 1]], axis=1)
        disagree = gap_matrix(T, anchors, pairs) > tol_m + tol_ratio * dist
        w = support[pairs[:, 1]]
        total = np.bincount(rows, weights=w, minlength=len(idx))
        against = np.bincount(rows, weights=w * disagree, minlength=len(idx))
        share = np.where(total > 0, against / np.maximum(total, 1e-12), 0.0)
        if protected is not None:
            share[protected[idx]] = 0.0
        worst = int(np.argmax(share))
        if share[worst] <= 0.5:
            return valid
        valid[idx[worst]] = False


def neighbour_pairs(keys: np.ndarray, valid: np.ndarray, k: int,
                    extra_neighbours: list[set[int]] | None = None) -> np.ndarray:
    """(P,2) unique pairs i < j of valid segments that are k-nearest (by ``keys``) or extra neighbours."""
    idx = np.flatnonzero(valid)
    if len(idx) < 2:
        return np.zeros((0, 2), np.int64)
    _, nn = cKDTree(keys[idx]).query(keys[idx], k=min(k + 1, len(idx)))
    nn = idx[np.atleast_2d(nn)]
    pairs = [(int(i), int(j)) for row, i in enumerate(idx) for j in nn[row] if j != i]
    if extra_neighbours is not None:
        pairs += [(int(i), int(j)) for i in idx for j in extra_neighbours[i] if valid[j] and j != i]
    if not pairs:
        return np.zeros((0, 2), np.int64)
    p = np.sort(np.array(pairs, np.int64), axis=1)
    return np.unique(p, axis=0)


def reject_minor_components(T: np.ndarray, valid: np.ndarray, anchors: np.ndarray, support: np.ndarray, k: int,
                            tol_m: float, tol_ratio: float,
                            extra_neighbours: list[set[int]] | None = None,
                            keys: np.ndarray | None = None) -> np.ndarray:
    """``valid`` without the components that disagree with the best-supported one (see module doc)."""
    pairs = neighbour_pairs(anchors if keys is None else keys, valid, k, extra_neighbours)
    if len(pairs) == 0:
        return valid.copy()
    dist = np.linalg.norm(anchors[pairs[:, 0]] - anchors[pairs[:, 1]], axis=1)
    agree = gap_matrix(T, anchors, pairs) <= tol_m + tol_ratio * dist
    S = len(valid)
    a = pairs[agree]
    graph = coo_matrix((np.ones(len(a)), (a[:, 0], a[:, 1])), shape=(S, S))
    _, comp = connected_components(graph, directed=False)
    comp = np.where(valid, comp, -1)
    labels = np.unique(comp[comp >= 0])
    score = np.array([support[comp == c].sum() for c in labels])
    main = labels[int(np.argmax(score))]
    bad = pairs[~agree]
    ci, cj = comp[bad[:, 0]], comp[bad[:, 1]]
    against_main = np.unique(np.concatenate([cj[ci == main], ci[cj == main]]))
    out = valid.copy()
    out[np.isin(comp, against_main[against_main != main])] = False
    return out
