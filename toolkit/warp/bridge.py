"""Camera poses across route gaps: cameras that see no registered façade follow the street
trajectory between the grounded cameras on either side, as a pose graph with fixed ends would
(docs/camera_bridge.md): rotation and scale slerped / interpolated in route position, the street
steps integrated from one end, the misclosure at the other spread linearly along the route."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation, Slerp


@dataclass(frozen=True)
class CameraPoses:
    """Corrections of the street cameras: scene-CRS centres (C,3), rotations street → scene (C,3,3),
    scale (C,) and spread (C,) metres."""

    centres: np.ndarray
    rotations: np.ndarray
    scale: np.ndarray
    spread: np.ndarray


def grounded_cameras(observations: np.ndarray, on_registered: np.ndarray, n_images: int,
                     min_observations: int) -> np.ndarray:
    """(C,) bool: the image observes at least ``min_observations`` sparse points on registered façades
    (``on_registered`` (P,) bool per sparse point)."""
    img = observations[:, 0].astype(np.int64)
    hit = on_registered[observations[:, 1].astype(np.int64)]
    return np.bincount(img[hit], minlength=n_images) >= min_observations


def sequence_breaks(street_centres: np.ndarray, max_step_ratio: float = 20.0) -> np.ndarray:
    """(C−1,) bool: the step from image i to i + 1 is no step of one trajectory (longer than
    ``max_step_ratio`` × the median step): another sequence starts there."""
    steps = np.linalg.norm(np.diff(street_centres, axis=0), axis=1)
    if len(steps) == 0:
        return np.zeros(0, bool)
    return steps > max_step_ratio * max(float(np.median(steps)), 1e-9)


def _route(street_centres: np.ndarray, max_step_ratio: float) -> tuple[np.ndarray, np.ndarray]:
    """(C,) sequence index and (C,) distance travelled of each camera (capture order); a sequence
    break adds no distance."""
    breaks = sequence_breaks(street_centres, max_step_ratio)
    steps = np.linalg.norm(np.diff(street_centres, axis=0), axis=1)
    return (np.concatenate([[0], np.cumsum(breaks)]),
            np.concatenate([[0.0], np.cumsum(np.where(breaks, 0.0, steps))]))


def ground_gap_m(street_centres: np.ndarray, grounded: np.ndarray, max_step_ratio: float = 20.0) -> np.ndarray:
    """(C,) route distance from each camera to the nearest grounded camera of its sequence (0 for a
    grounded one; inf in a sequence without any). Capture order, as ``bridge_gaps``."""
    gap = np.full(len(street_centres), np.inf)
    if len(street_centres) == 0:
        return gap
    seq_id, arc = _route(street_centres, max_step_ratio)
    for q in np.unique(seq_id):
        mine = np.flatnonzero(seq_id == q)
        at, x = arc[mine[grounded[mine]]], arc[mine]      # both non-decreasing along the sequence
        if len(at):
            i = np.searchsorted(at, x)
            gap[mine] = np.minimum(np.abs(x - at[np.maximum(i - 1, 0)]), np.abs(at[np.minimum(i, len(at) - 1)] - x))
    return gap


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, end) of each maximal run of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _end(grounded: np.ndarray, seq_id: np.ndarray, arc: np.ndarray, start: int, step: int,
         window_m: float) -> np.ndarray:
    """The grounded cameras next to a gap on one side: from ``start`` on in direction ``step`` while
    grounded, in the same sequence and within ``window_m`` of route of ``start`` (empty: none)."""
    out = []
    k = start
    while 0 <= k < len(grounded) and grounded[k] and seq_id[k] == seq_id[start] \
            and abs(arc[k] - arc[start]) <= window_m:
        out.append(k)
        k += step
    return np.array(sorted(out), np.int64)


def _bridge(street: np.ndarray, arc: np.ndarray, part: np.ndarray, left: np.ndarray, right: np.ndarray,
            poses: CameraPoses) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centres, rotations, scales and spread of the gap cameras ``part`` (consecutive) from the
    grounded stretches ``left`` / ``right`` beside it (either may be empty, not both)."""
    ends = [e for e in (left, right) if len(e)]
    keys_s = [float(arc[e].mean()) for e in ends]
    keys_R = Rotation.concatenate([Rotation.from_matrix(poses.rotations[e]).mean() for e in ends])
    keys_scale = [float(poses.scale[e].mean()) for e in ends]
    if len(ends) == 2:
        u = np.clip((arc[part] - keys_s[0]) / max(keys_s[1] - keys_s[0], 1e-9), 0.0, 1.0)
        rot = Slerp([0.0, 1.0], keys_R)(u).as_matrix()
        sc = keys_scale[0] + u * (keys_scale[1] - keys_scale[0])
    else:
        u = np.zeros(len(part))
        rot = np.repeat(keys_R.as_matrix()[:1], len(part), 0)
        sc = np.full(len(part), keys_scale[0])
    # the chain over the stretches and the gap: grounded steps turn with their own camera's correction
    idx = np.arange((left if len(left) else part)[0], (right if len(right) else part)[-1] + 1)
    R_step, s_step = poses.rotations[idx[1:]].copy(), poses.scale[idx[1:]].copy()
    in_gap = np.isin(idx[1:], part)
    stepped = np.isin(part, idx[1:])            # a gap at the start of the chain has no step into its first camera
    R_step[in_gap], s_step[in_gap] = rot[stepped], sc[stepped]
    path = np.concatenate([np.zeros((1, 3)), _chain(street, idx, np.zeros(3), R_step, s_step)])   # row k − idx[0]
    offsets = [np.median(poses.centres[e] - path[e - idx[0]], axis=0) for e in ends]
    off = offsets[0] if len(ends) == 1 else (1.0 - u)[:, None] * offsets[0] + u[:, None] * offsets[1]
    centres = path[part - idx[0]] + off
    miss = 0.0 if len(ends) == 1 else float(np.linalg.norm(offsets[1] - offsets[0]))
    return centres, rot, sc, miss * np.sqrt(u * (1.0 - u))


