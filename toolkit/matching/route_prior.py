"""A coarse placement of the street from its façades and the over-view outlines alone (no GPS).

The route is cut into overlapping windows along the cameras' path. Each window's façade points
are correlated with a map of the over-view's outer outlines over every rotation (one FFT per
rotation, ``scipy.fft``), keeping its best distinct placements. A chain search (Viterbi) then picks
one placement per window so that neighbouring windows put the cameras between them in the same
place, and each street segment takes the placement of the windows around its route position.
The result is a ``GpsPrior``: the data term prunes and weighs its candidates with it exactly as
with GPS fixes, so that a search over every over-view edge pair is no longer needed.

With GPS fixes as well (``with_gps``), each window also tries the placement that puts its cameras
on the fixes' track, and the chain pays for a placement far from that track: the fixes keep the
placement from a look-alike block, the façades place the route closer than metres-off fixes can.
The data term then takes the placement's prior for every segment it puts near the segment's GPS
position (``toolkit.matching.data_term.gated_prior``).

Only outlines facing open ground are kept: the walls between touching buildings (terraced houses
in OSM) are never seen from the street, and in a dense city they make any placement look good.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import fft as sfft
from scipy import ndimage

from toolkit.matching.gps import GpsPrior
from toolkit.types import OverviewSegments, StreetSegments


class RoutePriorConfig(BaseModel):
    """Without street/gps.csv: place the route by its façades first (see toolkit.matching.route_prior)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = Field(True, description="without GPS, place the route by its façades and prune as with GPS")
    with_gps: bool = Field(True, description="with GPS too: place the route near the fixes' track; segments placed "
                                             "near their fixes take its prior")
    gps_cost: float = Field(0.5, ge=0, description="cost of a window placement at least gps_agree_sigmas from the "
                                                   "GPS track (unitless, as a window score)")
    gps_agree_sigmas: float = Field(2.0, gt=0, description="the distance from the GPS track that costs in full, in "
                                                           "the fixes' σ or fit RMS, whichever is larger")
    window_m: float = Field(250.0, gt=20, description="route length of each placement window (metres)")
    cell_m: float = Field(4.0, gt=0, description="cell size of the correlation maps (metres)")
    tolerance_m: float = Field(6.0, gt=0, description="a façade point farther than this from an outline scores 0")
    rotation_step_deg: float = Field(3.0, gt=0, le=30, description="rotation step of the placement search (degrees)")
    candidates_per_window: int = Field(20, ge=1, description="distinct coarse placements re-scored on the fine map (count)")
    placements_per_window: int = Field(8, ge=1, description="distinct placements kept per window for the chain (count)")
    fine_cell_m: float = Field(1.0, gt=0, description="cell size of the fine map the coarse placements are re-scored on (m)")
    fine_tolerance_m: float = Field(3.0, gt=0, description="tolerance of the fine map (metres)")
    agree_m: float = Field(15.0, gt=0, description="neighbouring windows disagreeing by this much pay the full link cost (m)")
    link_cost: float = Field(0.5, ge=0, description="cost of a full disagreement between neighbouring "
                                                    "windows (unitless, as a window score)")
    sigma_m: float = Field(3.0, gt=0, description="accuracy the data term assumes for the placed segment centres (m)")
    min_score: float = Field(0.35, ge=0, le=1, description="a chain whose median window score (0-1) is below this is not used")


@dataclass(frozen=True)
class OutlineMap:
    """close: (H,W) float32 in [0,1], 1 on an outer outline, 0 from tolerance_m; cell (0,0)'s lower
    corner is at ``corner`` (world x, y); rows follow x, columns follow y."""

    corner: np.ndarray
    cell_m: float
    close: np.ndarray


@dataclass(frozen=True)
class Placement:
    """x_world = R(theta) (x − pivot) + t for levelled street xy; score: mean closeness in [0,1]."""

    theta: float
    t: np.ndarray
    pivot: np.ndarray
    score: float

    def apply(self, xy: np.ndarray) -> np.ndarray:
        c, s = np.cos(self.theta), np.sin(self.theta)
        return (np.asarray(xy) - self.pivot) @ np.array([[c, s], [-s, c]]) + self.t


