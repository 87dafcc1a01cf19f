"""The vehicle route: a walk along street centrelines (or any polyline), smoothed through turns,
offset to the driving lane, sampled every ``camera_step_m`` into forward-looking camera poses."""

from __future__ import annotations

from dataclasses import dataclass

import networkx as nx
import numpy as np

from toolkit.errors import CrossviewError
from toolkit.synth.config import SynthConfig


@dataclass
class Track:
    """True cameras in local metres. R_c2w: (C,3,3) columns = camera x (right), y (down), z (forward)."""

    centres: np.ndarray  # (C,3)
    R_c2w: np.ndarray  # (C,3,3)
    arclength: np.ndarray  # (C,)
    closed: bool

    def __len__(self) -> int:
        return len(self.centres)


def plan_route(world, cfg: SynthConfig, rng: np.random.Generator) -> tuple[np.ndarray, bool]:
    """Centreline polyline of the route and whether it is closed: along the streets when the world
    has them, else through the open space between buildings. A real city that cannot host the asked
    route gets a shorter one (still closed if it can, else open), with a warning."""
    g = world.street_graph
    if g is None or g.number_of_edges() == 0:
        from toolkit.synth.openspace import open_space_graph

        g = open_space_graph(world)
    try:
        return route_on_graph(g, cfg, rng), cfg.route_closed
    except CrossviewError:
        if world.name == "procedural":
            raise
    # a real city may be too small or too sparse for the asked route: settle for less, say so
    import logging

    for factor in (0.8, 0.6, 0.45, 0.3):
        for closed in (True, False) if cfg.route_closed else (False,):
            try:
                shorter = cfg.model_copy(
                    update={"route_length_m": cfg.route_length_m * factor, "route_closed": closed}
                )
                line = route_on_graph(g, shorter, rng)
            except CrossviewError:
                continue
            logging.getLogger("toolkit.synth").warning(
                "synth: %s: no %.0f m route; using a %s one of %.0f m",
                world.name,
                cfg.route_length_m,
                "closed" if closed else "open",
                shorter.route_length_m,
            )
            return line, closed
    raise CrossviewError(
        f"synth: {world.name}: no route of even {0.3 * cfg.route_length_m:.0f} m through its streets"
    )


