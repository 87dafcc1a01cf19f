"""The matching MRF (Ling & Qin 2022, §3.3.1, Eq. 1–2), laid out so that solvers never touch an L×L table.

Each conjugate node keeps only its *active* labels: the non-null labels cheaper than its null label
(pruned ones cost +inf; one costing at least D(null) is dominated by null, whose V is always c1, so
dropping it changes no minimum), sorted, then the null label (always last). Everything a solver needs is flat arrays over those lists:

- ``act_ptr`` (E+1): node i's active labels are ``act_label[act_ptr[i]:act_ptr[i+1]]``; a label
  is addressed by its *local* index in that list (null = ``n_act[i] - 1``).
- compatible pairs: for a conjugate edge (a, b) the non-null label pairs with V = c1, i.e. both map
  the shared street segment to the same over-view segment and their transforms agree within
  θ_th / t_th. Found by a sort-join on (edge, over-view segment), then vectorised threshold tests.
- directed messages sorted by (receiver, sender): all messages into node i are one contiguous
  (deg_i, n_act[i]) block of the flat message array, rows in ascending sender order.

V takes two values, so a message needs only min over all (h + c2), the null entry and a min over
the compatible pairs (Felzenszwalb & Huttenlocher 2006): see ``solvers_bp.send``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator

from toolkit.errors import StageError
from toolkit.stage import StageParams
from toolkit.types import ConjugateGraphs, DataCosts

PAIR_CHUNK = 2_000_000  # a-side entries per join chunk (bounds the join's temporary memory)


class SmoothnessParams(StageParams):
    """The energy (Ling & Qin 2022, Eq. 1–2) and the per-segment vote, shared by every match.* stage."""

    c1: float = Field(0.1, ge=0.0, description="smoothness cost V for compatible label pairs or a "
                                               "null label (unitless, the scale of D)")
    c2: float = Field(0.6, ge=0.0, description="smoothness cost V for incompatible label pairs (unitless, c2 >= c1)")
    theta_th_deg: float = Field(10.0, gt=0.0, description="max rotation difference of compatible labels (deg)")
    t_th_m: float = Field(100.0, gt=0.0, description="max translation difference of compatible labels (m)")
    tie_min_extent_m: float = Field(
        0.0, ge=0.0, description="vote: a tie with the null votes matches only a segment at "
                                 "least this long (horizontal diameter, m; 0: every tie)")

    @model_validator(mode="after")
    def _c1_not_above_c2(self) -> SmoothnessParams:
        if self.c1 > self.c2:
            raise ValueError(f"c1 ({self.c1}) must not exceed c2 ({self.c2})")
        return self


def ranges(starts: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Concatenation of arange(s, s + n) for each (s, n), vectorised."""
    lengths = np.asarray(lengths, dtype=np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, dtype=np.int64)
    offsets = np.cumsum(lengths) - lengths
    return np.repeat(np.asarray(starts, dtype=np.int64) - offsets, lengths) + np.arange(total)


def segment_argmin(values: np.ndarray, ptr: np.ndarray) -> np.ndarray:
    """Local index of the first minimum of each non-empty segment values[ptr[i]:ptr[i+1]]."""
    lens = np.diff(ptr)
    mins = np.minimum.reduceat(values, ptr[:-1])
    seg = np.repeat(np.arange(len(lens)), lens)
    hit = np.flatnonzero(values <= mins[seg])
    hs = seg[hit]
    first = hit[np.r_[True, hs[1:] != hs[:-1]]]
    return first - ptr[:-1]