@dataclass(frozen=True)
class RoutePlacement:
    """The chosen placement of each window, the prior it gives, and what tells a user how sure it is:
    window_scores (W,), link_m (W-1,) disagreement of neighbouring windows, top_share: share of
    windows whose chosen placement is also their best alone, link_agree_m (W-1,) the disagreement
    each link may have before the chain pays its full cost (beyond it, one of the two windows is
    placed elsewhere than the other: a broken link), alone_m (W,) how far each window's best
    placement alone puts its cameras from where the chosen one does, and overruled_m: beyond this
    the chain has overruled the window's own façades (its chosen placement is a neighbour's)."""

    prior: GpsPrior | None
    windows: tuple[Placement, ...]
    window_centres_m: np.ndarray
    window_scores: np.ndarray
    link_m: np.ndarray
    top_share: float
    reason: str = ""
    link_agree_m: np.ndarray | None = None
    alone_m: np.ndarray | None = None
    overruled_m: float = 0.0

    def figures(self) -> dict:
        """Truth-free figures for the run's self-assessment (JSON-able, rounded)."""
        alone = self.alone_m if self.alone_m is not None and len(self.alone_m) else None
        return {"used": self.prior is not None, "reason": self.reason or None, "windows": len(self.windows),
                "score_median": round(float(np.median(self.window_scores)), 4) if len(self.window_scores) else None,
                "score_min": round(float(self.window_scores.min()), 4) if len(self.window_scores) else None,
                "link_max_m": round(float(self.link_m.max()), 3) if len(self.link_m) else None,
                "links_broken": None if self.link_agree_m is None else int((self.link_m > self.link_agree_m).sum()),
                "links": len(self.link_m),
                "best_alone_share": round(self.top_share, 4),
                "overruled_share": None if alone is None else round(float(np.mean(alone > self.overruled_m)), 4),
                "alone_max_m": None if alone is None else round(float(alone.max()), 3)}

    def chain_value(self, link_cost: float) -> float:
        """The chain's objective per window: (Σ score − link_cost·Σ min(link / agree, 1)) / windows
        (0 without a window): how well one rigid placement per window fits, links included."""
        if not len(self.window_scores):
            return 0.0
        broken = np.minimum(self.link_m / self.link_agree_m, 1.0).sum() if self.link_agree_m is not None else 0.0
        return float((self.window_scores.sum() - link_cost * broken) / len(self.window_scores))

    def describe(self) -> str:
        scores = " ".join(f"{v:.2f}" for v in self.window_scores)
        links = " ".join(f"{v:.1f}" for v in self.link_m)
        used = "used" if self.prior is not None else f"not used: {self.reason}"
        return (f"route placement {used}; {len(self.windows)} windows, scores [{scores}], "
                f"neighbour disagreement m [{links}], best alone in {self.top_share:.0%}"
                + ("" if self.alone_m is None else f", own best placement m [{' '.join(f'{v:.0f}' for v in self.alone_m)}]"))


def capture_order(image_names) -> np.ndarray:
    """Indices of the images in capture order: by name, numbers compared as numbers (frame_9 < frame_10)."""
    import re

    def key(name: str):
        return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", str(name))]

    return np.array(sorted(range(len(image_names)), key=lambda i: key(image_names[i])), dtype=np.int64)


def outer_outline_map(overview: OverviewSegments, cell_m: float, tolerance_m: float,
                      margin_m: float) -> OutlineMap:
    """Outline pixels next to ground (not to another segment), as a closeness map on a coarse grid."""
    lab = overview.label_image
    inside = lab >= 0
    ground = np.pad(~inside, 1, constant_values=True)
    touches = np.zeros_like(inside)
    for dr, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):
        touches |= ground[dr:dr + lab.shape[0], dc:dc + lab.shape[1]]
    rows, cols = np.nonzero(inside & touches)
    xy = overview.grid.pixel_to_world(rows, cols)
    corner = xy.min(axis=0) - margin_m
    shape = np.ceil((xy.max(axis=0) + margin_m - corner) / cell_m).astype(np.int64) + 1
    occupied = np.zeros(tuple(shape), dtype=bool)
    ij = ((xy - corner) / cell_m).astype(np.int64)
    occupied[ij[:, 0], ij[:, 1]] = True
    d_m = ndimage.distance_transform_edt(~occupied) * cell_m
    close = np.clip(1.0 - d_m / tolerance_m, 0.0, 1.0).astype(np.float32)
    return OutlineMap(corner=corner, cell_m=cell_m, close=close)


