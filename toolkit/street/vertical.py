"""The vertical direction of a street cloud from the distribution of its normals (Ling & Qin 2022, street-view building segments).

1. Histogram of normal orientations on the sphere (Fibonacci lattice, ~``bin_deg`` cells, each
   normal counted with its antipode since PCA normals have no sign); candidates are local maxima
   holding more than 1/1000 of the normals.
2. Each candidate is scored by the share of normals parallel or perpendicular to it (the released
   code's score) and the best ones are refined: the axis that is perpendicular to the façade
   normals, least squares over the normals within a shrinking angular window, with a small
   ground (parallel) term that only matters when all façades face one way.
3. Ground and façades make every horizontal axis of a Manhattan street grid score as well as the
   true one, so the survivors are told apart and the sign is resolved by one physical fact:
   façades rise above the ground next to them. In horizontal cells (``cell_m``) holding both
   near-parallel ("ground") and near-perpendicular ("façade") points, the façade points must be
   higher; the candidate whose cells agree most is up, oriented so that they do. Streets lined on
   both sides make this vote split for a horizontal axis; where it cannot (one wall and the ground
   only, which are alike), near-ties go to the axis along which the cloud is thinnest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field
from scipy.spatial import cKDTree

from toolkit.errors import StageError
from toolkit.street.params import StreetConfig


class VerticalConfig(StreetConfig):
    """The vertical from the normals (see ``find_vertical``)."""

    bin_deg: float = Field(2.0, gt=0, le=10, description="sphere histogram bin size for the vertical (degrees)")
    min_support: float = Field(
        0.2, ge=0, le=1, description="min share of normals parallel or perpendicular (±5°) to the found vertical")
    cell_m: float = Field(4.0, gt=0, description="cell size of the façade-above-ground sign test (m)")
    sample: int = Field(100_000, ge=1000, description="normals sampled for the vertical (count)")


@dataclass(frozen=True)
class Vertical:
    """up: (3,) unit vector in the input frame; support: share of sampled normals within
    ``support_deg`` of parallel or perpendicular to it; agreement: share of cells whose façade
    points are above their ground points; cells: how many cells voted."""

    up: np.ndarray
    support: float
    agreement: float
    cells: int
    candidates: int


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (1.0 + 5**0.5) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def histogram_candidates(normals: np.ndarray, bin_deg: float, min_share: float,
                         max_candidates: int) -> np.ndarray:
    """(C,3) local maxima of the axial orientation histogram, strongest first, antipodes merged."""
    bin_rad = np.radians(bin_deg)
    lattice = fibonacci_sphere(max(64, int(np.ceil(4 * np.pi / bin_rad**2))))
    tree = cKDTree(lattice)
    counts = np.zeros(len(lattice), dtype=np.int64)
    for sign in (1.0, -1.0):
        counts += np.bincount(tree.query(sign * normals)[1], minlength=len(lattice))
    _, nbrs = tree.query(lattice, k=9)
    is_max = (counts >= counts[nbrs].max(axis=1)) & (counts > min_share * len(normals))
    peaks = np.flatnonzero(is_max)
    peaks = peaks[np.argsort(-counts[peaks], kind="stable")]
    kept: list[np.ndarray] = []
    for p in peaks:  # a few dozen peaks at most
        v = lattice[p]
        if all(abs(v @ k) < np.cos(np.radians(5 * bin_deg)) for k in kept):
            kept.append(v)
        if len(kept) == max_candidates:
            break
    return np.array(kept).reshape(-1, 3)


def axis_support(normals: np.ndarray, axis: np.ndarray, tol_deg: float) -> float:
    """Share of normals within ``tol_deg`` of parallel or of perpendicular to ``axis``."""
    d = np.abs(normals @ axis)
    return float(((d > np.cos(np.radians(tol_deg))) | (d < np.sin(np.radians(tol_deg)))).mean())


def refine_axis(normals: np.ndarray, axis: np.ndarray, windows_deg: tuple[float, ...] = (10.0, 6.0, 4.0, 4.0),
                ground_weight: float = 0.01) -> np.ndarray:
    """Least-squares up: minimise Σ_façade (n·u)² − w Σ_ground (n·u)² over the normals in the window."""
    u = axis / np.linalg.norm(axis)
    for win in windows_deg:
        d = normals @ u
        perp = normals[np.abs(d) < np.sin(np.radians(win))]
        par = normals[np.abs(d) > np.cos(np.radians(win))]
        a = np.zeros((3, 3))
        if len(perp):
            a += perp.T @ perp / len(perp)
        if len(par):
            a -= ground_weight * (par.T @ par) / len(par)
        _, vecs = np.linalg.eigh(a)
        new = vecs[:, 0]
        u = new if new @ u >= 0 else -new
    return u


def façade_above_ground(points: np.ndarray, normals: np.ndarray, up: np.ndarray, cell_m: float,
                        angle_deg: float = 15.0, min_points: int = 5) -> tuple[float, int, int]:
    """Vote of horizontal cells on whether façade points lie above ground points along ``up``.

    Returns (agreement in [0.5, 1], sign +1/-1 of the majority, number of voting cells).
    """
    d = normals @ up
    ground = np.abs(d) > np.cos(np.radians(angle_deg))
    facade = np.abs(d) < np.sin(np.radians(angle_deg))
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    cells = np.floor(np.stack([points @ e1, points @ e2], axis=1) / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    key = cells[:, 0] * (cells[:, 1].max() + 1) + cells[:, 1]
    _, inv = np.unique(key, return_inverse=True)
    h = points @ up
    m = inv.max() + 1 if len(inv) else 0
    ng = np.bincount(inv[ground], minlength=m)
    nf = np.bincount(inv[facade], minlength=m)
    hg = np.bincount(inv[ground], weights=h[ground], minlength=m) / np.maximum(ng, 1)
    hf = np.bincount(inv[facade], weights=h[facade], minlength=m) / np.maximum(nf, 1)
    voting = (ng >= min_points) & (nf >= min_points)
    n = int(voting.sum())
    if n == 0:
        return 0.5, 1, 0
    above = int((hf[voting] > hg[voting]).sum())
    sign = 1 if 2 * above >= n else -1
    return max(above, n - above) / n, sign, n


def estimate_up(points: np.ndarray, normals: np.ndarray, *, bin_deg: float = 2.0, min_share: float = 1e-3,
                max_candidates: int = 12, compare: int = 3, support_deg: float = 5.0, cell_m: float = 4.0,
                sample: int = 100_000, coarse_sample: int = 40_000, tie_share: float = 0.9,
                seed: int = 0) -> Vertical | None:
    """Up direction of ``points`` (M,3) with unit ``normals`` (M,3); None when no peak exists.

    The histogram and candidate scores use ``coarse_sample`` normals, the refinement and the sign
    test ``sample`` points: the answer is an average, more normals only cost time.
    """
    rng = np.random.default_rng(seed)
    if len(points) > sample:
        pick = np.sort(rng.choice(len(points), sample, replace=False))
        points, normals = points[pick], normals[pick]
    normals = np.asarray(normals, dtype=np.float64)
    norm = np.linalg.norm(normals, axis=1)
    ok = np.isfinite(norm) & (norm > 0.5)
    points, normals = points[ok], normals[ok] / norm[ok, None]
    if len(normals) == 0:
        return None
    coarse = rng.permutation(len(normals))[:coarse_sample]
    c_normals = normals[coarse]
    cands = histogram_candidates(c_normals, bin_deg, min_share, max_candidates)
    if len(cands) == 0:
        return None
    scores = np.array([axis_support(c_normals, c, support_deg) for c in cands])
    order = np.argsort(-scores, kind="stable")[:compare]
    found = []
    for c in cands[order]:
        u = refine_axis(normals, c)
        support = axis_support(normals, u, support_deg)
        agreement, sign, n_cells = façade_above_ground(points, normals, u, cell_m)
        # agreement decides between axes that explain the normals about as well (Manhattan grids)
        rank = support * (2.0 * agreement - 1.0) if n_cells else 0.0
        h = points @ u
        extent = float(np.quantile(h, 0.99) - np.quantile(h, 0.01))
        found.append((rank, extent, support, sign * u, agreement, n_cells))
    top = max(f[0] for f in found)
    # near-ties (e.g. a street lined on one side only, where ground and wall look alike): a street
    # cloud is far flatter than it is long, so the axis along which it is thinnest is up
    close = [f for f in found if f[0] >= tie_share * top]
    _, _, support, up, agreement, n_cells = min(close, key=lambda f: f[1])
    return Vertical(up=up, support=support, agreement=agreement, cells=n_cells, candidates=len(cands))


def find_vertical(points: np.ndarray, normals: np.ndarray, cfg: VerticalConfig, seed: int, who: str) -> Vertical:
    """``estimate_up`` with ``cfg``; a ``StageError`` (one line) when the normals hold no vertical."""
    vertical = estimate_up(points, normals, bin_deg=cfg.bin_deg, cell_m=cfg.cell_m, sample=cfg.sample, seed=seed)
    if vertical is None or vertical.support < cfg.min_support:
        support = 0.0 if vertical is None else vertical.support
        raise StageError(f"{who}: no vertical structure: normals have no dominant orientation "
                         f"(support {support:.2f} < vertical.min_support {cfg.min_support}; "
                         f"a street frame far from metric does this: set street_scale)")
    return vertical
