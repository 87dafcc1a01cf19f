"""Coarse GPS fixes → an approximate scene position and heading of each street segment.

street/gps.csv (image_name,lon,lat[,sigma_m]) names COLMAP images; their camera centres, levelled,
pair with the fixes projected to the scene CRS. For each street segment a weighted 2D rigid fit
(scale is metric) over the ``n_local`` fixes nearest to it (released code: one fit per block of
~100 fixes, which follows the drift of a long route) predicts where the segment lies.

The data term (``GpsConfig``) trusts each predicted position within a radius (from the fixes' σ,
widened where the local fit's residual is large) and the predicted heading within ``angle_deg``;
the route placement (``toolkit.matching.route_prior``) gives a ``GpsPrior`` used the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.matching.config import MatchingConfig
from toolkit.matching.mrf import wrap_angle
from toolkit.types import StreetSegments


class GpsConfig(MatchingConfig):
    """How the data term uses a prior position of each segment: GPS fixes or the route placement."""

    flat_prefix = "gps_"

    radius_m: float | None = Field(None, gt=0, description="prune poses putting a segment centre farther than "
                                                          "this from its GPS position (m; None: from the fixes' σ)")
    cost_weight: float = Field(0.3, ge=0, description="weight w of the soft prior w·(d / GPS radius)² added to "
                                                      "the raw chamfer cost (0: hard pruning only)")
    radius_sigmas: float = Field(5.0, gt=0, description="GPS radius in fix σ when radius_m is None")
    radius_fit_sigmas: float | None = Field(
        3.0, gt=0, description="with radius_m None: widen a segment's radius to this many RMS residuals "
                               "of its local GPS fit (None: off)")
    radius_margin_m: float = Field(5.0, ge=0, description="added to the σ-based GPS radius (pose error of "
                                                          "the candidate itself)")
    angle_deg: float | None = Field(45.0, gt=0, description="prune candidates whose rotation differs more "
                                                            "(degrees; None: no test)")
    fit_fixes: int = Field(100, ge=3, description="GPS fixes per local rigid fit (count; nearest to the segment)")


@dataclass(frozen=True)
class GpsPrior:
    """position: (S,2) predicted scene x, y of each street segment centroid; angle: (S,) rotation
    (levelled street → scene) of the local fit; n_fixes: fixes used; sigma_m: their median σ;
    fit_rms_m: (S,) RMS residual (metres) of the inlier fixes of each segment's local fit, or None.

    fit_rms_m is the fit's own measure of how well a rigid motion explains the fixes around the
    segment. Where the SfM street frame bends or the fixes are biased it is far above σ (campus seed 2:
    ~20 m around the segments whose predicted position is off by 20-50 m, ≤ 6 m elsewhere), so a
    radius built from σ alone prunes their true candidates."""

    position: np.ndarray
    angle: np.ndarray
    n_fixes: int
    sigma_m: float = 10.0  # median stated accuracy of the fixes used (the default when none is given)
    fit_rms_m: np.ndarray | None = None


def rigid_fit_2d(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Batched weighted 2D rigid fit dst ≈ R(θ) src + t. src, dst: (B,K,2); w: (B,K). → θ (B,), t (B,2)."""
    ws = w / np.maximum(w.sum(axis=1, keepdims=True), 1e-300)
    ms = np.einsum("bk,bki->bi", ws, src)
    md = np.einsum("bk,bki->bi", ws, dst)
    a, b = src - ms[:, None], dst - md[:, None]
    cross = np.einsum("bk,bk->b", ws, a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0])
    dot = np.einsum("bk,bk->b", ws, a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1])
    theta = np.arctan2(cross, dot)
    c, s = np.cos(theta), np.sin(theta)
    t = md - np.stack([c * ms[:, 0] - s * ms[:, 1], s * ms[:, 0] + c * ms[:, 1]], axis=1)
    return theta, t


def _apply(theta: np.ndarray, t: np.ndarray, xy: np.ndarray) -> np.ndarray:
    c, s = np.cos(theta)[..., None], np.sin(theta)[..., None]
    return np.stack([c[..., 0] * xy[..., 0] - s[..., 0] * xy[..., 1],
                     s[..., 0] * xy[..., 0] + c[..., 0] * xy[..., 1]], axis=-1) + t


def gps_prior(capture: StreetCapture, street: StreetSegments, n_local: int = 100, default_sigma_m: float | None = None,
              warn=None) -> GpsPrior | None:
    """The prior from the capture's fixes and COLMAP cameras (in the CRS of its scene), or None (with
    a warning) when fewer than 3 fixes match COLMAP images."""
    cent = np.asarray(street.centroids, dtype=np.float64).reshape(-1, 2)
    return gps_predict(capture, street, cent, n_local, default_sigma_m, warn)