def route_arclength(cameras_xy: np.ndarray) -> np.ndarray:
    """(C,) distance travelled to each camera (cameras in capture order)."""
    step = np.linalg.norm(np.diff(cameras_xy, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(step)])


def _window_placements(maps: RouteMaps, pts: np.ndarray, thetas: np.ndarray, keep: int, batch: int = 24,
                       workers: int = 1) -> list[Placement]:
    """Best distinct placements of one window's points over every rotation (FFT correlation)."""
    omap = maps.coarse
    cell = omap.cell_m
    pivot = pts.mean(axis=0)
    radius = np.linalg.norm(pts - pivot, axis=1).max() if len(pts) else 0.0
    spectrum, (H, W) = maps.spectrum(2 * radius + 2 * cell)   # any rotation of the points fits
    found: list[tuple[float, float, int, int, np.ndarray]] = []
    for b0 in range(0, len(thetas), batch):
        th = thetas[b0:b0 + batch]
        imgs = np.zeros((len(th), H, W), dtype=np.float32)
        lows = []
        for r, a in enumerate(th):
            c, s = np.cos(a), np.sin(a)
            ij = np.floor((pts - pivot) @ np.array([[c, s], [-s, c]]) / cell).astype(np.int64)
            low = ij.min(axis=0)
            ij -= low
            lows.append(low)
            if ij[:, 0].max() >= H or ij[:, 1].max() >= W:
                continue
            imgs[r, ij[:, 0], ij[:, 1]] = 1.0
        n = np.maximum(imgs.sum(axis=(1, 2)), 1.0)
        corr = sfft.irfft2(spectrum[None] * np.conj(sfft.rfft2(imgs, axes=(1, 2), workers=workers)), s=(H, W),
                           axes=(1, 2), workers=workers)
        # each rotation's 3 best values lie in its 3 rows with the highest maxima
        rows = np.argpartition(corr.max(axis=2), -3, axis=1)[:, -3:]
        held = np.take_along_axis(corr, rows[:, :, None], axis=1).reshape(len(th), -1)
        best = np.argpartition(held, -3, axis=1)[:, -3:]
        for r in range(len(th)):
            for f in best[r]:
                k, v = divmod(int(f), W)
                found.append((float(held[r, f] / n[r]), float(th[r]), int(rows[r, k]), v, lows[r]))
    found.sort(key=lambda x: -x[0])
    out: list[Placement] = []
    for score, a, u, v, low in found:
        t = omap.corner + (np.array([u, v]) - low) * cell + cell / 2
        dup = any(np.linalg.norm(t - o.t) < 2 * omap.cell_m + radius * abs(_wrap(a - o.theta))
                  and abs(_wrap(a - o.theta)) < np.deg2rad(10) for o in out)
        if not dup:
            out.append(Placement(theta=a, t=t, pivot=pivot, score=score))
        if len(out) >= keep:
            break
    return out


def _refine(fine: OutlineMap, pts: np.ndarray, found: list[Placement], cfg: RoutePriorConfig,
            max_points: int = 300, reach: float = 1.0) -> list[Placement]:
    """Each coarse placement re-scored on the fine map at its best pose within a cell and a rotation
    step of it; best first."""
    if not found:
        return []
    sub = pts[np.linspace(0, len(pts) - 1, min(max_points, len(pts))).round().astype(int)]
    d_theta = np.deg2rad(np.arange(-1.0, 1.01, 0.5) * reach * cfg.rotation_step_deg / 2)
    r = np.arange(-reach * cfg.cell_m, reach * cfg.cell_m + 1e-9, fine.cell_m)
    d_t = np.stack(np.meshgrid(r, r, indexing="ij"), axis=-1).reshape(-1, 2)
    # the shifts are whole fine cells: one gather per pose from a zero-padded map (0 off the map)
    k = np.rint(d_t / fine.cell_m).astype(np.int64)
    pad = int(np.abs(k).max()) + 1
    H, W = fine.close.shape
    padded = np.pad(fine.close, 2 * pad)
    Wp = W + 4 * pad
    shift = (k[:, 0] * Wp + k[:, 1])[None, :, None]
    out = []
    for p in found:
        a = p.theta + d_theta
        c, s = np.cos(a)[:, None], np.sin(a)[:, None]
        q = sub - p.pivot
        base = np.stack([q[:, 0] * c - q[:, 1] * s, q[:, 0] * s + q[:, 1] * c], axis=-1)   # (rotations, points, 2)
        ij = np.floor((base + (p.t - fine.corner)) / fine.cell_m).astype(np.int64)
        i = np.clip(ij[..., 0], -pad, H + pad - 1) + 2 * pad
        j = np.clip(ij[..., 1], -pad, W + pad - 1) + 2 * pad
        score = padded.ravel()[(i * Wp + j)[:, None, :] + shift].mean(axis=2)   # (rotations, shifts)
        best = np.unravel_index(int(np.argmax(score)), score.shape)
        out.append(Placement(theta=float(a[best[0]]), t=p.t + d_t[best[1]], pivot=p.pivot, score=float(score[best])))
    out.sort(key=lambda q: -q.score)
    return out


