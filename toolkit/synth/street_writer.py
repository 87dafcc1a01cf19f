"""Write the street-view products and their truth, streaming the cloud chunk by chunk:
street/cloud.ply, street/sparse/, street/gps.csv, truth/street_points.npy, truth/street_labels.npy,
truth/drift.npz, truth/cameras.txt and truth/lidar.ply.

With ``street_density_factor`` K > 1 (``toolkit.synth.density``) the cloud is street/cloud.laz, K rows
per MVS point, and the truth covers the first row of each only: truth/street_points.npy,
truth/street_labels.npy and truth/drift.npz's ``camera_index`` and ``sparse_point_index`` are the
K = 1 scene's arrays (M truth rows), and truth/street_rows.npy (M,) int64 holds the cloud row of each
truth row, i*K. ``sparse_point_index`` indexes the truth rows; a COLMAP point's id is its cloud row + 1
(street_rows[sparse_point_index] + 1). No array of the K·M cloud rows is written besides the LAZ."""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

from toolkit.io.cloud import write_ply
from toolkit.io.colmap import write_model
from toolkit.synth import colmap_model
from toolkit.synth.config import SynthConfig
from toolkit.synth.drift import Drift, make_drift
from toolkit.synth.files import RowStream, finish_ply, ply_record_dtype, ply_records, save_npz
from toolkit.synth.mesh import LABEL_CLUTTER
from toolkit.synth.overview import cover_colors
from toolkit.synth.raycast import Caster
from toolkit.synth.route import Track
from toolkit.synth.street import StreetChunk, VoxelFilter, capture_chunk, chunks
from toolkit.synth.world import World

PREVIEW_POINTS = 150_000


@dataclass
class StreetResult:
    n_points: int
    n_sparse: int
    n_obs: int
    preview_drifted: np.ndarray  # (M,2) street points with the global transform undone (drift kept)
    preview_true: np.ndarray  # (M,2) the same points' true positions
    n_truth: int = 0  # rows of the truth arrays (n_points / street_density_factor)


