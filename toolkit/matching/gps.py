"""Coarse GPS fixes → an approximate scene position and heading of each street segment.

street/gps.csv (image_name,lon,lat[,sigma_m]) names COLMAP images; their camera centres, levelled,
pair with the fixes projected to the scene CRS. For each street segment a weighted 2D rigid fit
(scale is metric) over the ``n_local`` fixes nearest to it (released code: one fit per block of
~100 fixes, which follows the drift of a long route) predicts where the segment lies.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.types import StreetSegments


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


def read_gps_csv(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Names, (N,2) lon/lat, (N,) sigma_m (NaN when absent); layouts in ``toolkit.io.gps``."""
    from toolkit.io.gps import read_gps_csv as read_fixes

    fixes = read_fixes(path)
    return list(fixes.names), fixes.lonlat, fixes.sigma_m


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


def gps_prior(scene, street: StreetSegments, n_local: int = 100, default_sigma_m: float = 10.0,
              warn=None) -> GpsPrior | None:
    """The prior, or None (with a warning) when fewer than 3 fixes match COLMAP images."""
    from pyproj import Transformer

    from toolkit.io.gps import match_images
    from toolkit.scene import load_sparse

    path = scene.files.gps
    names, lonlat, sigma = read_gps_csv(path)
    model = load_sparse(scene, who="unary.distance_map (GPS pruning)")
    image = match_images(names, model.image_names)  # exact names, else file names
    hit = image >= 0
    if hit.sum() < 3:
        if warn:
            warn(f"{path}: {int(hit.sum())} fix(es) match images of the COLMAP model; GPS pruning off")
        return None
    cam = street.level(model.centres[image[hit]])[:, :2]
    tr = Transformer.from_crs("EPSG:4326", scene.crs, always_xy=True)
    east, north = tr.transform(lonlat[hit, 0], lonlat[hit, 1])
    world = np.stack([east, north], axis=1)
    sig = np.where(np.isfinite(sigma[hit]) & (sigma[hit] > 0), sigma[hit], default_sigma_m)
    origin = world.mean(axis=0)  # local origin: UTM values would cost precision in the fit
    local = world - origin
    cent = np.asarray(street.centroids, dtype=np.float64).reshape(-1, 2)
    k = min(n_local, len(cam))
    from scipy.spatial import cKDTree

    _, nn = cKDTree(cam).query(cent, k=k)
    nn = nn.reshape(len(cent), k)
    src, dst, w = cam[nn], local[nn], 1.0 / sig[nn] ** 2
    theta, t = rigid_fit_2d(src, dst, w)
    # one trimmed refit: drop fixes far off the first fit (wrong fixes, multipath)
    res = np.linalg.norm(_apply(theta[:, None], t[:, None], src) - dst, axis=-1)
    thr = np.maximum(3 * np.median(res, axis=1, keepdims=True), 3 * sig[nn])
    inlier = res <= thr
    theta, t = rigid_fit_2d(src, dst, w * inlier)
    pos = _apply(theta, t, cent) + origin
    res = np.linalg.norm(_apply(theta[:, None], t[:, None], src) - dst, axis=-1)
    rms = np.sqrt((res ** 2 * inlier).sum(axis=1) / np.maximum(inlier.sum(axis=1), 1))
    return GpsPrior(position=pos, angle=theta, n_fixes=int(hit.sum()), sigma_m=float(np.median(sig)),
                    fit_rms_m=rms)