def _seed_from_neighbours(fine: OutlineMap, windows: list[list[Placement]], window_pts: list[np.ndarray],
                          cfg: RoutePriorConfig, seeds: int = 2) -> list[list[Placement]]:
    """Each window also tries its neighbours' best placements (the drift is slow along the route),
    refined over twice the usual reach: a window that is ambiguous alone follows its neighbours."""
    out = []
    for w, found in enumerate(windows):
        pivot = found[0].pivot
        tried = []
        for n in (w - 1, w + 1):
            if 0 <= n < len(windows):
                for q in windows[n][:seeds]:
                    tried.append(Placement(theta=q.theta, t=q.apply(pivot[None])[0], pivot=pivot, score=q.score))
        extra = _refine(fine, window_pts[w], tried, cfg, reach=2.0) if tried else []
        merged = sorted(found + extra, key=lambda q: -q.score)
        keep: list[Placement] = []
        for q in merged:
            if not any(abs(_wrap(q.theta - k.theta)) < np.deg2rad(1.5) and np.linalg.norm(q.t - k.t) < 2.0
                       for k in keep):
                keep.append(q)
        out.append(keep[:cfg.placements_per_window + len(extra)])
    return out


def agree_m(cfg: RoutePriorConfig, gap_m: float | np.ndarray) -> float | np.ndarray:
    """The disagreement neighbouring windows ``gap_m`` apart may have before their link costs in full:
    ``agree_m`` plus 5 % of the route between them (drift grows with it)."""
    return cfg.agree_m + 0.05 * gap_m


def _chain(windows: list[list[Placement]], links: list[np.ndarray], cfg: RoutePriorConfig,
           gaps_m: np.ndarray, anchors: list[_WindowAnchor] | None = None,
           gps_tolerance_m: float = 1.0) -> tuple[list[int], np.ndarray]:
    """Viterbi over windows: maximise Σ (score − GPS cost) − link_cost·Σ min(disagreement / agree, 1)."""
    def link(a: list[Placement], b: list[Placement], cams: np.ndarray) -> np.ndarray:
        """(len(a), len(b)) RMS distance between where each pair puts the cameras."""
        pa, pb = np.array([p.apply(cams) for p in a]), np.array([p.apply(cams) for p in b])
        return np.sqrt(np.mean(np.sum((pa[:, None] - pb[None]) ** 2, axis=3), axis=2))

    def unary(w: int) -> np.ndarray:
        score = np.array([p.score for p in windows[w]])
        if anchors is None:
            return score
        d = np.array([anchors[w].distance(p) for p in windows[w]])
        return score - cfg.gps_cost * np.minimum(d / (cfg.gps_agree_sigmas * gps_tolerance_m), 1.0)

    value = unary(0)
    back = []
    dist_tables = []
    for w in range(1, len(windows)):
        agree = agree_m(cfg, gaps_m[w - 1])
        d = link(windows[w - 1], windows[w], links[w - 1])
        total = value[:, None] - cfg.link_cost * np.minimum(d / agree, 1.0)
        back.append(np.argmax(total, axis=0))
        value = total.max(axis=0) + unary(w)
        dist_tables.append(d)
    pick = [int(np.argmax(value))]
    for w in range(len(windows) - 1, 0, -1):
        pick.append(int(back[w - 1][pick[-1]]))
    pick.reverse()
    link_m = np.array([dist_tables[w - 1][pick[w - 1], pick[w]] for w in range(1, len(windows))])
    return pick, link_m