def write_street(world: World, track: Track, cfg: SynthConfig, root: Path, ov, rngs: dict) -> StreetResult:
    origin3 = np.array([world.origin[0], world.origin[1], 0.0])
    centres = track.centres + origin3
    drift = make_drift(centres, track.R_c2w, track.arclength, cfg, rngs["drift"])
    mesh = world.street_mesh()
    caster = Caster(mesh)
    tmpdir = root / ".streams"
    tmpdir.mkdir()
    s_cloud = RowStream(tmpdir, "cloud", ply_record_dtype(True))
    s_true = RowStream(tmpdir, "true", np.float64, (3,))
    s_label = RowStream(tmpdir, "label", np.int32)
    s_cam = RowStream(tmpdir, "camera", np.int32)
    lidar_parts = []
    prev_d, prev_t = [], []
    density, lidar_density = VoxelFilter(cfg.point_spacing_m), VoxelFilter(cfg.lidar_spacing_m)
    expected = _expected_points(track, cfg)
    every = max(1, expected // PREVIEW_POINTS)
    from toolkit.synth.timing import timed

    k = int(cfg.street_density_factor)
    dense = None
    if k > 1:
        from toolkit.synth.density import DenseCloudWriter

        dense = DenseCloudWriter(root / "street/cloud.laz", drift, cfg, origin3, rngs["density"])
        s_rows = RowStream(tmpdir, "rows", np.int64)
    for caps in chunks(track, cfg):
        with timed(f"  capture {len(caps)} positions"):
            ch: StreetChunk = capture_chunk(caster, track, caps, cfg, rngs["capture"], density, lidar_density)
        ground = ch.labels == -1
        ch.colors[ground] = cover_colors(ov.cover, ov.grid, world.origin, ch.points[ground, :2])
        scene_pts = ch.points + origin3
        street = drift.apply(scene_pts, ch.camera)
        if dense is not None:
            with timed(f"  densify x{k}: {len(street) * k:,} rows"):
                s_rows.append((s_true.rows + np.arange(len(street), dtype=np.int64)) * k)
                dense.write(ch, street)
        s_cloud.append(ply_records(street, ch.colors))
        s_true.append(scene_pts)
        s_label.append(ch.labels)
        s_cam.append(ch.camera)
        lidar_parts.append(ch.surface + origin3)
        sel = slice(None, None, every)
        prev_d.append(((street[sel] / drift.global_scale - drift.global_translation) @ drift.global_rotation)[:, :2])
        prev_t.append(scene_pts[sel, :2])
    n = s_true.rows
    if dense is None:
        finish_ply(s_cloud, root / "street/cloud.ply", with_colors=True)
        cloud = read_ply_body(root / "street/cloud.ply", ply_record_dtype(True))
    else:
        dense.close()
        s_rows.finish_npy(root / "truth/street_rows.npy")
        s_cloud.close()  # the K = 1 cloud (rows i*K before quantisation), for the COLMAP points
        cloud = np.memmap(s_cloud.path, dtype=ply_record_dtype(True), mode="r")
    s_true.finish_npy(root / "truth/street_points.npy")
    s_label.finish_npy(root / "truth/street_labels.npy")
    s_cam.finish_npy(tmpdir / "camera.npy")
    camera_of = np.load(tmpdir / "camera.npy")

    with timed("  colmap model"):
        n_sparse, n_obs, sparse_rows = _write_colmap(
            root, track, centres, drift, camera_of, cfg, rngs["sparse"], cloud
        )
    del cloud
    save_npz(
        root / "truth/drift.npz",
        {**drift.arrays(), "camera_index": camera_of, "sparse_point_index": sparse_rows.astype(np.int64)},
    )
    _write_gps(root / "street/gps.csv", centres, cfg, rngs["gps"])
    with timed("  lidar"):
        _write_lidar(root / "truth/lidar.ply", world, track, cfg, lidar_parts, origin3)
    shutil.rmtree(tmpdir)
    return StreetResult(n * k, n_sparse, n_obs, np.concatenate(prev_d), np.concatenate(prev_t), n)


def _expected_points(track: Track, cfg: SynthConfig) -> int:
    return int(track.arclength[-1] * 60 / cfg.point_spacing_m**2 * 0.05)


def read_ply_body(path: Path, dtype: np.dtype) -> np.ndarray:
    """Memory-map the vertex records of a PLY written by ``write_ply`` / ``finish_ply``."""
    with open(path, "rb") as fh:
        head = fh.read(4096)
    offset = head.index(b"end_header\n") + len(b"end_header\n")
    return np.memmap(path, dtype=dtype, mode="r", offset=offset)


def _write_colmap(
    root: Path,
    track: Track,
    centres: np.ndarray,
    drift: Drift,
    camera_of: np.ndarray,
    cfg: SynthConfig,
    rng: np.random.Generator,
    cloud: np.ndarray,
) -> tuple[int, int, np.ndarray]:
    """The COLMAP model of ``cfg.sparse_points`` truth rows; ``cloud``: the K = 1 street records.
    Returns (points, observations, the truth rows of the points)."""
    truth = np.load(root / "truth/street_points.npy", mmap_mode="r")
    labels = np.load(root / "truth/street_labels.npy", mmap_mode="r")
    pool = np.flatnonzero(np.asarray(labels) != LABEL_CLUTTER)  # feature tracks rarely survive on outliers
    rows = np.sort(rng.choice(pool, min(cfg.sparse_points, len(pool)), replace=False)) if len(pool) else pool
    obs, kept = colmap_model.observe(np.asarray(truth[rows]), camera_of[rows], centres, track.R_c2w, cfg, rng)
    rows = rows[kept]
    rec = cloud[rows]
    xyz = np.column_stack([rec["x"], rec["y"], rec["z"]])
    rgb = np.column_stack([rec["red"], rec["green"], rec["blue"]])
    ids = rows * int(cfg.street_density_factor) + 1  # COLMAP point id = street cloud row + 1
    R_s, t_s = drift.street_poses(track.R_c2w)
    write_model(colmap_model.sparse_model(cfg, R_s, t_s, ids, xyz, rgb, obs), root / "street/sparse")
    R_true = np.transpose(track.R_c2w, (0, 2, 1))
    t_true = -np.einsum("cij,cj->ci", R_true, centres)
    tmp = root / ".true_model"
    write_model(colmap_model.sparse_model(cfg, R_true, t_true, ids, np.asarray(truth[rows]), rgb, obs), tmp)
    (tmp / "images.txt").rename(root / "truth/cameras.txt")
    shutil.rmtree(tmp)
    return len(rows), len(obs), rows


def _write_gps(path: Path, centres: np.ndarray, cfg: SynthConfig, rng: np.random.Generator) -> None:
    """Consumer-GPS-like fixes: slowly wandering error of about ``gps_sigma_m`` per axis."""
    from pyproj import Transformer

    err = gaussian_filter1d(rng.normal(0, 1, (len(centres), 2)), sigma=15, axis=0, mode="nearest")
    err *= cfg.gps_sigma_m / max(float(err.std()), 1e-9)
    xy = centres[:, :2] + err
    lon, lat = Transformer.from_crs(cfg.crs, "EPSG:4326", always_xy=True).transform(xy[:, 0], xy[:, 1])
    names = colmap_model.image_names(len(centres))
    lines = ["image_name,lon,lat,sigma_m"] + [
        f"{n},{lo:.8f},{la:.8f},{cfg.gps_sigma_m:g}" for n, lo, la in zip(names, lon, lat)
    ]
    path.write_text("\n".join(lines) + "\n")


def _write_lidar(
    path: Path, world: World, track: Track, cfg: SynthConfig, parts: list, origin3: np.ndarray
) -> None:
    """Façades and ground seen from the street plus roofs and ground from above, clutter removed."""
    import shapely
    from shapely.geometry import LineString

    from toolkit.synth.mesh import CAR, CROWN, POLE, TRUNK

    corridor = LineString(track.centres[:, :2]).buffer(cfg.lidar_corridor_m)
    xmin, ymin, xmax, ymax = corridor.bounds
    s = cfg.lidar_spacing_m
    gx, gy = np.meshgrid(np.arange(xmin, xmax, s) + s / 2, np.arange(ymin, ymax, s) + s / 2)
    xy = np.column_stack([gx.ravel(), gy.ravel()])
    xy = xy[shapely.contains_xy(corridor, xy[:, 0], xy[:, 1])]
    mesh = world.street_mesh()
    caster = Caster(mesh)
    top = float(mesh.vertices[:, 2].max()) + 50
    t, prim, _ = caster.cast(
        np.column_stack([xy, np.full(len(xy), top)]), np.tile([0.0, 0.0, -1.0], (len(xy), 1))
    )
    ok = (prim >= 0) & ~np.isin(mesh.kind[np.maximum(prim, 0)], [CROWN, TRUNK, CAR, POLE])
    als = np.column_stack([xy[ok], top - t[ok].astype(np.float64)]) + origin3
    pts = np.concatenate(parts + [als])
    keep = VoxelFilter(s)(pts - origin3)
    write_ply(path, pts[keep])
