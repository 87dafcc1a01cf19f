"""Scene folders: read and validate ``scene.yaml`` (contract: docs/formats.md) and load its files.

Loaders are cached per (path, mtime) so several stages reading the same DSM pay once.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from toolkit.errors import SceneError
from toolkit.io.crs import check_metric_crs
from toolkit.logcache import replaying_cache
from toolkit.types import Grid, Raster, Scene, SceneFiles, SparseModel

# manifest section → key → SceneFiles field
MANIFEST_KEYS: dict[str, dict[str, str]] = {
    "overview": {"dsm": "dsm", "ortho": "ortho", "footprints": "footprints", "osm": "osm",
                 "labels": "labels", "cloud": "overview_cloud", "dem": "dem"},
    "street": {"cloud": "street_cloud", "sparse": "sparse", "gps": "gps"},
    "truth": {"lidar": "truth_lidar", "street_points": "truth_street_points",
              "street_labels": "truth_street_labels", "street_rows": "truth_street_rows",
              "buildings": "truth_buildings",
              "cameras": "truth_cameras"},
}
FIELD_TO_MANIFEST = {f: f"{sec}.{k}" for sec, keys in MANIFEST_KEYS.items() for k, f in keys.items()}
TOP_KEYS = {"scene", "name", "crs", "street_scale", *MANIFEST_KEYS, "synth"}
log = logging.getLogger("crossview.scene")


def load_scene(path: str | Path) -> Scene:
    """Load ``scene.yaml`` (or a folder holding it). Files named but absent are errors."""
    path = Path(path)
    manifest_path = path / "scene.yaml" if path.is_dir() or not path.suffix else path
    if not manifest_path.is_file():
        raise SceneError(f"{manifest_path}: scene manifest not found")
    try:
        data = yaml.safe_load(manifest_path.read_text())
    except yaml.YAMLError as exc:
        raise SceneError(f"{manifest_path}: invalid YAML ({_yaml_where(exc)})") from exc
    if not isinstance(data, dict):
        raise SceneError(f"{manifest_path}: expected a mapping with 'scene: 1', got {type(data).__name__}")
    unknown = sorted(set(data) - TOP_KEYS)
    if unknown:
        raise SceneError(f"{manifest_path}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(TOP_KEYS))})")
    if data.get("scene") != 1:
        raise SceneError(f"{manifest_path}: 'scene' must be 1 (format version), got {data.get('scene')!r}")
    crs = data.get("crs")
    if not isinstance(crs, str):
        raise SceneError(f"{manifest_path}: 'crs' must be a string like 'EPSG:32617', got {crs!r}")
    check_metric_crs(manifest_path, crs)
    root = manifest_path.parent.resolve()
    files: dict[str, Path] = {}
    for section, keys in MANIFEST_KEYS.items():
        entries = data.get(section) or {}
        if not isinstance(entries, dict):
            raise SceneError(f"{manifest_path}: '{section}' must be a mapping of file paths")
        for key, value in entries.items():
            if key not in keys:
                raise SceneError(f"{manifest_path}: unknown key '{section}.{key}' "
                                 f"(allowed: {', '.join(keys)})")
            if value is None:
                continue
            if not isinstance(value, str):
                raise SceneError(f"{manifest_path}: '{section}.{key}' must be a path string, got {value!r}")
            p = (root / Path(value).expanduser()).resolve()  # relative to the scene folder, or absolute
            if not p.exists():
                raise SceneError(f"{p}: file named by {section}.{key} in {manifest_path} not found")
            files[keys[key]] = p
    name = str(data.get("name") or root.name)
    return Scene(root=root, name=name, crs=crs, files=SceneFiles(**files), manifest=data)


def _yaml_where(exc: yaml.YAMLError) -> str:
    mark = getattr(exc, "problem_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    return f"line {mark.line + 1}: {problem}" if mark else problem


def need(scene: Scene, key: str, who: str) -> Path:
    """The path of scene file ``key`` or a one-line error naming the stage that needs it."""
    p = getattr(scene.files, key)
    if p is None:
        raise SceneError(f"{who} needs {FIELD_TO_MANIFEST.get(key, key)}, which {scene.root / 'scene.yaml'} does not name")
    return p


# --- cached loaders ---------------------------------------------------------------------------
def _mtime(p: Path) -> float:
    return p.stat().st_mtime_ns


# Rasters in another CRS or on another grid are warped onto the scene grid with these kernels.
RESAMPLING = {"dsm": "bilinear", "ortho": "bilinear", "labels": "nearest", "dem": "bilinear"}
GRID_SOURCES = ("dsm", "labels", "ortho")  # the first the scene names defines the scene grid


@dataclass(frozen=True)
class SceneGrid:
    """The over-view grid of a scene, in its CRS, and the raster (``GRID_SOURCES`` key) it comes from."""

    grid: Grid
    source: str
    path: Path


def scene_grid(scene: Scene) -> SceneGrid | None:
    """The DSM's grid, else the label map's, else the ortho's, in the scene CRS at its own GSD
    (None when the scene names none of them)."""
    key = next((k for k in GRID_SOURCES if scene.has(k)), None)
    if key is None:
        return None
    p = getattr(scene.files, key)
    return SceneGrid(_grid(p, _mtime(p), scene.crs), key, p)


@functools.lru_cache(maxsize=8)
def _grid(path: Path, mtime: float, crs: str) -> Grid:
    from toolkit.io.raster import grid_in_crs, read_header

    return grid_in_crs(read_header(path).grid, crs, path)


@replaying_cache(maxsize=8)
def _raster(path: Path, mtime: float, grid: Grid, resampling: str) -> Raster:
    from toolkit.io.raster import on_grid, read_header, read_raster, warp_raster

    own = read_header(path).grid
    if on_grid(own, grid):
        return read_raster(path)
    log.info("%s: %s; resampled (%s) onto the scene grid, %s", path, describe_grid(own), resampling, describe_grid(grid))
    return warp_raster(path, grid, resampling)


def describe_grid(grid: Grid) -> str:
    """The grid in words, e.g. 745x612 px of 0.5m in EPSG:32617."""
    from toolkit.io.crs import axis_units, parse_crs

    unit = axis_units(parse_crs(grid.crs, grid.crs))[0]
    unit = {"metre": "m", "degree": "°", "US survey foot": "ftUS", "foot": "ft"}.get(unit, f" {unit}")
    return f"{grid.width}x{grid.height} px of {grid.gsd_m:.6g}{unit} in {grid.crs}"


def load_raster(scene: Scene, key: str, who: str = "") -> Raster:
    """A scene raster on the scene grid: read as it is when it is on it, else reprojected."""
    p = need(scene, key, who or key)
    target = scene_grid(scene)
    return _raster(p, _mtime(p), target.grid, RESAMPLING[key])


def load_dem(scene: Scene, who: str = "") -> Raster:
    """The terrain model on the scene grid, or, in a scene without one, on its own grid in the scene CRS."""
    p = need(scene, "dem", who or "dem")
    target = scene_grid(scene)
    grid = target.grid if target is not None else _grid(p, _mtime(p), scene.crs)
    return _raster(p, _mtime(p), grid, RESAMPLING["dem"])


@replaying_cache(maxsize=4)
def _points(path: Path, mtime: float) -> np.ndarray:
    from toolkit.io.cloud import read_points

    pts = read_points(path)
    pts.setflags(write=False)
    return pts


def load_points(scene: Scene, key: str = "street_cloud", who: str = "") -> np.ndarray:
    """(N,3) float64, read-only (shared between stages); the street cloud in metres (divided by the
    scene's street scale)."""
    p = need(scene, key, who or key)
    if key == "street_cloud" and scene.street_scale.value != 1.0:
        return _scaled_points(p, _mtime(p), scene.street_scale.value)
    return _points(p, _mtime(p))


def load_cloud(scene: Scene, key: str, who: str = "") -> np.ndarray:
    """(N,3) float64, read-only, of the over-view cloud or the truth lidar. The street cloud is not
    read here: it comes with the run's ``toolkit.capture.StreetCapture``, in metres."""
    if key == "street_cloud":
        raise ValueError("the street cloud is read through toolkit.capture.StreetCapture")
    return load_points(scene, key, who)


def overview_heights(scene: Scene, who: str = "") -> Raster | np.ndarray | None:
    """Where the over-view heights come from: the DSM, else the terrain model (rasters on the scene
    grid), else the over-view cloud ((N,3), read-only); None when the scene has none of them."""
    if scene.has("dsm"):
        return load_raster(scene, "dsm", who)
    if scene.has("dem"):
        return load_dem(scene, who)
    if scene.has("overview_cloud"):
        return load_cloud(scene, "overview_cloud", who)
    return None


@replaying_cache(maxsize=1)
def _scaled_points(path: Path, mtime: float, scale: float) -> np.ndarray:
    pts = _points(path, mtime) / scale
    pts.setflags(write=False)
    return pts


@functools.lru_cache(maxsize=2)
def _model(path: Path, mtime: float) -> SparseModel:
    from toolkit.io.colmap import read_model

    return read_model(path)


def load_sparse(scene: Scene, who: str = "") -> SparseModel:
    """The COLMAP model in metres (camera positions and points divided by the street scale)."""
    p = need(scene, "sparse", who or "sparse")
    if scene.street_scale.value != 1.0:
        return _scaled_model(p, _mtime(p), scene.street_scale.value)
    return _model(p, _mtime(p))


def read_sparse_raw(scene: Scene, who: str = "") -> SparseModel:
    """The COLMAP model as written (the street frame's own units)."""
    p = need(scene, "sparse", who or "sparse")
    return _model(p, _mtime(p))


@functools.lru_cache(maxsize=1)
def _scaled_model(path: Path, mtime: float, scale: float) -> SparseModel:
    from dataclasses import replace

    model = _model(path, mtime)
    return replace(model, t=np.asarray(model.t, np.float64) / scale,
                   points3d=np.asarray(model.points3d, np.float64) / scale)


def load_array(scene: Scene, key: str, mmap: bool = False) -> np.ndarray:
    """A scene .npy; ``mmap``: memory-mapped read-only (read as it is used)."""
    p = need(scene, key, key)
    try:
        return np.load(p, allow_pickle=False, mmap_mode="r" if mmap else None)
    except Exception as exc:
        raise SceneError(f"{p}: cannot read .npy ({exc})") from exc


def write_manifest(root: Path, name: str, crs: str, entries: dict[str, dict[str, str]],
                   extra: dict[str, Any] | None = None) -> Path:
    """Write scene.yaml (used by the generator and converters)."""
    doc: dict[str, Any] = {"scene": 1, "name": name, "crs": crs}
    doc.update({k: v for k, v in entries.items() if v})
    if extra:
        doc.update(extra)
    out = Path(root) / "scene.yaml"
    out.write_text(yaml.safe_dump(doc, sort_keys=False))
    return out