def wrap_angle(a: np.ndarray) -> np.ndarray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@dataclass
class MRF:
    """Active labels, compatible pairs and message layout of one matching problem (see module doc)."""

    n_nodes: int
    n_labels: int
    c1: float
    c2: float
    theta_th_rad: float
    t_th_m: float
    label_pairs: np.ndarray     # (L-1,2)
    theta: np.ndarray           # (E,L-1)
    t: np.ndarray               # (E,L-1,2)
    cost: np.ndarray            # (E,L) with +inf = pruned
    conj_edges: np.ndarray      # (C,2)
    conj_pos: np.ndarray        # (C,2) column of the shared segment in street edge a / b
    street_edges: np.ndarray    # (E,2) street segments (j, k) of each node
    act_ptr: np.ndarray
    act_label: np.ndarray
    act_cost: np.ndarray
    n_act: np.ndarray
    pair_edge: np.ndarray       # (P,) compatible non-null pairs: conj edge, local label at a, at b
    pair_a: np.ndarray
    pair_b: np.ndarray
    msg_send: np.ndarray        # (M,) directed messages sorted by (receiver, sender)
    msg_recv: np.ndarray
    msg_rev: np.ndarray
    msg_of_edge: np.ndarray     # (C,2) message a→b, b→a
    msg_ptr: np.ndarray         # (M+1,) slot ranges; message d lives over its receiver's labels
    in_first: np.ndarray        # (E,) first message into node i; deg[i] of them, senders ascending
    deg: np.ndarray
    slot_node_flat: np.ndarray  # (slots,) flat active index each message slot refers to
    pm_ptr: np.ndarray          # (M+1,) compatible pairs per directed message:
    pm_src: np.ndarray          #   local label at the sender,
    pm_tgt: np.ndarray          #   local label at the receiver,
    pm_nbpos: np.ndarray        #   row of the sender in the receiver's incoming block

    @property
    def null_label(self) -> int:
        return self.n_labels - 1

    def to_global(self, local: np.ndarray) -> np.ndarray:
        """Local indices (..., E) → global labels."""
        return self.act_label[self.act_ptr[:-1] + np.asarray(local, dtype=np.int64)]

    def greedy_local(self) -> np.ndarray:
        """Winner-takes-all on D (null included)."""
        return segment_argmin(self.act_cost, self.act_ptr)

    def energy(self, labels: np.ndarray) -> float | np.ndarray:
        """E(L) = Σ D + Σ_conj_edges V for global labels (E,) or a batch (B,E); from scratch (no pair
        lists), so it also checks the solvers' bookkeeping."""
        labels = np.asarray(labels, dtype=np.int64)
        e = self.cost[np.arange(self.n_nodes), labels].sum(axis=-1)
        if len(self.conj_edges):
            e = e + self.pairwise(labels).sum(axis=-1)
        return float(e) if labels.ndim == 1 else e

    def pairwise(self, labels: np.ndarray) -> np.ndarray:
        """(..., C) V of every conjugate edge under global labels (..., E)."""
        a, b = self.conj_edges[:, 0], self.conj_edges[:, 1]
        return self.edge_costs(np.arange(len(a)), labels[..., a], labels[..., b])

    def edge_costs(self, edges: np.ndarray, la: np.ndarray, lb: np.ndarray) -> np.ndarray:
        """(..., n) V of conjugate ``edges`` (n,) given the global labels (..., n) of their two ends."""
        a, b, pos = self.conj_edges[edges, 0], self.conj_edges[edges, 1], self.conj_pos[edges]
        null = (la == self.null_label) | (lb == self.null_label)
        la_c, lb_c = np.where(null, 0, la), np.where(null, 0, lb)
        same = self.label_pairs[la_c, pos[:, 0]] == self.label_pairs[lb_c, pos[:, 1]]
        dth = np.abs(wrap_angle(self.theta[a, la_c] - self.theta[b, lb_c]))
        dt = np.linalg.norm(self.t[a, la_c] - self.t[b, lb_c], axis=-1)
        with np.errstate(invalid="ignore"):
            compat = same & (dth < self.theta_th_rad) & (dt < self.t_th_m)
        return np.where(null | compat, self.c1, self.c2)


