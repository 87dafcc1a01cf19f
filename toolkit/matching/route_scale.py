"""The street frame's scale from its façades and the over-view outlines alone (no GPS).

A monocular SfM model has no metric scale. The route placement (``toolkit.matching.route_prior``)
fits one rigid placement per window of route onto the over-view's outer outlines; at the true
scale every window's façades line up with the outlines at once, so the chain's objective per window
(``RoutePlacement.chain_value``) has a sharp peak there. Away from it the objective drifts smoothly
with the factor: a street shrunk onto the map fits somewhere more easily (fewer, closer façade cells),
so the raw objective favours small factors. ``scan_scale`` therefore scans candidate factors g
(levelled street xy × g = metres) over a range with a coarse step, takes each value's height above
the scan's robust trend (a Theil-Sen line in log g) in units of the residuals' robust spread (the
*prominence*), scans finely around the most prominent coarse peak, and puts a parabola through the
best fine value and its neighbours (in log g). A window's rotation does not depend on the factor, so
the fine scan searches each window only near the rotation its placement has at that coarse peak.

A peak whose prominence is below ``min_prominence`` is no evidence of a scale (a route the placement
cannot place at any scale looks like this), and the caller keeps its first guess.
See docs/scale_and_heights.md.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from scipy.spatial import cKDTree

from toolkit.matching.route_prior import (
    RouteMaps,
    RoutePlacement,
    RoutePriorConfig,
    place_route,
    rotation_grid,
    route_arclength,
    route_maps,
    window_index,
)
from toolkit.types import OverviewSegments, StreetSegments


class ScaleSearchConfig(BaseModel):
    """The scan over street scales (see toolkit.matching.route_scale)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    coarse_step: float = Field(0.04, gt=0, le=0.5, description="relative step of the coarse scan (fraction)")
    fine_step: float = Field(0.015, gt=0, le=0.2, description="relative step of the fine scan (fraction)")
    fine_reach: float = Field(0.075, gt=0, le=0.5, description="the fine scan covers the best coarse factor ± this (fraction)")
    stretch_windows: float = Field(3.0, gt=0, description="length of route scanned, the stretch with the most façades (route placement windows)")
    coarse_factor: float = Field(2.0, ge=1, description="the coarse scan's rotation step over the route placement's (factor)")
    fine_rotation_reach_deg: float = Field(15.0, ge=0, le=180, description="the fine scan searches each window's rotations within this of its placement at the best coarse factor (degrees; 0: every rotation)")
    peak_apart: float = Field(0.15, gt=0, description="coarse peaks closer than this (relative) are one peak (fraction)")
    min_prominence: float = Field(4.5, ge=0, description="least prominence (robust z above the scan's trend) of a peak taken as the scale")


@dataclass(frozen=True)
class ScaleScan:
    """factor: the best g (levelled street xy × g = metres); value: its chain value per window;
    prominence: the coarse peak's robust z above the scan's trend (None: no coarse scan);
    runner_up: the most prominent other coarse peak's factor and runner_up_prominence its z (None:
    no other peak); coarse, fine: (n, 2) arrays of (g, value) as scanned; evaluations: placements
    computed."""

    factor: float
    value: float
    prominence: float | None
    runner_up: float | None
    runner_up_prominence: float | None
    coarse: np.ndarray
    fine: np.ndarray
    evaluations: int

    def figures(self) -> dict:
        r = (lambda v, k=4: None if v is None else round(v, k))
        return {"factor": round(self.factor, 5), "value": round(self.value, 4), "prominence": r(self.prominence, 2),
                "runner_up_factor": r(self.runner_up), "runner_up_prominence": r(self.runner_up_prominence, 2),
                "evaluations": self.evaluations}


