"""``warp.npz``: a run's point warp on disk, reloadable by ``crossview apply`` (docs/apply.md).

An ordinary ``.npz`` (``np.load`` reads it; no pickles), written with fixed zip timestamps so the
same run gives the same bytes. Arrays (S segments, V valid ones, F footprint points, N street points):

    format_version  ()        1
    crs, crs_wkt    ()  str   the scene CRS as written in scene.yaml, and as WKT
    origin          (3,)      local origin of the street frame in metres (StreetSegments.origin)
    up_rotation     (3,3)     levelling rotation: levelled = (p − origin) @ up_rotationᵀ
    T               (S,4,4)   segment transforms, input street frame → scene CRS
    valid           (V,)      indices of the valid segments (the others are never blended)
    footprint_xy    (F,2)     thinned footprints of the valid segments (levelled x, y; blend distances)
    footprint_segment (F,)    the segment of each footprint point
    neighbours      (V,K)     blending neighbours of each valid segment, nearest first, −1 padded
    neighbours_k, min_distance_m, weight_cell_m, relative_distance   () the blend's parameters
    source_xyz      (N,3) f4  the run's street points in metres minus ``origin``
    source_segment  (N,)  i4  the carrier segment each was moved with
    las_offset_m    (3,)      offsets of registered.laz (and of ``apply``'s LAZ outputs)
    las_scale_m     ()        their scale (0.001 unless the cloud is too wide for 1 mm)
    street_scale    ()        street-frame units per metre: input points are divided by it first
    camera_A (C,3,3), camera_b (C,3), camera_origin (3,), source_camera (N,) i4   only when the
                              points follow their capture cameras (``toolkit.adjust.remake``): each
                              camera's pose change p ↦ A p + b + origin, and each street point's camera
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import CrossviewError
from toolkit.warp.cameras import CameraMaps
from toolkit.warp.index import SegmentIndex
from toolkit.warp.model import CarrierSource, PointWarp

FORMAT_VERSION = 1
FILE_NAME = "warp.npz"
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed member timestamps: byte-identical files
_STORED = ("source_xyz",)  # float32 coordinates deflate by ~30 % only, at ~1 s per million points
_KEYS = ("crs", "crs_wkt", "origin", "up_rotation", "T", "valid", "footprint_xy", "footprint_segment", "neighbours",
         "neighbours_k", "min_distance_m", "weight_cell_m", "relative_distance", "source_xyz", "source_segment",
         "las_offset_m", "las_scale_m")


@dataclass(frozen=True)
class StoredWarp:
    """A run's warp with the frame it writes into."""

    warp: PointWarp
    crs: str
    crs_wkt: str
    las_offset_m: np.ndarray
    las_scale_m: float


def warp_arrays(stored: StoredWarp) -> dict[str, np.ndarray]:
    w = stored.warp
    if w.source is None:
        raise ValueError("a stored warp needs its carrier source (PointWarp.with_source)")
    return {
        "format_version": np.int64(FORMAT_VERSION), "crs": np.str_(stored.crs), "crs_wkt": np.str_(stored.crs_wkt),
        "origin": w.origin, "up_rotation": w.up_rotation, "T": w.T, **w.index.to_arrays(),
        "neighbours_k": np.int64(w.neighbours_k), "min_distance_m": np.float64(w.min_distance_m),
        "weight_cell_m": np.float64(w.weight_cell_m), "relative_distance": np.bool_(w.relative_distance),
        "source_xyz": w.source.xyz_f32, "source_segment": w.source.segment,
        "las_offset_m": np.asarray(stored.las_offset_m, np.float64), "las_scale_m": np.float64(stored.las_scale_m),
        "street_scale": np.float64(w.street_scale),
        **({} if w.cameras is None else {
            "camera_A": w.cameras.A, "camera_b": w.cameras.b, "camera_origin": w.cameras.origin,
            "source_camera": w.source.camera}),
    }


def save_warp(path: Path, stored: StoredWarp) -> None:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, value in warp_arrays(stored).items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_STORED if name in _STORED else zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)


def load_warp(path: Path) -> StoredWarp:
    """The warp of ``path`` (a run folder or its warp.npz); a ``CrossviewError`` naming the file otherwise."""
    path = Path(path)
    if path.is_dir():
        path = path / FILE_NAME
    if not path.is_file():
        raise CrossviewError(f"{path}: no stored warp (runs write warp.npz when the recipe has a warp step)")
    try:
        with np.load(path, allow_pickle=False) as data:
            a = {k: data[k] for k in data.files}
    except Exception as exc:
        raise CrossviewError(f"{path}: cannot read the stored warp ({type(exc).__name__}: {exc})") from exc
    if int(a.get("format_version", -1)) != FORMAT_VERSION:
        raise CrossviewError(f"{path}: stored warp format {a.get('format_version')!r}, "
                             f"this crossview reads format {FORMAT_VERSION}")
    missing = [k for k in _KEYS if k not in a]
    if missing:
        raise CrossviewError(f"{path}: stored warp lacks {', '.join(missing)} (not written by crossview?)")
    index = SegmentIndex.from_arrays(a["valid"], a["footprint_xy"], a["footprint_segment"], a["neighbours"])
    follows = "camera_A" in a
    cameras = CameraMaps(a["camera_A"], a["camera_b"], a["camera_origin"]) if follows else None
    warp = PointWarp(a["origin"], a["up_rotation"], a["T"], index, int(a["neighbours_k"]),
                     float(a["min_distance_m"]), float(a["weight_cell_m"]), bool(a["relative_distance"]),
                     CarrierSource(a["source_xyz"], a["source_segment"], a["source_camera"] if follows else None),
                     float(a.get("street_scale", 1.0)), cameras)
    return StoredWarp(warp, str(a["crs"]), str(a["crs_wkt"]), a["las_offset_m"], float(a["las_scale_m"]))
