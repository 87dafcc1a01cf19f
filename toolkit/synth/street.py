"""Street-view capture: rays from a forward camera every ``capture_step_m`` along the route, kept
within MVS range and incidence limits, thinned to MVS density, with depth-growing noise and a few
percent of gross outliers. Points are produced in route order, one chunk of route at a time."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from toolkit.synth.config import SynthConfig
from toolkit.synth.mesh import CAR, CROWN, LABEL_CLUTTER, POLE, TRUNK
from toolkit.synth.raycast import Caster
from toolkit.synth.route import Track


@dataclass
class StreetChunk:
    points: np.ndarray  # (N,3) true local positions (noise included, drift not)
    labels: np.ndarray  # (N,) int32 building id, -1 ground, -2 clutter/outlier
    colors: np.ndarray  # (N,3) uint8
    camera: np.ndarray  # (N,) int32 index of the camera whose pose carries the point's drift
    surface: np.ndarray  # (M,3) noise-free façade/ground hits (clutter excluded), for truth/lidar.ply
    surface_labels: np.ndarray  # (M,)
    # what street_density_factor > 1 needs to sample the same surface again (row for row with points)
    hits: np.ndarray  # (N,3) noise-free local hit point of each point's ray
    normals: np.ndarray  # (N,3) float32 unit normal of the surface hit
    sigma: np.ndarray  # (N,) the MVS noise sigma the point got (noise_sigma of its depth)
    outlier: np.ndarray  # (N,) bool: replaced by a gross outlier


def intrinsics(cfg: SynthConfig) -> tuple[float, float, float]:
    """Focal length and principal point (pixels) of the forward camera."""
    f = cfg.image_width_px / 2 / np.tan(np.deg2rad(cfg.hfov_deg) / 2)
    return float(f), cfg.image_width_px / 2, cfg.image_height_px / 2


def capture_cameras(track: Track, cfg: SynthConfig) -> np.ndarray:
    stride = max(1, int(round(cfg.capture_step_m / cfg.camera_step_m)))
    return np.arange(0, len(track), stride)


def chunks(track: Track, cfg: SynthConfig) -> list[np.ndarray]:
    """Capture-camera indices split into runs of about ``chunk_route_m``."""
    caps = capture_cameras(track, cfg)
    bins = np.floor(track.arclength[caps] / cfg.chunk_route_m).astype(int)
    return [caps[bins == b] for b in np.unique(bins)]


class VoxelFilter:
    """At most one point per voxel, first come first kept; remembers the previous chunk's voxels."""

    def __init__(self, spacing: float):
        self.spacing = spacing
        self.previous = np.zeros(0, np.int64)

    def keys(self, xyz: np.ndarray) -> np.ndarray:
        k = np.floor(xyz / self.spacing).astype(np.int64) + (1 << 20)
        return (k[:, 0] << 42) | (k[:, 1] << 21) | k[:, 2]

    def __call__(self, xyz: np.ndarray) -> np.ndarray:
        """Sorted indices of the rows kept."""
        keys = self.keys(xyz)
        _, first = np.unique(keys, return_index=True)
        first = np.sort(first)
        first = first[~np.isin(keys[first], self.previous)]
        self.previous = keys[first]
        return first


COARSE = 4  # the first pass casts one ray in COARSE×COARSE of the full grid
OVERSAMPLE = 3.0  # fine rays kept per voxel-sized patch (slanted surfaces need more than one)