def check_inputs(graphs: ConjugateGraphs, costs: DataCosts) -> None:
    """One-line StageError when the containers disagree with each other."""
    e, lab = graphs.n_nodes, graphs.n_labels
    if costs.cost.shape != (e, lab):
        raise StageError(f"match: DataCosts.cost has shape {costs.cost.shape} but the conjugate graph has "
                         f"{e} nodes and {lab} labels (unary stage out of step with the graph stage)")
    if costs.theta_rad.shape != (e, lab - 1) or costs.t.shape != (e, lab - 1, 2):
        raise StageError(f"match: DataCosts.theta_rad/t shapes {costs.theta_rad.shape}/{costs.t.shape} "
                         f"do not match ({e}, {lab - 1})")
    if e and not np.all(np.isfinite(costs.cost[:, -1])):
        raise StageError("match: DataCosts.cost has a non-finite null-label column (expected 1)")
    if np.isnan(costs.cost).any() or (np.isfinite(costs.cost) & (costs.cost < 0)).any():
        raise StageError("match: DataCosts.cost has NaN or negative entries (expected [0,1] or +inf)")
    ce = np.asarray(graphs.conj_edges).reshape(-1, 2)
    if len(ce) and (ce.min() < 0 or ce.max() >= e or np.any(ce[:, 0] == ce[:, 1])):
        raise StageError("match: ConjugateGraphs.conj_edges refers to a node outside 0..E-1 or to itself")


def build_mrf(graphs: ConjugateGraphs, costs: DataCosts, c1: float, c2: float,
              theta_th_deg: float, t_th_m: float) -> MRF:
    check_inputs(graphs, costs)
    n_nodes, n_labels = graphs.n_nodes, graphs.n_labels
    cost = np.asarray(costs.cost, dtype=np.float64)
    street_edges = np.asarray(graphs.street_edges, dtype=np.int64).reshape(-1, 2)
    conj = np.asarray(graphs.conj_edges, dtype=np.int64).reshape(-1, 2)
    shared = np.asarray(graphs.conj_shared, dtype=np.int64).reshape(-1)
    label_pairs = np.asarray(graphs.label_pairs, dtype=np.int64).reshape(-1, 2)
    theta = np.asarray(costs.theta_rad, dtype=np.float64)
    tr = np.asarray(costs.t, dtype=np.float64)

    # A label costing at least the null label's D is dominated by null (V(null, ·) = c1 <= V(l, ·)):
    # dropping it changes no minimum and removes ties that make message passing flip-flop.
    active = np.isfinite(cost) & (cost < cost[:, -1:]) if n_nodes else np.zeros(cost.shape, bool)
    active[:, -1] = True
    act_node, act_label = np.nonzero(active)  # row-major: by node, labels ascending, null last
    act_ptr = np.concatenate([[0], np.cumsum(active.sum(axis=1))]).astype(np.int64)
    n_act = np.diff(act_ptr)

    conj_pos = np.zeros((len(conj), 2), dtype=np.int64)
    for side in (0, 1):
        se = street_edges[conj[:, side]]
        hit0, hit1 = se[:, 0] == shared, se[:, 1] == shared
        if not np.all(hit0 | hit1):
            raise StageError("match: ConjugateGraphs.conj_shared is not a segment of both street edges")
        conj_pos[:, side] = np.where(hit0, 0, 1)

    mrf_args = {"n_nodes": n_nodes, "n_labels": n_labels, "c1": float(c1), "c2": float(c2),
                "theta_th_rad": float(np.deg2rad(theta_th_deg)), "t_th_m": float(t_th_m),
                "label_pairs": label_pairs, "theta": theta, "t": tr, "cost": cost, "conj_edges": conj,
                "conj_pos": conj_pos, "street_edges": street_edges, "act_ptr": act_ptr,
                "act_label": act_label.astype(np.int64),
                "act_cost": cost[act_node, act_label], "n_act": n_act}
    pair_edge, pair_a, pair_b = _compatible_pairs(mrf_args, act_node)
    return MRF(**mrf_args, pair_edge=pair_edge, pair_a=pair_a, pair_b=pair_b,
               **_message_layout(n_nodes, conj, n_act, act_ptr, pair_edge, pair_a, pair_b))


