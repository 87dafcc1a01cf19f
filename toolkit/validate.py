"""Cheap header checks of scene files, run by ``build()`` before any computation.

Contents (NaN coordinates, empty geometries) are checked when a stage loads a file; here what a
header tells and what the run would reject later: the file opens, a raster has a CRS and meets the
scene grid (it is reprojected onto it when needed), clouds have points, footprints are in a known
format with a usable CRS, the COLMAP folder is complete, GPS fixes name its images, and each
stage's own checks (``Stage.check_scene``: e.g. the ortho bands ``overview.dsm_tophat`` needs).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

from toolkit.capture import StreetCapture
from toolkit.errors import SceneError
from toolkit.types import Scene

RASTERS = ("dsm", "ortho", "labels", "dem")
CLOUDS = ("street_cloud", "overview_cloud", "truth_lidar")
FOOTPRINTS = ("footprints", "osm", "truth_buildings")


@dataclass(frozen=True)
class GpsMatch:
    """How many of the GPS fixes name an image of the COLMAP model."""

    matched: int
    fixes: int


def check_scene_files(scene: Scene, keys: Iterable[str], stages: Sequence[Any] = (),
                      capture: StreetCapture | None = None) -> None:
    """``capture``: the run's street capture (default: the scene's as it is)."""
    keys = [k for k in dict.fromkeys(keys) if scene.has(k)]
    for key in keys:
        path: Path = getattr(scene.files, key)
        if key in RASTERS:
            _raster_header(path)
        elif key in CLOUDS:
            _cloud_header(path, scene.crs)
        elif key in FOOTPRINTS:
            _footprints(path, scene.crs)
        elif key == "sparse":
            _sparse(path)
    if any(k in RASTERS or k in ("footprints", "osm") for k in keys):  # both are read onto the scene grid
        _rasters_meet_the_grid(scene, [k for k in keys if k in RASTERS])
    if uses_gps(scene, stages):
        check_gps(capture if capture is not None else StreetCapture(scene))
    for stage in stages:
        stage.check_scene(scene)


def uses_gps(scene: Scene, stages: Sequence[Any]) -> bool:
    """The data term (a ``unary`` step) pairs street/gps.csv with the COLMAP images when both exist."""
    return scene.has("gps") and scene.has("sparse") and any(s.kind == "unary" for s in stages)


def gps_match(capture: StreetCapture) -> GpsMatch:
    from toolkit.io.gps import match_images

    fixes = capture.gps
    model = capture.require_sparse("street.gps")
    return GpsMatch(int((match_images(fixes.names, model.image_names) >= 0).sum()), len(fixes))


def check_gps(capture: StreetCapture) -> GpsMatch:
    """How many GPS fixes name a COLMAP image; a one-line error when none does."""
    found = gps_match(capture)
    if found.matched == 0:
        raise SceneError(f"{capture.gps_path}: none of its {found.fixes} fixes names an image of the COLMAP "
                         f"model {capture.sparse_path} (matched by image name, then by file name)")
    return found


def _raster_header(path: Path) -> None:
    from toolkit.io.raster import read_header

    read_header(path)


def _rasters_meet_the_grid(scene: Scene, keys: list[str]) -> None:
    """Every raster must overlap the scene grid it is resampled onto (computing the grid also
    checks that the raster defining it reprojects to the scene CRS)."""
    from toolkit.io.raster import overlaps, read_header
    from toolkit.scene import scene_grid

    target = scene_grid(scene)
    for key in keys if target is not None else ():
        path = getattr(scene.files, key)
        if path != target.path and not overlaps(read_header(path).grid, target.grid):
            raise SceneError(f"{path}: does not overlap the scene grid, which {target.path.name} defines "
                             f"({_fmt(target.grid)}); check the CRS and transform of both files")


def _fmt(g) -> str:
    t = g.transform
    return f"{g.width}x{g.height} at ({t[2]:.2f}, {t[5]:.2f}) step {t[0]:g} in {g.crs}"


def _footprints(path: Path, crs: str) -> None:
    from toolkit.io.vector import check_footprints

    check_footprints(path, crs)


def _cloud_header(path: Path, scene_crs: str) -> None:
    if path.stat().st_size == 0:
        raise SceneError(f"{path}: file is empty")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        with open(path, "rb") as fh:
            if fh.readline().strip() != b"ply":
                raise SceneError(f"{path}: not a PLY file (missing 'ply' magic)")
    elif suffix in (".las", ".laz"):
        import laspy

        from toolkit.io.cloud import check_las_header

        check_las_header(path)
        try:
            with laspy.open(path) as reader:
                n = reader.header.point_count
        except Exception as exc:
            raise SceneError(f"{path}: cannot read LAS/LAZ header ({' '.join(str(exc).split())})") from exc
        if n == 0:
            raise SceneError(f"{path}: point cloud has no points")
        from toolkit.io.crs import check_cloud_crs

        check_cloud_crs(path, _las_crs(path), scene_crs)
    elif suffix != ".pcd":
        raise SceneError(f"{path}: unsupported point cloud format {suffix!r} (use .ply, .las, .laz, .pcd)")


def _las_crs(path: Path):
    """The CRS a LAS/LAZ header declares (laspy ``parse_crs``), None without one or when unreadable."""
    import laspy

    try:
        with laspy.open(path) as reader:
            return reader.header.parse_crs()
    except Exception:  # an unreadable CRS record: the cloud is used without one, as scene init does
        return None


def _sparse(path: Path) -> None:
    if not path.is_dir():
        raise SceneError(f"{path}: COLMAP model folder not found")
    for ext in (".bin", ".txt"):
        names = [path / f"{n}{ext}" for n in ("cameras", "images", "points3D")]
        if names[0].is_file():
            for f in names[1:]:
                if not f.is_file():
                    raise SceneError(f"{f}: file not found (COLMAP model incomplete)")
            return
    raise SceneError(f"{path}: no cameras.txt or cameras.bin in the COLMAP model folder")