def _chain(street: np.ndarray, idx: np.ndarray, start: np.ndarray, R: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Positions of cameras idx[1:], integrating the street steps from ``start`` (position of idx[0]),
    step i turned by R[i] and scaled by s[i] (R, s: one per step)."""
    steps = np.diff(street[idx], axis=0)
    return start + np.cumsum(s[:, None] * np.einsum("nab,nb->na", R, steps), axis=0)


def bridge_gaps(street_centres: np.ndarray, poses: CameraPoses, grounded: np.ndarray, min_gap_m: float = 0.0,
                end_window_m: float = 20.0, max_step_ratio: float = 20.0) -> tuple[CameraPoses, np.ndarray]:
    """Bridged poses, and (C,) bool: which cameras were bridged (see the module doc). Runs shorter
    than ``min_gap_m`` of route (from grounded camera to grounded camera) keep the blend.

    street_centres: (C,) camera centres in the street frame, in capture (sequence) order.
    """
    C = len(street_centres)
    centres, rotations = poses.centres.copy(), poses.rotations.copy()
    scale, spread = poses.scale.copy(), poses.spread.copy()
    bridged = np.zeros(C, bool)
    if C < 3 or not grounded.any():
        return poses, bridged
    seq_id, arc = _route(street_centres, max_step_ratio)
    for lo, hi in _runs(~grounded):
        # a run that crosses a sequence break is bridged piecewise, from the ends it has
        for part in np.split(np.arange(lo, hi), np.flatnonzero(np.diff(seq_id[lo:hi])) + 1):
            left = _end(grounded, seq_id, arc, part[0] - 1, -1, end_window_m) \
                if part[0] > 0 and seq_id[part[0] - 1] == seq_id[part[0]] else np.zeros(0, np.int64)
            right = _end(grounded, seq_id, arc, part[-1] + 1, 1, end_window_m) \
                if part[-1] + 1 < C and seq_id[part[-1] + 1] == seq_id[part[-1]] else np.zeros(0, np.int64)
            span = arc[(right if len(right) else part)[0]] - arc[(left if len(left) else part)[-1]]
            if (len(left) == 0 and len(right) == 0) or span < min_gap_m:
                continue
            bridged[part] = True
            centres[part], rotations[part], scale[part], unc = _bridge(street_centres, arc, part, left, right, poses)
            spread[part] = np.maximum(spread[part], unc)
    return CameraPoses(centres, rotations, scale, spread), bridged