def scaled_street(street: StreetSegments, g: float) -> StreetSegments:
    """The segments' horizontal geometry × g (what the route placement reads)."""
    return replace(street, boundary_xy=tuple(np.asarray(b) * g for b in street.boundary_xy),
                   centroids=np.asarray(street.centroids) * g, extent_m=np.asarray(street.extent_m) * g)


def scan_stretch(street: StreetSegments, cams_xy: np.ndarray, length: float) -> tuple[StreetSegments, np.ndarray]:
    """The segments and cameras of the ``length`` of route (levelled frame units) holding the most
    façade points (the whole route when it is shorter): the scan's cost then does not grow with the route."""
    arc = route_arclength(cams_xy)
    if arc[-1] <= length:
        return street, cams_xy
    cent = np.asarray(street.centroids, np.float64).reshape(-1, 2)
    _, nearest = cKDTree(cams_xy).query(cent)
    s_seg = arc[nearest]
    weight = np.array([len(b) for b in street.boundary_xy], np.float64)
    starts = np.linspace(0.0, arc[-1] - length, 33)
    held = [weight[(s_seg >= a) & (s_seg <= a + length)].sum() for a in starts]
    a = starts[int(np.argmax(held))]
    keep = np.flatnonzero((s_seg >= a) & (s_seg <= a + length))
    cams = cams_xy[(arc >= a) & (arc <= a + length)]
    sub = replace(street, ids=np.asarray(street.ids)[keep], boundary_xy=tuple(street.boundary_xy[i] for i in keep),
                  centroids=cent[keep], extent_m=np.asarray(street.extent_m)[keep])
    return sub, cams


def coarse_config(cfg: RoutePriorConfig, search: ScaleSearchConfig) -> RoutePriorConfig:
    """The route placement's config for the coarse scan: rotations farther apart (its maps and
    windows stay: coarser maps, looser tolerances or shorter windows lose the true scale's peak)."""
    f = search.coarse_factor
    return cfg.model_copy(update={"rotation_step_deg": min(f * cfg.rotation_step_deg, 30.0)})


def _placed(street: StreetSegments, overview: OverviewSegments, cams_xy: np.ndarray, g: float,
            cfg: RoutePriorConfig, maps: RouteMaps, rotations: dict[int, np.ndarray] | None = None) -> RoutePlacement:
    """The route placement at factor g, its windows fixed in the street frame (window_m × g metres),
    so that every factor places the same point sets."""
    at = cfg.model_copy(update={"window_m": cfg.window_m * g})
    return place_route(scaled_street(street, g), overview, cams_xy * g, at, maps, rotations=rotations)


def _values(street, overview, cams_xy, grid: np.ndarray, cfg: RoutePriorConfig, maps: RouteMaps,
            workers: int, rotations: dict[int, np.ndarray] | None = None) -> tuple[np.ndarray, list[RoutePlacement]]:
    """The chain value per window (``RoutePlacement.chain_value``) at every factor, and the placements."""
    def one(g):
        return _placed(street, overview, cams_xy, g, cfg, maps, rotations)

    if workers <= 1:
        placed = [one(g) for g in grid]
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(workers, "crossview-scale") as pool:
            placed = list(pool.map(one, grid))
    return np.array([p.chain_value(cfg.link_cost) for p in placed]), placed


def near_rotations(placed: RoutePlacement, g: float, window_m: float, step_deg: float,
                   reach_deg: float) -> dict[int, np.ndarray]:
    """Per window (``window_index``), the route placement's rotations (every ``step_deg``) within
    ``reach_deg`` of the rotation its window has in ``placed`` (made at factor g)."""
    grid = rotation_grid(step_deg)   # the placement's own grid: the same rotations, the same FFTs
    out = {}
    for p, c in zip(placed.windows, placed.window_centres_m):
        off = np.abs((grid - p.theta + np.pi) % (2 * np.pi) - np.pi)
        out[window_index(c / g, window_m)] = grid[off <= np.deg2rad(max(reach_deg, step_deg / 2)) + 1e-9]
    return out


