"""Min-sum message passing with the two-valued smoothness in O(L + |compatible|) per message.

For a message a→b with sender values h(l_a) (unary + incoming messages except b's):
    m(l_b)    = min( min_la h + c2 , c1 + min(h(null), min_{l_a compatible with l_b} h(l_a)) )
    m(null_b) = min_la h + c1
valid because c1 <= c2. A ``MessagePlan`` precomputes, for any set of directed messages, where the
sender values live and where the compatible pairs point, so one ``send`` computes all of them with
a handful of numpy reductions (loopy BP: one plan for every message; TRW-S: one per node and pass).

``loopy_bp`` is the paper's synchronous (flooding) schedule in the cost domain: all messages are
updated from the previous ones, normalised to min 0, optionally damped; labels are the belief
argmins; it stops when the energy of the labelling has not changed for ``patience`` iterations.
Where the flooding schedule keeps cycling (the best energy stops improving), it damps harder and
goes on: a damped update has the same fixed points as the plain one, it only moves towards them in
smaller steps, so ``patience`` is counted in the same message travel (more iterations per unit).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from toolkit.matching.mrf import MRF, conditional_scores, ranges, segment_argmin
from toolkit.matching.solvers_common import BestTracker, IterCallback, SolveResult
from toolkit.matching.solvers_local import icm_polish


@dataclass
class MessagePlan:
    msgs: np.ndarray        # (k,) directed message ids
    src_slots: np.ndarray   # global slots of rev(msgs), concatenated: the sender-side buffer
    src_starts: np.ndarray  # (k,) start of each message's sender values in that buffer
    src_null: np.ndarray    # (k,) position of the sender's null label in that buffer
    out_slots: np.ndarray   # global slots of msgs, concatenated
    out_starts: np.ndarray
    out_lens: np.ndarray
    out_null: np.ndarray
    pair_src: np.ndarray    # compatible pairs sorted by target: sender buffer positions
    tgt_unique: np.ndarray  # distinct target positions in the output buffer
    tgt_starts: np.ndarray  # start of each target's group in pair_src
    tgt_msg: np.ndarray     # plan index of each target's message
    out_msg: np.ndarray | None = None  # plan index of every out position (for buffered sends)


def build_plan(mrf: MRF, msgs: np.ndarray, src_slots: bool = True, out_index: bool = False) -> MessagePlan:
    """Plan for messages ``msgs``; src_slots=False skips the sender-slot list (when the caller
    already has h in that order), out_index=True adds ``out_msg`` for ``send(..., out=buffer)``."""
    msgs = np.asarray(msgs, dtype=np.int64)
    src = mrf.msg_rev[msgs]
    src_lens = mrf.msg_ptr[src + 1] - mrf.msg_ptr[src]
    src_starts = np.cumsum(src_lens) - src_lens
    out_lens = mrf.msg_ptr[msgs + 1] - mrf.msg_ptr[msgs]
    out_starts = np.cumsum(out_lens) - out_lens
    cnt = mrf.pm_ptr[msgs + 1] - mrf.pm_ptr[msgs]
    idx = ranges(mrf.pm_ptr[msgs], cnt)
    k = np.repeat(np.arange(len(msgs)), cnt)
    psrc = mrf.pm_src[idx] + src_starts[k]
    ptgt = mrf.pm_tgt[idx] + out_starts[k]
    order = np.argsort(ptgt, kind="stable")
    psrc, ptgt, k = psrc[order], ptgt[order], k[order]
    first = np.r_[True, ptgt[1:] != ptgt[:-1]] if len(ptgt) else np.zeros(0, bool)
    return MessagePlan(
        msgs=msgs, src_slots=ranges(mrf.msg_ptr[src], src_lens) if src_slots else np.zeros(0, np.int64),
        src_starts=src_starts,
        src_null=src_starts + src_lens - 1, out_slots=ranges(mrf.msg_ptr[msgs], out_lens),
        out_starts=out_starts, out_lens=out_lens, out_null=out_starts + out_lens - 1,
        pair_src=psrc, tgt_unique=ptgt[first], tgt_starts=np.flatnonzero(first), tgt_msg=k[first],
        out_msg=np.repeat(np.arange(len(msgs)), out_lens) if out_index else None)


def send(plan: MessagePlan, h: np.ndarray, c1: float, c2: float, normalise: bool = True,
         out: np.ndarray | None = None) -> np.ndarray:
    """New values of the plan's messages (over the plan's out buffer) from sender values h.

    Every message entry is >= min_all + c1 = its null entry (V >= c1), so normalising to min 0 means
    subtracting exactly that: m(l) = min(c2 - c1, h(null) - min_all, min_compatible h - min_all).
    ``out``: a preallocated result buffer (needs ``plan.out_msg``); big temporaries cost page faults.
    """
    if len(plan.msgs) == 0:
        return np.zeros(0)
    min_all = np.minimum.reduceat(h, plan.src_starts)
    base = np.minimum(c2 - c1, h[plan.src_null] - min_all)
    if out is not None and plan.out_msg is not None:
        np.take(base, plan.out_msg, out=out, mode="clip")  # "raise" would buffer
    else:
        out = np.repeat(base, plan.out_lens)
    if len(plan.pair_src):
        best = np.minimum.reduceat(h[plan.pair_src], plan.tgt_starts) - min_all[plan.tgt_msg]
        out[plan.tgt_unique] = np.minimum(out[plan.tgt_unique], best)
    out[plan.out_null] = 0.0
    if not normalise:
        out += (min_all + c1)[plan.out_msg] if plan.out_msg is not None else np.repeat(min_all + c1, plan.out_lens)
    return out


def beliefs(mrf: MRF, msg: np.ndarray) -> np.ndarray:
    """Flat (over active labels) unary + all incoming messages."""
    return mrf.act_cost + np.bincount(mrf.slot_node_flat, weights=msg, minlength=len(mrf.act_cost))


def _incoming_matrix(mrf: MRF, position: np.ndarray, dtype: type = np.float64):
    """Sparse 0/1 matrix summing, for every active label, the messages into it (a CSR matvec is
    several times faster than a weighted bincount). position: where each storage slot is kept."""
    from scipy.sparse import csr_matrix

    n_flat = len(mrf.act_cost)
    node = np.repeat(np.arange(mrf.n_nodes), mrf.n_act)
    deg = mrf.deg[node]
    indptr = np.concatenate([[0], np.cumsum(deg)])
    # the slots of flat entry (node i, label l) are msg_ptr[in_first[i]] + l + r·n_i, r < deg_i
    first = mrf.msg_ptr[np.minimum(mrf.in_first[node], len(mrf.msg_ptr) - 1)] + np.arange(n_flat) - mrf.act_ptr[node]
    row = np.arange(int(indptr[-1])) - np.repeat(indptr[:-1], deg)
    slots = np.repeat(first, deg) + row * np.repeat(mrf.n_act[node], deg)
    return csr_matrix((np.ones(len(slots), dtype=dtype), position[slots], indptr), shape=(n_flat, len(position)))


def loopy_bp(mrf: MRF, max_iters: int = 100, damping: float = 0.0, patience: int = 1,
             energy_tol: float = 1e-9, message_tol: float | None = None, stall_iters: int | None = None,
             max_damping: float | None = None, dtype: type = np.float64, polish: bool = False,
             on_iter: IterCallback | None = None) -> SolveResult:
    """Synchronous min-sum loopy BP (module doc). Returns the lowest-energy labelling seen.

    Converged: the energy has not changed for ``patience`` iterations and, unless message_tol is
    None (the paper's criterion), no message entry moved by more than message_tol in the last one.
    When the best energy has not improved for ``stall_iters`` iterations: with ``max_damping``, halve
    (1 − damping), up to max_damping, count patience as patience·(1 − damping₀)/(1 − damping) and go
    on; otherwise (or at max_damping) give up, not converged.
    dtype: of the messages; float32 halves the memory traffic of every sweep (energies stay float64).
    polish: finish with ICM started from that labelling (never raises its energy; as TRW-S does): a
    belief argmin is only locally consistent through the messages, so a single node can still have
    a strictly better label given its neighbours' final labels.
    """
    n_slots = int(mrf.msg_ptr[-1])
    # Plan messages listed as rev(0..M-1): their sender values are the slots in storage order. The
    # messages themselves are kept in the plan's output order (``mp``): beliefs do not care about
    # order, and reading m_{j→i} back in storage order is a single gather per iteration.
    plan = build_plan(mrf, mrf.msg_rev[np.arange(len(mrf.msg_send))], src_slots=False, out_index=True)
    stored_at = np.empty(n_slots, dtype=np.int64)
    stored_at[plan.out_slots] = np.arange(n_slots)
    incoming = _incoming_matrix(mrf, stored_at, dtype)
    mp = np.zeros(n_slots, dtype=dtype)
    new, h, tmp = (np.empty(n_slots, dtype=dtype) for _ in range(3))  # reused: big temporaries page-fault
    unary = mrf.act_cost.astype(dtype)
    tracker = BestTracker(mrf, patience, energy_tol, on_iter)
    tracker.start(mrf.greedy_local())
    belief = unary.copy()
    converged, it, d = False, 0, damping
    for it in range(1, max_iters + 1):
        if n_slots:
            np.take(mp, stored_at, out=tmp, mode="clip")
            np.take(belief, mrf.slot_node_flat, out=h, mode="clip")
            np.subtract(h, tmp, out=h)  # at slot of j→i: node i's values without j's message
            send(plan, h, mrf.c1, mrf.c2, out=new)
            if d > 0.0:
                new *= 1.0 - d
                np.multiply(mp, d, out=tmp)
                new += tmp
            belief = unary + incoming @ new
        still = tracker.step(it, segment_argmin(belief, mrf.act_ptr))
        if still and message_tol is not None and n_slots:
            np.subtract(new, mp, out=tmp)
            still = max(float(tmp.max()), -float(tmp.min())) <= message_tol
        mp, new = new, mp
        if still:
            converged = True
            break
        if stall_iters is not None and tracker.since_best >= stall_iters:
            if max_damping is None or d >= max_damping:
                break
            d = min(max_damping, 1.0 - (1.0 - d) / 2.0)
            tracker.patience = math.ceil(patience * (1.0 - damping) / (1.0 - d))
            tracker.since_best = tracker.still = 0
    labels, energy = tracker.best_labels, tracker.best_energy
    if polish:
        # ICM from the best belief-argmin labelling and from the final messages decoded sequentially
        # (each node conditioned on the labels already chosen for its earlier neighbours, messages
        # standing for the later ones): two roundings of the same fixed point, keep the lower
        starts: tuple[np.ndarray, ...] = ()
        if n_slots:
            np.take(mp, stored_at, out=tmp, mode="clip")  # mp holds the last update (swapped above)
            decoded = sequential_decode(mrf, tmp)
            if not np.array_equal(decoded, labels):
                starts = (decoded,)
        labels, energy = icm_polish(mrf, labels, energy, starts)
    return SolveResult(labels=labels, energy=energy, energy_trace=tracker.trace,
                       iterations=it, converged=converged, damping=d)


def sequential_decode(mrf: MRF, msg: np.ndarray) -> np.ndarray:
    """Local labels decoded node by node in index order from messages in storage order: node i takes
    argmin D_i + Σ_{earlier j} V(·, x_j) + Σ_{later j} m_{j→i} (TRW-S's forward decoding)."""
    x = np.zeros(mrf.n_nodes, dtype=np.int64)
    for i in range(mrf.n_nodes):  # sequential by definition: each node sees the earlier choices
        f, d, n = mrf.in_first[i], mrf.deg[i], mrf.n_act[i]
        ne = int(np.count_nonzero(mrf.msg_send[f:f + d] < i))  # senders ascending: earlier rows first
        block = msg[mrf.msg_ptr[f]:mrf.msg_ptr[f] + d * n].reshape(d, n)
        x[i] = int(np.argmin(conditional_scores(mrf, i, x, ne) + block[ne:].sum(axis=0)))
    return x