def _compatible_pairs(m: dict, act_node: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    conj, act_ptr, n_act = m["conj_edges"], m["act_ptr"], m["n_act"]
    label_pairs = m["label_pairs"]
    n_ov = int(label_pairs.max()) + 1 if len(label_pairs) else 1
    # θ and t of every active flat entry (null entries never join: only non-null ranges are used)
    lab = np.minimum(m["act_label"], max(m["n_labels"] - 2, 0))
    th = m["theta"][act_node, lab] if len(label_pairs) else np.zeros(len(act_node))
    th = np.where(np.isfinite(th), th, 0.0)  # null entries (never joined) and bad unary output
    tt = m["t"][act_node, lab] if len(label_pairs) else np.zeros((len(act_node), 2))
    # Join key: (edge, over-view segment the shared street segment goes to, θ bin). Bins are at least
    # 2·θ_th wide, so a compatible b lies in a's bin or in the neighbour bin nearer to θ_a.
    n_bins = max(1, int(np.floor(2 * np.pi / (2 * m["theta_th_rad"]))))
    n_bins = 1 if n_bins < 3 else n_bins
    bin_w = 2 * np.pi / n_bins
    pos = np.nan_to_num((th + np.pi) / bin_w, nan=0.0)  # NaN θ: pruned labels, never active
    bin_own = np.minimum(pos.astype(np.int64), n_bins - 1)
    bin_near = np.where(pos - bin_own >= 0.5, bin_own + 1, bin_own - 1) % n_bins
    out_e, out_a, out_b = [], [], []
    n_nonnull = n_act - 1
    load = np.cumsum(n_nonnull[conj[:, 0]]) if len(conj) else np.zeros(0, np.int64)
    per_edge = n_ov * n_bins
    max_edges = max(1, PAIR_CHUNK // per_edge)  # bounds the count table
    start = 0
    while start < len(conj):
        stop = int(np.searchsorted(load, load[start] - n_nonnull[conj[start, 0]] + PAIR_CHUNK, "right"))
        stop = min(max(stop, start + 1), start + max_edges)
        ch = np.arange(start, stop)
        start = stop
        a, b = conj[ch, 0], conj[ch, 1]
        fa = ranges(act_ptr[a], n_nonnull[a])
        ea = np.repeat(np.arange(len(ch)), n_nonnull[a])
        fb = ranges(act_ptr[b], n_nonnull[b])
        eb = np.repeat(np.arange(len(ch)), n_nonnull[b])
        if len(fa) == 0 or len(fb) == 0:
            continue
        group_a = (ea * n_ov + label_pairs[m["act_label"][fa], m["conj_pos"][ch[ea], 0]]) * n_bins
        key_b = (eb * n_ov + label_pairs[m["act_label"][fb], m["conj_pos"][ch[eb], 1]]) * n_bins + bin_own[fb]
        count_b = np.bincount(key_b, minlength=len(ch) * per_edge)
        start_b = np.cumsum(count_b) - count_b
        fb_sorted = fb[np.argsort(key_b, kind="stable")]
        bins = (bin_own[fa],) if n_bins == 1 else (bin_own[fa], bin_near[fa])
        for bin_a in bins:
            key_a = group_a + bin_a
            cnt = count_b[key_a]
            ia = np.repeat(fa, cnt)
            ib = fb_sorted[ranges(start_b[key_a], cnt)]
            e = np.repeat(ea, cnt)
            ok = np.abs(wrap_angle(th[ia] - th[ib])) < m["theta_th_rad"]
            ia, ib, e = ia[ok], ib[ok], e[ok]
            ok = np.hypot(tt[ia, 0] - tt[ib, 0], tt[ia, 1] - tt[ib, 1]) < m["t_th_m"]
            ce = ch[e[ok]]
            out_e.append(ce)
            out_a.append(ia[ok] - act_ptr[conj[ce, 0]])
            out_b.append(ib[ok] - act_ptr[conj[ce, 1]])
    if not out_e:
        z = np.zeros(0, dtype=np.int64)
        return z, z.copy(), z.copy()
    return np.concatenate(out_e), np.concatenate(out_a), np.concatenate(out_b)


def _message_layout(n_nodes: int, conj: np.ndarray, n_act: np.ndarray, act_ptr: np.ndarray,
                    pair_edge: np.ndarray, pair_a: np.ndarray, pair_b: np.ndarray) -> dict:
    c = len(conj)
    send = np.concatenate([conj[:, 0], conj[:, 1]])
    recv = np.concatenate([conj[:, 1], conj[:, 0]])
    order = np.lexsort((send, recv))
    inv = np.empty(2 * c, dtype=np.int64)
    inv[order] = np.arange(2 * c)
    msg_of_edge = np.stack([inv[:c], inv[c:]], axis=1) if c else np.zeros((0, 2), np.int64)
    msg_rev = np.empty(2 * c, dtype=np.int64)
    msg_rev[inv[:c]] = inv[c:]
    msg_rev[inv[c:]] = inv[:c]
    msg_send, msg_recv = send[order], recv[order]
    msg_len = n_act[msg_recv]
    msg_ptr = np.concatenate([[0], np.cumsum(msg_len)]).astype(np.int64)
    deg = np.bincount(msg_recv, minlength=n_nodes).astype(np.int64)
    in_first = (np.cumsum(deg) - deg).astype(np.int64)
    # pairs per directed message: a→b reads a's label (src) and writes b's (tgt); b→a the reverse
    pm_msg = np.concatenate([msg_of_edge[pair_edge, 0], msg_of_edge[pair_edge, 1]]) if c else np.zeros(0, np.int64)
    pm_src = np.concatenate([pair_a, pair_b])
    pm_tgt = np.concatenate([pair_b, pair_a])
    o = np.argsort(pm_msg, kind="stable")
    pm_msg, pm_src, pm_tgt = pm_msg[o], pm_src[o], pm_tgt[o]
    pm_ptr = np.concatenate([[0], np.cumsum(np.bincount(pm_msg, minlength=2 * c))]).astype(np.int64)
    return {"msg_send": msg_send, "msg_recv": msg_recv, "msg_rev": msg_rev, "msg_of_edge": msg_of_edge,
            "msg_ptr": msg_ptr, "in_first": in_first, "deg": deg,
            "slot_node_flat": ranges(act_ptr[msg_recv], msg_len),
            "pm_ptr": pm_ptr, "pm_src": pm_src, "pm_tgt": pm_tgt,
            "pm_nbpos": pm_msg - in_first[msg_recv[pm_msg]]}


def conditional_scores(mrf: MRF, i: int, x: np.ndarray, n_rows: int | None = None) -> np.ndarray:
    """D_i(l) + Σ V(l, x_j) over node i's active labels, for its neighbours j in the first ``n_rows``
    rows of its incoming block (all neighbours when None; rows are senders in ascending order)."""
    f, d = mrf.in_first[i], mrf.deg[i]
    rows = d if n_rows is None else n_rows
    n = mrf.n_act[i]
    score = mrf.act_cost[mrf.act_ptr[i]:mrf.act_ptr[i + 1]].copy()
    if rows == 0:
        return score
    nbs = mrf.msg_send[f:f + rows]
    xn = x[nbs]
    p0, p1 = mrf.pm_ptr[f], mrf.pm_ptr[f + rows]
    pos = mrf.pm_nbpos[p0:p1]
    hit = mrf.pm_src[p0:p1] == xn[pos]
    agree = np.bincount(mrf.pm_tgt[p0:p1][hit], minlength=n).astype(np.float64)
    agree += np.count_nonzero(xn == mrf.n_act[nbs] - 1)
    score += rows * mrf.c2 - (mrf.c2 - mrf.c1) * agree
    score[n - 1] = mrf.act_cost[mrf.act_ptr[i + 1] - 1] + rows * mrf.c1
    return score