def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    n = max(int(np.ceil(np.log(hi / lo) / np.log1p(step))), 1)
    return np.exp(np.linspace(np.log(lo), np.log(hi), n + 1))


def prominence(grid: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Each value's height above the robust trend of the scan (Theil-Sen line in log g), in units of
    the residuals' robust spread (1.4826 MAD)."""
    from scipy.stats import theilslopes

    x = np.log(grid)
    slope, intercept, _, _ = theilslopes(values, x)
    r = values - (intercept + slope * x)
    spread = 1.4826 * np.median(np.abs(r - np.median(r)))
    return r / max(spread, 1e-6)


def _peaks(values: np.ndarray) -> np.ndarray:
    """Indices of the local maxima (ends included), best first."""
    v = np.concatenate([[-np.inf], values, [-np.inf]])
    idx = np.flatnonzero((v[1:-1] >= v[:-2]) & (v[1:-1] >= v[2:]))
    return idx[np.argsort(-values[idx], kind="stable")]


def _parabola_peak(g: np.ndarray, v: np.ndarray, i: int) -> float:
    """The vertex (in log g) of the parabola through the best value and its two neighbours."""
    if i == 0 or i == len(g) - 1:
        return float(g[i])
    x = np.log(g[i - 1:i + 2])
    a, b, _ = np.polyfit(x, v[i - 1:i + 2], 2)
    if a >= 0:
        return float(g[i])
    return float(np.exp(np.clip(-b / (2 * a), x[0], x[2])))


def scan_scale(street: StreetSegments, overview: OverviewSegments, cams_xy: np.ndarray, lo: float, hi: float,
               cfg: RoutePriorConfig, search: ScaleSearchConfig, coarse: bool = True, workers: int = 1) -> ScaleScan:
    """The factor g in [lo, hi] whose route placement fits best (see the module doc). ``coarse``:
    False scans only the fine grid over [lo, hi] (a range already narrow). ``workers``: threads,
    one factor each (the result does not depend on them)."""
    street, cams_xy = scan_stretch(street, cams_xy, search.stretch_windows * cfg.window_m)
    maps = route_maps(overview, cfg)
    n_eval = 0
    z_best = runner = z_runner = None
    coarse_gv = np.zeros((0, 2))
    rotations = None
    if coarse:
        ccfg = coarse_config(cfg, search)
        g_c = _grid(lo, hi, search.coarse_step)
        v_c, placed_c = _values(street, overview, cams_xy, g_c, ccfg, maps, workers)
        n_eval += len(g_c)
        coarse_gv = np.column_stack([g_c, v_c])
        z = prominence(g_c, v_c)
        peaks = _peaks(z)
        best = peaks[0]
        z_best = float(z[best])
        others = [p for p in peaks[1:] if abs(np.log(g_c[p] / g_c[best])) > np.log1p(search.peak_apart)]
        if others:
            runner, z_runner = float(g_c[others[0]]), float(z[others[0]])
        centre = float(g_c[best])
        lo_f, hi_f = max(lo, centre / (1 + search.fine_reach)), min(hi, centre * (1 + search.fine_reach))
        if search.fine_rotation_reach_deg > 0:  # a window's rotation does not depend on the factor
            rotations = near_rotations(placed_c[best], centre, cfg.window_m, cfg.rotation_step_deg,
                                       search.fine_rotation_reach_deg)
    else:
        lo_f, hi_f = lo, hi
    g_f = _grid(lo_f, hi_f, search.fine_step)
    v_f, _ = _values(street, overview, cams_xy, g_f, cfg, maps, workers, rotations)
    n_eval += len(g_f)
    i = int(np.argmax(v_f))
    return ScaleScan(_parabola_peak(g_f, v_f, i), float(v_f[i]), z_best, runner, z_runner, coarse_gv,
                     np.column_stack([g_f, v_f]), n_eval)