@dataclass(frozen=True)
class GpsTrack:
    """Where the GPS fixes put the cameras: position (C,2) scene x, y of each camera (capture order,
    from the local fits of ``toolkit.matching.gps``); tolerance_m: the distance a right placement may
    have from it (the fixes' σ or the fits' RMS, whichever is larger)."""

    position: np.ndarray
    tolerance_m: float


@dataclass(frozen=True)
class _WindowAnchor:
    """A window's cameras (levelled xy) and their GPS positions (scene xy)."""

    cams: np.ndarray
    gps: np.ndarray

    def distance(self, p: Placement) -> float:
        return float(np.sqrt(np.mean(np.sum((p.apply(self.cams) - self.gps) ** 2, axis=1))))

    def placement(self, pivot: np.ndarray) -> Placement:
        """The rigid placement that puts the cameras on their GPS positions."""
        from toolkit.matching.gps import rigid_fit_2d

        theta, t0 = rigid_fit_2d(self.cams[None], self.gps[None], np.ones((1, len(self.cams))))
        c, s = np.cos(theta[0]), np.sin(theta[0])
        return Placement(theta=float(theta[0]), t=np.array([[c, -s], [s, c]]) @ pivot + t0[0], pivot=pivot, score=0.0)


@dataclass(frozen=True)
class RouteMaps:
    """The over-view's outer outlines as the placement search reads them: the coarse closeness map,
    its spectra (``spectrum``) and the fine map the placements are re-scored on. They depend on the
    over-view and the config only (``route_maps``), so a search over street scales builds them once."""

    coarse: OutlineMap
    fine: OutlineMap
    _spectra: dict = field(default_factory=dict, repr=False, compare=False)
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def spectrum(self, extent_m: float) -> tuple[np.ndarray, tuple[int, int]]:
        """The coarse map's spectrum at an FFT shape padded for point sets ``extent_m`` across (the
        correlation does not wrap around), and that shape; one per shape, kept."""
        pad = int(np.ceil(extent_m / self.coarse.cell_m)) + 2
        H, W = self.coarse.close.shape
        shape = (sfft.next_fast_len(H + pad, real=True), sfft.next_fast_len(W + pad, real=True))
        with self._lock:  # the scale scan places several factors at once
            if shape not in self._spectra:
                self._spectra[shape] = sfft.rfft2(self.coarse.close, s=shape).astype(np.complex64)
            return self._spectra[shape], shape


def route_maps(overview: OverviewSegments, cfg: RoutePriorConfig) -> RouteMaps:
    omap = outer_outline_map(overview, cfg.cell_m, cfg.tolerance_m, margin_m=2 * cfg.tolerance_m)
    fine = outer_outline_map(overview, cfg.fine_cell_m, cfg.fine_tolerance_m, margin_m=2 * cfg.tolerance_m)
    return RouteMaps(omap, fine)


def place_route(street: StreetSegments, overview: OverviewSegments, cameras_xy: np.ndarray,
                cfg: RoutePriorConfig, maps: RouteMaps | None = None, track: GpsTrack | None = None,
                rotations: dict[int, np.ndarray] | None = None) -> RoutePlacement:
    """The placement of the route (levelled street xy → scene xy) and the prior it gives each segment.
    ``maps``: ``route_maps(overview, cfg)`` when already made. ``track``: the cameras' GPS positions
    (same order as ``cameras_xy``): each window also tries the placement that fits them, and the
    chain pays for placements far from them. ``rotations``: the rotations (radians) searched in
    some windows, by the window's index along the route (``window_index``); the others search all."""
    arc = route_arclength(cameras_xy)
    pts, seg = _facade_cells(street, cfg.cell_m / 2)
    from scipy.spatial import cKDTree

    s_pt = arc[cKDTree(cameras_xy).query(pts)[1]]
    maps = maps or route_maps(overview, cfg)
    found = _search_windows(pts, s_pt, arc, cameras_xy, maps, cfg, track, rotations or {})
    if not found.windows:
        return RoutePlacement(None, (), found.centres, np.zeros(0), np.zeros(0), 0.0, "no window with façades")
    windows, centres = found.windows, found.centres
    links = [_cameras_between(cameras_xy, arc, a, b) for a, b in zip(centres[:-1], centres[1:])]
    chain_gps = {"anchors": found.anchors, "gps_tolerance_m": track.tolerance_m} if track is not None else {}
    pick, link_m = _chain(windows, links, cfg, np.diff(centres), **chain_gps)
    agree = agree_m(cfg, np.diff(centres))
    # a window off the chain tries its chosen neighbours' placements, then the chain again. Without GPS a
    # group of windows placed elsewhere comes back one window per round, so rounds go on while the chain
    # moves; with GPS every window also has the track's placement (two rounds, as measured)
    for _ in range(len(windows) if track is None else 2):
        if not _retry_off_chain(windows, found.points, pick, link_m > agree, maps.fine, cfg):
            break
        before, (pick, link_m) = pick, _chain(windows, links, cfg, np.diff(centres), **chain_gps)
        if pick == before:
            break
    chosen = tuple(windows[w][h] for w, h in enumerate(pick))
    scores = np.array([p.score for p in chosen])
    top_share = float(np.mean([h == 0 for h in pick]))
    alone = _alone_m(windows, chosen, cameras_xy, arc, centres, cfg.window_m)
    told = {"link_agree_m": agree, "alone_m": alone, "overruled_m": cfg.agree_m}
    if np.median(scores) < cfg.min_score:
        return RoutePlacement(None, chosen, centres, scores, link_m, top_share,
                              f"median window score {np.median(scores):.2f} < {cfg.min_score}", **told)
    prior = _segment_prior(street, seg, s_pt, chosen, centres, cfg)
    return RoutePlacement(prior, chosen, centres, scores, link_m, top_share, **told)