def _ray_dirs(
    caps: np.ndarray,
    rays: np.ndarray,
    off: np.ndarray,
    nu: int,
    step_px: float,
    cfg: SynthConfig,
    track: Track,
    cap_pos: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions in the camera frame and in the world of rays ``rays`` (flat grid index) of
    captures ``cap_pos`` (positions in ``caps``)."""
    f, cx, cy = intrinsics(cfg)
    row, col = np.divmod(rays, nu)
    d_cam = np.empty((len(rays), 3), np.float32)
    d_cam[:, 0] = ((col + 0.5) * step_px + off[cap_pos, 0] - cx) / f
    d_cam[:, 1] = ((row + 0.5) * step_px + off[cap_pos, 1] - cy) / f
    d_cam[:, 2] = 1.0
    d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
    R = track.R_c2w[caps].astype(np.float32)
    d_world = np.einsum("nij,nj->ni", R[cap_pos], d_cam)
    return d_cam, d_world


def noise_sigma(depth: np.ndarray, cfg: SynthConfig) -> np.ndarray:
    """MVS noise sigma (m, per axis) of a point seen at ``depth``: ``noise_m`` at 10 m, linear in depth."""
    return cfg.noise_m * np.maximum(depth / 10.0, 0.3)


def _with_noise(pts: np.ndarray, dirs: np.ndarray, depth: np.ndarray, labels: np.ndarray, cfg: SynthConfig,
                rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Range-dependent noise, and outliers spread along their rays (labelled clutter); also the
    outlier mask."""
    sigma = noise_sigma(depth, cfg)
    noisy = pts + rng.normal(0, 1, pts.shape) * sigma[:, None]
    outlier = np.zeros(len(noisy), bool)
    n_out = int(round(cfg.outlier_fraction * len(noisy)))
    if n_out:
        o = np.sort(rng.choice(len(noisy), n_out, replace=False))
        along = rng.normal(0, 3.0, n_out) + np.sign(rng.normal(size=n_out)) * 0.5
        scatter = rng.normal(0, 0.8, (n_out, 3))
        noisy[o] = pts[o] + dirs[o] * along[:, None] + scatter
        labels = labels.copy()
        labels[o] = LABEL_CLUTTER
        outlier[o] = True
    return noisy, labels, outlier


def capture_chunk(
    caster: Caster,
    track: Track,
    caps: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator,
    density: VoxelFilter,
    lidar_density: VoxelFilter,
) -> StreetChunk:
    """Cast each capture's rays in two passes: a coarse grid gives the depth of the view, then the
    full grid is sampled with a probability that grows with that depth, so near surfaces (already
    denser than the MVS voxel) cost few rays while far ones keep the full angular resolution."""
    f, _, _ = intrinsics(cfg)
    step_rad = np.deg2rad(cfg.ray_step_deg)
    step_px = max(1.0, step_rad * f)
    nu, nv = int(cfg.image_width_px / step_px), int(cfg.image_height_px / step_px)
    n_caps = len(caps)
    # a fresh sub-pixel offset per capture so successive captures interleave rather than alias
    off = rng.uniform(-0.5, 0.5, (n_caps, 2)) * step_px
    grid = np.arange(nu * nv)
    row, col = np.divmod(grid, nu)
    is_coarse = (row % COARSE == 0) & (col % COARSE == 0)
    coarse = grid[is_coarse]
    cap_pos = np.repeat(np.arange(n_caps), len(coarse))
    ray = np.tile(coarse, n_caps)
    d_cam, d_world = _ray_dirs(caps, ray, off, nu, step_px, cfg, track, cap_pos)
    t1, p1, n1 = caster.cast(track.centres[caps[cap_pos]], d_world, want_normals=True)
    depth1 = t1 * d_cam[:, 2]
    nvc, nuc = -(-nv // COARSE), -(-nu // COARSE)
    far = np.where(np.isfinite(depth1) & (depth1 <= cfg.max_range_m * 1.1), depth1, 0.0).reshape(
        n_caps, nvc, nuc
    )
    far = ndi.maximum_filter(far, size=(1, 3, 3), mode="nearest")
    ref = cfg.point_spacing_m / step_rad  # range where the ray spacing equals the MVS voxel
    prob = np.clip(OVERSAMPLE * (far / ref) ** 2, 0.0, 1.0)
    fine = grid[~is_coarse]
    p_fine = prob[:, row[fine] // COARSE, col[fine] // COARSE]  # (n_caps, n_fine)
    take_c, take_r = np.nonzero(rng.random(p_fine.shape, dtype=np.float32) < p_fine)
    del p_fine
    d_cam2, d_world2 = _ray_dirs(caps, fine[take_r], off, nu, step_px, cfg, track, take_c)
    t2, p2, n2 = caster.cast(track.centres[caps[take_c]], d_world2, want_normals=True)
    # merge both passes in (capture, grid index) order
    order_key = np.concatenate([cap_pos * (nu * nv) + ray, take_c * (nu * nv) + fine[take_r]])
    order = np.argsort(order_key, kind="stable")
    t = np.concatenate([t1, t2])[order]
    prim = np.concatenate([p1, p2])[order]
    normals = np.concatenate([n1, n2])[order]
    d_world = np.concatenate([d_world, d_world2])[order]
    dz = np.concatenate([d_cam[:, 2], d_cam2[:, 2]])[order]
    cap_all = caps[np.concatenate([cap_pos, take_c])[order]]
    del d_cam, d_cam2, d_world2

    idx = np.flatnonzero(np.isfinite(t))
    depth = t[idx] * dz[idx]
    cos_inc = np.abs(np.einsum("ij,ij->i", normals[idx], d_world[idx]))
    ok = (depth >= cfg.min_range_m) & (depth <= cfg.max_range_m)
    ok &= cos_inc >= np.sin(np.deg2rad(cfg.min_incidence_deg))
    idx, depth = idx[ok], depth[ok]
    cap_of = cap_all[idx]
    dirs_all = d_world[idx].astype(np.float64)
    surface = track.centres[cap_of] + dirs_all * t[idx, None].astype(np.float64)
    mesh = caster.mesh
    prim = prim[idx]
    labels = mesh.label[prim]
    colors = mesh.color[prim]

    keep = density(surface)
    pts, labels, colors, cap_of = surface[keep], labels[keep], colors[keep], cap_of[keep]
    dirs, dep, hit_normals = dirs_all[keep], depth[keep], normals[idx[keep]]
    stride = max(1, int(round(cfg.capture_step_m / cfg.camera_step_m)))
    camera = np.minimum(cap_of + rng.integers(0, stride, len(cap_of)), len(track) - 1).astype(np.int32)

    noisy, labels, outlier = _with_noise(pts, dirs, dep, labels, cfg, rng)

    clean = ~np.isin(mesh.kind[prim], [CROWN, TRUNK, CAR, POLE])
    surf = surface[clean]
    lk = lidar_density(surf)
    return StreetChunk(
        noisy, labels.astype(np.int32), colors, camera, surf[lk], mesh.label[prim[clean][lk]],
        pts, hit_normals, noise_sigma(dep, cfg), outlier,
    )