def route_on_graph(
    g: nx.Graph, cfg: SynthConfig, rng: np.random.Generator, attempts: int = 300
) -> np.ndarray:
    """A self-avoiding walk of about ``route_length_m`` (closed back to its start when asked)."""
    target = cfg.route_length_m
    pos = np.array([g.nodes[n]["xy"] for n in g.nodes])
    nodes = np.array(list(g.nodes))
    centre = pos.mean(0)
    near = nodes[np.argsort(np.linalg.norm(pos - centre, axis=1))[: max(3, len(nodes) // 4)]]
    best, best_score = None, np.inf
    for _ in range(attempts):
        path = _walk(g, int(rng.choice(near)), target, cfg.route_closed, rng)
        if path is None:
            continue
        line = path_polyline(g, path)
        length = np.linalg.norm(np.diff(line, axis=0), axis=1).sum()
        score = abs(length - target) / target
        if cfg.route_closed:  # prefer round loops to thin out-and-back ones
            score -= 0.3 * _roundness(line, length)
        if score < best_score:
            best, best_score = line, score
    if best is None and cfg.route_closed:
        best = _cycle_route(g, target, centre)
    if best is None:
        raise CrossviewError(f"synth: no street route of about {target:.0f} m found; lower route_length_m")
    return best


def _roundness(line: np.ndarray, length: float) -> float:
    """Enclosed area over that of a circle of the same perimeter (1: a circle, 0: out and back)."""
    x, y = line[:, 0], line[:, 1]
    area = abs(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return float(area / (length**2 / (4 * np.pi)))


def _cycle_route(
    g: nx.Graph, target: float, centre: np.ndarray, max_cycles: int = 50_000, max_edges: int = 40
) -> np.ndarray | None:
    """The roundest simple cycle of the graph within 10 % of ``target`` (nearer the centre breaks
    ties), when random walks found none: sparse street graphs (villages, the open space of one
    block) hold few loops, and a walk rarely closes on one of the right length."""
    import itertools

    pos = {n: np.asarray(g.nodes[n]["xy"], np.float64) for n in g.nodes}
    extent = max(float(np.ptp(np.array(list(pos.values())), axis=0).max()), 1.0)
    best, best_score = None, np.inf
    for cyc in itertools.islice(nx.simple_cycles(g, length_bound=max_edges), max_cycles):
        if len(cyc) < 3:
            continue
        length = sum(g.edges[a, b]["length"] for a, b in zip(cyc, cyc[1:] + cyc[:1]))
        if abs(length - target) > 0.1 * target:
            continue
        line = path_polyline(g, [*cyc, cyc[0]])
        middle = np.mean([pos[n] for n in cyc], axis=0)
        score = (
            abs(length - target) / target
            - 0.3 * _roundness(line, length)
            + 0.2 * np.linalg.norm(middle - centre) / extent
        )
        if score < best_score:
            best, best_score = line, score
    return best


def _walk(g: nx.Graph, start: int, target: float, closed: bool, rng) -> list[int] | None:
    path, visited, length = [start], {start}, 0.0
    while True:
        u = path[-1]
        if closed and length >= 0.4 * target and len(path) > 2:
            allowed = [n for n in g.nodes if n not in visited or n in (start, u)]
            try:
                back = nx.shortest_path(g.subgraph(allowed), u, start, weight="length")
            except nx.NetworkXNoPath:
                back = None
            if back is not None and len(back) > 1:
                blen = sum(g.edges[a, b]["length"] for a, b in zip(back[:-1], back[1:]))
                if abs(length + blen - target) <= 0.1 * target:
                    return path + back[1:]
        cands = [v for v in g.neighbors(u) if v not in visited]
        if not cands or length > 1.3 * target:
            return None
        w = np.ones(len(cands))
        if len(path) > 1:  # vehicles mostly go straight on
            d0 = g.nodes[u]["xy"] - g.nodes[path[-2]]["xy"]
            for i, v in enumerate(cands):
                d1 = g.nodes[v]["xy"] - g.nodes[u]["xy"]
                cosang = d0 @ d1 / (np.linalg.norm(d0) * np.linalg.norm(d1))
                w[i] = 0.5 + max(cosang, 0) * 1.5
        v = int(cands[rng.choice(len(cands), p=w / w.sum())])
        length += g.edges[u, v]["length"]
        path.append(v)
        visited.add(v)
        if not closed and length >= target:
            return path


def path_polyline(g: nx.Graph, path: list[int]) -> np.ndarray:
    pts = []
    for a, b in zip(path[:-1], path[1:]):
        xy = np.asarray(g.edges[a, b]["geom"].coords)
        if np.linalg.norm(xy[0] - g.nodes[a]["xy"]) > np.linalg.norm(xy[-1] - g.nodes[a]["xy"]):
            xy = xy[::-1]
        pts.append(xy if not pts else xy[1:])
    return np.concatenate(pts)


def resample(line: np.ndarray, step: float, closed: bool = False) -> np.ndarray:
    if closed and np.linalg.norm(line[0] - line[-1]) > 1e-9:
        line = np.vstack([line, line[:1]])
    seg = np.linalg.norm(np.diff(line, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-9])
    line, s = line[keep], np.concatenate([[0], np.cumsum(seg[seg > 1e-9])])
    n = max(2, int(np.floor(s[-1] / step)) + 1)
    q = np.arange(n) * step
    if closed:
        q = q[q < s[-1] - step / 2]
    return np.column_stack([np.interp(q, s, line[:, k]) for k in range(line.shape[1])])


def smooth(line: np.ndarray, closed: bool, iterations: int = 3) -> np.ndarray:
    """Chaikin corner cutting: turns become arcs a vehicle can drive."""
    for _ in range(iterations):
        p = np.vstack([line, line[:1]]) if closed else line
        q = 0.75 * p[:-1] + 0.25 * p[1:]
        r = 0.25 * p[:-1] + 0.75 * p[1:]
        mid = np.empty((2 * len(q), line.shape[1]))
        mid[0::2], mid[1::2] = q, r
        line = mid if closed else np.vstack([p[:1], mid, p[-1:]])
    return line


def make_track(
    centreline: np.ndarray, terrain, cfg: SynthConfig, rng: np.random.Generator, closed: bool
) -> Track:
    line = smooth(resample(centreline, 5.0, closed), closed)
    line = resample(line, 0.5, closed)
    tangent = _tangents(line, closed)
    right = np.column_stack([tangent[:, 1], -tangent[:, 0]])
    line = line + right * cfg.lane_offset_m
    xy = resample(line, cfg.camera_step_m, closed)
    if not closed:
        xy = xy[: int(cfg.route_length_m / cfg.camera_step_m) + 1]
    tangent = _tangents(xy, closed, half_window=max(1, int(round(2.0 / cfg.camera_step_m))))
    n = len(xy)
    z = terrain(xy[:, 0], xy[:, 1]) + cfg.camera_height_m + rng.normal(0, 0.02, n)
    heading = np.arctan2(tangent[:, 1], tangent[:, 0]) + np.deg2rad(rng.normal(0, 0.3, n))
    ahead = xy + tangent * 3.0
    slope = (
        terrain(ahead[:, 0], ahead[:, 1])
        - terrain(xy[:, 0] - tangent[:, 0] * 3, xy[:, 1] - tangent[:, 1] * 3)
    ) / 6
    pitch = np.arctan(slope) + np.deg2rad(cfg.camera_pitch_deg + rng.normal(0, 0.3, n))
    fwd = np.column_stack([np.cos(heading) * np.cos(pitch), np.sin(heading) * np.cos(pitch), np.sin(pitch)])
    rgt = np.column_stack([np.sin(heading), -np.cos(heading), np.zeros(n)])
    down = np.cross(fwd, rgt)
    R = np.stack([rgt, down, fwd], axis=2)
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    return Track(np.column_stack([xy, z]), R, np.concatenate([[0], np.cumsum(seg)]), closed)


def _tangents(line: np.ndarray, closed: bool, half_window: int = 1) -> np.ndarray:
    k = half_window
    if closed:
        d = np.roll(line, -k, axis=0) - np.roll(line, k, axis=0)
    else:
        idx = np.arange(len(line))
        d = line[np.minimum(idx + k, len(line) - 1)] - line[np.maximum(idx - k, 0)]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