def _alone_m(windows: list[list[Placement]], chosen: tuple[Placement, ...], cameras_xy: np.ndarray,
             arc: np.ndarray, centres: np.ndarray, window_m: float) -> np.ndarray:
    """(W,) RMS distance between where each window's best placement alone (its best score) and its
    chosen one put the window's cameras."""
    out = np.zeros(len(chosen))
    for w, (found, p) in enumerate(zip(windows, chosen)):
        cams = _cameras_between(cameras_xy, arc, centres[w] - window_m / 2, centres[w] + window_m / 2)
        out[w] = np.sqrt(np.mean(np.sum((found[0].apply(cams) - p.apply(cams)) ** 2, axis=1)))
    return out


@dataclass(frozen=True)
class _WindowSearch:
    """The windows with façades, in route order: each one's candidate placements (best first), its
    route centre, its façade points and, with GPS, its cameras' anchor (else ``anchors`` is empty)."""

    windows: list[list[Placement]]
    centres: np.ndarray
    points: list[np.ndarray]
    anchors: list[_WindowAnchor]


def rotation_grid(step_deg: float) -> np.ndarray:
    """The rotations (radians) a window's placement is searched over."""
    return np.deg2rad(np.arange(0.0, 360.0, step_deg))


def window_index(centre_m: float, window_m: float) -> int:
    """The index along the route of the window centred ``centre_m`` of route (windows overlap by half)."""
    return int(round(centre_m / (window_m / 2))) - 1


def _search_windows(pts: np.ndarray, s_pt: np.ndarray, arc: np.ndarray, cameras_xy: np.ndarray, maps: RouteMaps,
                    cfg: RoutePriorConfig, track: GpsTrack | None,
                    rotations: dict[int, np.ndarray]) -> _WindowSearch:
    """Every half-overlapping window of route: its best placements on the outlines, then those of its
    neighbours (``_seed_from_neighbours``), then, with GPS, the one that puts its cameras on the track."""
    starts = np.arange(0.0, max(arc[-1] - cfg.window_m / 2, 0.0) + 1e-9, cfg.window_m / 2)
    thetas = rotation_grid(cfg.rotation_step_deg)
    windows, centres, window_pts, anchors, by_gps = [], [], [], [], []
    for k, w0 in enumerate(starts):
        sel = (s_pt >= w0) & (s_pt < w0 + cfg.window_m)
        if sel.sum() < 30:  # a park or an open square: the neighbours carry it
            continue
        found = _window_placements(maps, pts[sel], rotations.get(k, thetas), cfg.candidates_per_window)
        found = _refine(maps.fine, pts[sel], found, cfg)[:cfg.placements_per_window]
        if not found:
            continue
        if track is not None:
            cams = (arc >= w0) & (arc < w0 + cfg.window_m)
            anchors.append(_WindowAnchor(cameras_xy[cams], track.position[cams]))
            by_gps.append(_refine(maps.fine, pts[sel], [anchors[-1].placement(found[0].pivot)], cfg, reach=2.0))
        windows.append(found)
        window_pts.append(pts[sel])
        centres.append(w0 + cfg.window_m / 2)
    windows = _seed_from_neighbours(maps.fine, windows, window_pts, cfg)
    if by_gps:  # after the seeding, which keeps only the best-scoring placements
        windows = [sorted(found + extra, key=lambda q: -q.score) for found, extra in zip(windows, by_gps)]
    return _WindowSearch(windows, np.asarray(centres), window_pts, anchors)