def gps_predict(capture: StreetCapture, street: StreetSegments, query_xy: np.ndarray, n_local: int = 100,
                default_sigma_m: float | None = None, warn=None) -> GpsPrior | None:
    """Scene x, y of levelled street points ``query_xy`` (Q,2), each from the rigid fit of its
    ``n_local`` nearest fixes (as a ``GpsPrior`` over the Q points), or None as ``gps_prior``."""
    from toolkit.io.gps import match_images

    fixes = capture.gps
    names = list(fixes.names)
    model = capture.require_sparse("unary.distance_map (GPS pruning)")
    image = match_images(names, model.image_names)  # exact names, else file names
    hit = image >= 0
    if hit.sum() < 3:
        if warn:
            warn(f"{capture.gps_path}: {int(hit.sum())} fix(es) match images of the COLMAP model; GPS pruning off")
        return None
    cam = street.level(model.centres[image[hit]])[:, :2]
    world = fixes.scene_xy(capture.scene.crs)[hit]
    sig = fixes.sigma_or_default(default_sigma_m)[hit]
    origin = world.mean(axis=0)  # local origin: UTM values would cost precision in the fit
    local = world - origin
    query = np.asarray(query_xy, dtype=np.float64).reshape(-1, 2)
    k = min(n_local, len(cam))
    from scipy.spatial import cKDTree

    _, nn = cKDTree(cam).query(query, k=k)
    nn = nn.reshape(len(query), k)
    src, dst, w = cam[nn], local[nn], 1.0 / sig[nn] ** 2
    theta, t = rigid_fit_2d(src, dst, w)
    # one trimmed refit: drop fixes far off the first fit (wrong fixes, multipath)
    res = np.linalg.norm(_apply(theta[:, None], t[:, None], src) - dst, axis=-1)
    thr = np.maximum(3 * np.median(res, axis=1, keepdims=True), 3 * sig[nn])
    inlier = res <= thr
    theta, t = rigid_fit_2d(src, dst, w * inlier)
    pos = _apply(theta, t, query) + origin
    res = np.linalg.norm(_apply(theta[:, None], t[:, None], src) - dst, axis=-1)
    rms = np.sqrt((res ** 2 * inlier).sum(axis=1) / np.maximum(inlier.sum(axis=1), 1))
    return GpsPrior(position=pos, angle=theta, n_fixes=int(hit.sum()), sigma_m=float(np.median(sig)),
                    fit_rms_m=rms)


@dataclass(frozen=True)
class PruningPrior:
    """The prior the data term prunes with: positions (None: every pair is searched), each segment's
    radius_m (S,), where it came from ("gps", "route_placement" or None) and the placement's figures."""

    prior: GpsPrior | None = None
    radius_m: np.ndarray | None = None
    source: str | None = None
    figures: dict | None = None


def prior_radii(prior: GpsPrior, n_seg: int, cfg: GpsConfig) -> np.ndarray:
    """(S,) radius (m) of each street segment: radius_m, or σ- and fit-based (see ``GpsConfig``)."""
    if cfg.radius_m is not None:
        return np.full(n_seg, cfg.radius_m)
    radius = np.full(n_seg, cfg.radius_sigmas * prior.sigma_m)
    if cfg.radius_fit_sigmas is not None and prior.fit_rms_m is not None:
        radius = np.maximum(radius, cfg.radius_fit_sigmas * prior.fit_rms_m)
    return radius + cfg.radius_margin_m


def prior_offsets(prior: GpsPrior, theta: np.ndarray, t: np.ndarray, s_cent: np.ndarray, sj: np.ndarray,
                  sk: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(P,2) distances of both segment centres, placed by the poses, from their prior positions,
    and (P,2) |rotation − the prior's rotation| (radians)."""
    c, s = np.cos(theta), np.sin(theta)
    dist, turn = [], []
    for seg in (sj, sk):
        x = s_cent[seg]
        placed = np.stack([c * x[:, 0] - s * x[:, 1], s * x[:, 0] + c * x[:, 1]], 1) + t
        dist.append(np.linalg.norm(placed - prior.position[seg], axis=1))
        turn.append(np.abs(wrap_angle(theta - prior.angle[seg])))
    return np.stack(dist, axis=1), np.stack(turn, axis=1)


def prior_penalty(cost: np.ndarray, theta: np.ndarray, t: np.ndarray, s_cent: np.ndarray, sj: np.ndarray,
                  sk: np.ndarray, prior: PruningPrior, cfg: GpsConfig, exact: bool = True) -> np.ndarray:
    """cost + the soft prior term; with ``exact``, +inf where the final pose puts a centre outside its
    radius or turns farther than angle_deg from the prior heading."""
    dist, turn = prior_offsets(prior.prior, theta, t, s_cent, sj, sk)
    rel = dist / np.stack([prior.radius_m[sj], prior.radius_m[sk]], axis=1)
    cost = cost + cfg.cost_weight * rel.max(axis=1) ** 2
    if exact:
        bad = rel.max(axis=1) > 1.0
        if cfg.angle_deg is not None:
            bad |= turn.max(axis=1) > np.deg2rad(cfg.angle_deg)
        cost[bad] = np.inf
    return cost