def _retry_off_chain(windows: list[list[Placement]], window_pts: list[np.ndarray], pick: list[int],
                     broken: np.ndarray, fine: OutlineMap, cfg: RoutePriorConfig) -> bool:
    """Each window at a broken link also tries its neighbours' chosen placements (in place). False
    when no link is broken."""
    off = np.zeros(len(windows), bool)
    off[:-1] |= broken
    off[1:] |= broken
    for w in np.nonzero(off)[0]:
        pivot = windows[w][0].pivot
        tried = [Placement(theta=windows[n][pick[n]].theta, t=windows[n][pick[n]].apply(pivot[None])[0],
                           pivot=pivot, score=0.0) for n in (w - 1, w + 1) if 0 <= n < len(windows)]
        windows[w] = sorted(windows[w] + _refine(fine, window_pts[w], tried, cfg, reach=2.0), key=lambda q: -q.score)
    return bool(off.any())


def _facade_cells(street: StreetSegments, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """One façade point per cell of each segment (levelled xy) and its segment index."""
    pts, seg = [np.zeros((0, 2))], [np.zeros(0, np.int64)]
    for i, xy in enumerate(street.boundary_xy):  # one iteration per street segment
        if len(xy) == 0:
            continue
        _, first = np.unique(np.floor(np.asarray(xy) / cell_m).astype(np.int64), axis=0, return_index=True)
        pts.append(np.asarray(xy)[np.sort(first)])
        seg.append(np.full(len(first), i, np.int64))
    return np.concatenate(pts), np.concatenate(seg)


def _cameras_between(cameras_xy: np.ndarray, arc: np.ndarray, a: float, b: float, n: int = 16) -> np.ndarray:
    idx = np.nonzero((arc >= a) & (arc <= b))[0]
    if len(idx) == 0:
        idx = np.array([int(np.argmin(np.abs(arc - (a + b) / 2)))])
    return cameras_xy[idx[np.linspace(0, len(idx) - 1, min(n, len(idx))).round().astype(int)]]


def _segment_prior(street: StreetSegments, seg: np.ndarray, s_pt: np.ndarray, chosen: tuple[Placement, ...],
                   centres: np.ndarray, cfg: RoutePriorConfig) -> GpsPrior:
    """Each segment from the two windows nearest its route position, blended; their disagreement
    there is its fit residual (the data term widens its radius by it)."""
    S = len(street)
    cent = np.asarray(street.centroids, dtype=np.float64).reshape(-1, 2)
    s_seg = np.array([np.median(s_pt[seg == i]) if np.any(seg == i) else np.nan for i in range(S)])
    s_seg = np.where(np.isfinite(s_seg), s_seg, np.nanmedian(s_seg) if np.isfinite(s_seg).any() else 0.0)
    pos, ang, rms = np.zeros((S, 2)), np.zeros(S), np.zeros(S)
    for i in range(S):  # one iteration per street segment
        order = np.argsort(np.abs(centres - s_seg[i]))[:2]
        w = np.maximum(cfg.window_m / 2 - np.abs(centres[order] - s_seg[i]), 1e-3)
        placed = np.array([chosen[o].apply(cent[i][None])[0] for o in order])
        pos[i] = (w[:, None] * placed).sum(axis=0) / w.sum()
        th = np.array([chosen[o].theta for o in order])
        ang[i] = np.arctan2((w * np.sin(th)).sum(), (w * np.cos(th)).sum())
        rms[i] = np.linalg.norm(placed[0] - placed[-1]) / 2
    return GpsPrior(position=pos, angle=ang, n_fixes=len(chosen), sigma_m=cfg.sigma_m, fit_rms_m=rms)


def _wrap(a: float) -> float:
    return float(np.mod(a + np.pi, 2 * np.pi) - np.pi)
