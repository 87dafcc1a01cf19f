"""``crossview scene init DIR``: write DIR/scene.yaml from files anywhere, check it as ``validate``
does, and say what was found.

Paths on the command line are relative to the working directory or absolute (``~`` expanded).
scene.yaml names a file inside DIR relative to DIR (the folder can be moved with its files) and any
other file by its absolute path. Formats are detected from the files: clouds PLY, LAS/LAZ or PCD; a
COLMAP text or binary model folder (or a folder holding just one, as COLMAP's ``sparse/0``);
GeoTIFF rasters; footprints GeoJSON, GeoPackage, Shapefile, OSM XML or PBF (OSM files become
``overview.osm``, the others ``overview.footprints``). The scene CRS is ``--crs``, else the DSM's,
else the first other raster's (labels, ortho, DEM), else the footprints' when projected, else a
LAS/LAZ cloud's; it must be projected and metric (``toolkit.io.crs``). ``--images DIR`` writes
DIR/street/gps.csv from the photos' EXIF (``toolkit.io.exif``).

Nothing is written unless every check passes: scene.yaml (and gps.csv) are written under a
``.partial`` name, checked, then renamed.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from toolkit.errors import SceneError
from toolkit.io.exif import ExifScan
from toolkit.types import Scene, SceneFiles

# option → manifest entry, in the order scene.yaml lists them
ENTRIES: tuple[tuple[str, str], ...] = (
    ("dsm", "overview.dsm"), ("ortho", "overview.ortho"), ("footprints", "overview.footprints"),
    ("labels", "overview.labels"), ("dem", "overview.dem"),
    ("cloud", "street.cloud"), ("sparse", "street.sparse"), ("gps", "street.gps"))
RASTER_OPTIONS = ("dsm", "labels", "ortho", "dem")  # after --crs, the first of these gives the scene CRS
CLOUD_FORMATS = {".ply": "PLY", ".las": "LAS", ".laz": "LAZ", ".pcd": "PCD"}
FOOTPRINT_FORMATS = {".gpkg": "GeoPackage", ".shp": "Shapefile"}
GPS_FILE = "street/gps.csv"  # written by --images
PARTIAL = ".partial"


@dataclass(frozen=True)
class Input:
    """A file given on the command line: its option, manifest entry, absolute path, what it is and
    its CRS (None: none declared); image_names: the images a COLMAP model lists (--sparse only)."""

    option: str
    entry: str
    path: Path
    what: str
    crs: str | None = None
    image_names: tuple[str, ...] = ()


@dataclass(frozen=True)
class InitResult:
    """The scene written, where its CRS comes from, what each input is, the EXIF scan and GPS match."""

    scene: Scene
    crs_from: str
    inputs: tuple[Input, ...]
    exif: ExifScan | None
    gps: Any  # toolkit.validate.GpsMatch | None


def init_scene(args: argparse.Namespace) -> InitResult:
    from toolkit.io.crs import check_metric_crs

    root = absolute(args.dir)
    refuse_existing(root, args.overwrite, bool(args.images))
    inputs = tuple(describe(option, existing(option, value)) for option, value in given(args))
    crs, crs_from = scene_crs(args.crs, inputs)
    check_metric_crs(crs_from if crs_from == "--crs" else f"{crs_from} (the scene CRS comes from it unless "
                     "--crs is given)", crs)
    exif = scan_exif(args.images, inputs) if args.images else None
    manifest = compose(root, args.name or root.name, crs, inputs, exif)
    scene, gps = write_checked(root, manifest, exif)
    return InitResult(scene, crs_from, inputs, exif, gps)


# --- command-line paths -------------------------------------------------------------------------
def absolute(value: str | Path) -> Path:
    """``~`` expanded, relative to the working directory; symlinks kept as given."""
    return Path(os.path.abspath(Path(value).expanduser()))


def given(args: argparse.Namespace) -> list[tuple[str, str]]:
    return [(option, getattr(args, option)) for option, _ in ENTRIES if getattr(args, option, None)]


def existing(option: str, value: str) -> Path:
    path = absolute(value)
    where = f"--{option} {value}" + (f" ({path})" if str(path) != value else "")
    if not path.exists():
        raise SceneError(f"{where}: not found")
    if option == "sparse" and not path.is_dir():
        raise SceneError(f"{where}: is a file; give the COLMAP model folder (holding cameras, images and "
                         "points3D .bin or .txt)")
    if option != "sparse" and path.is_dir():
        raise SceneError(f"{where}: is a folder, not a file")
    return path


def refuse_existing(root: Path, overwrite: bool, writes_gps: bool) -> None:
    if root.exists() and not root.is_dir():
        raise SceneError(f"{root}: exists and is not a folder")
    for path in [root / "scene.yaml"] + ([root / GPS_FILE] if writes_gps else []):
        if path.exists() and not overwrite:
            raise SceneError(f"{path}: already exists (pass --overwrite to replace it)")


def manifest_path(path: Path, root: Path) -> str:
    """Relative to the scene folder when the file is inside it, else absolute."""
    try:
        return path.relative_to(root).as_posix()
    except ValueError:
        return str(path)


# --- what each file is --------------------------------------------------------------------------
def describe(option: str, path: Path) -> Input:
    entry = dict(ENTRIES)[option]
    if option == "cloud":
        return Input(option, entry, path, *cloud_info(path))
    if option == "sparse":
        return sparse_info(path)
    if option == "footprints":
        return footprints_info(path)
    if option == "gps":
        from toolkit.io.gps import read_gps_csv

        return Input(option, entry, path, f"GPS fixes CSV, {len(read_gps_csv(path))} fixes")
    return Input(option, entry, path, *raster_info(path))


def cloud_info(path: Path) -> tuple[str, str | None]:
    """(what it is, its CRS): LAS/LAZ from its header (and its CRS VLR), PLY/PCD from their header."""
    fmt = CLOUD_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise SceneError(f"{path}: unsupported point cloud format {path.suffix!r} (use .ply, .las, .laz, .pcd)")
    if fmt in ("LAS", "LAZ"):
        return las_info(path, fmt)
    from toolkit.io.cloud import coordinate_dtype

    count = declared_count(path, "vertex" if fmt == "PLY" else "POINTS")
    dtype = {"f4": "float32 x, y, z", "f8": "float64 x, y, z"}.get(coordinate_dtype(path) or "", "")
    return ", ".join(filter(None, [fmt, f"{count:,} points" if count is not None else "", dtype])), None


def declared_count(path: Path, word: str, max_lines: int = 64) -> int | None:
    """The point count a PLY (``element vertex N``) or PCD (``POINTS N``) header declares."""
    with open(path, "rb") as fh:
        for _ in range(max_lines):
            words = fh.readline(4096).decode("ascii", "replace").split()
            if words[:1] in (["end_header"], ["DATA"]):
                break
            if len(words) >= 2 and words[-2] == word and words[-1].isdigit():
                return int(words[-1])
    return None


def las_info(path: Path, fmt: str) -> tuple[str, str | None]:
    import laspy

    from toolkit.io.cloud import check_las_header

    check_las_header(path)
    try:
        with laspy.open(path) as reader:
            header = reader.header
    except Exception as exc:
        raise SceneError(f"{path}: cannot read LAS/LAZ header ({' '.join(str(exc).split())})") from exc
    try:
        crs = header.parse_crs()
    except Exception:  # an unreadable CRS record: the cloud is used without one, as most street clouds
        crs = None
    code = crs_code(crs) if crs is not None else None
    return (f"{fmt} {header.version}, point format {header.point_format.id}, {header.point_count:,} points, "
            f"{code or 'no CRS'}"), code


def sparse_info(path: Path) -> Input:
    from toolkit.io.colmap import read_model

    folder = model_folder(path)
    model = read_model(folder)
    kind = "binary" if (folder / "cameras.bin").is_file() else "text"
    where = f" (in {folder.name}/)" if folder != path else ""
    what = f"COLMAP {kind} model{where}, {len(model.image_names):,} images, {len(model.points3d):,} points"
    return Input("sparse", "street.sparse", folder, what, image_names=tuple(model.image_names))


def model_folder(path: Path) -> Path:
    """``path``, or its only sub-folder holding a model (COLMAP writes ``sparse/0``)."""
    if _has_model(path):
        return path
    subs = [p for p in sorted(path.iterdir()) if p.is_dir() and _has_model(p)]
    if len(subs) == 1:
        return subs[0]
    if subs:
        raise SceneError(f"{path}: holds several COLMAP models ({', '.join(p.name for p in subs)}); "
                         "give --sparse the one to use")
    raise SceneError(f"{path}: no cameras.txt or cameras.bin in the COLMAP model folder")


def _has_model(folder: Path) -> bool:
    return any((folder / f"cameras{ext}").is_file() for ext in (".bin", ".txt"))


def raster_info(path: Path) -> tuple[str, str]:
    from toolkit.io.raster import read_header
    from toolkit.scene import describe_grid

    header = read_header(path)
    bands = f"{header.count} band{'s' if header.count > 1 else ''} {header.dtype}"
    if any(header.band_names):
        bands += f" ({', '.join(n or '?' for n in header.band_names)})"
    return f"GeoTIFF, {bands}, {describe_grid(header.grid)}", crs_code(header.grid.crs)


def footprints_info(path: Path) -> Input:
    from toolkit.io.vector import footprint_format, footprints_crs

    fmt = footprint_format(path)
    crs = crs_code(footprints_crs(path))
    label = {"geojson": "GeoJSON", "osm": "OSM"}.get(fmt) or FOOTPRINT_FORMATS.get(path.suffix.lower(), fmt)
    where = crs if is_projected(crs) else "lon/lat"
    entry = "overview.osm" if fmt == "osm" else "overview.footprints"
    return Input("footprints", entry, path, f"{label} footprints, {where}", crs)


def crs_code(crs: Any) -> str:
    """``AUTH:CODE`` when pyproj finds one for ``crs`` (a WKT from a GeoTIFF or LAS header), else its WKT."""
    from toolkit.io.crs import parse_crs

    obj = parse_crs(crs, crs) if isinstance(crs, str) else crs
    auth = obj.to_authority(min_confidence=90)
    return f"{auth[0]}:{auth[1]}" if auth else obj.to_wkt()


def is_projected(crs: str | None) -> bool:
    from pyproj import CRS

    return crs is not None and CRS.from_user_input(crs).is_projected


# --- the scene CRS ------------------------------------------------------------------------------
def scene_crs(given_crs: str | None, inputs: tuple[Input, ...]) -> tuple[str, str]:
    """(scene CRS, where it comes from): --crs, the DSM, another raster, projected footprints, a LAS/LAZ."""
    from toolkit.io.crs import parse_crs

    if given_crs:
        parse_crs(given_crs, "--crs")
        return given_crs, "--crs"
    by_option = {i.option: i for i in inputs}
    ranked = [by_option[o] for o in RASTER_OPTIONS if o in by_option]
    ranked += [i for i in inputs if i.option == "footprints" and is_projected(i.crs)]
    ranked += [i for i in inputs if i.option == "cloud" and i.crs]
    if not ranked:
        raise SceneError("no scene CRS: no raster, no projected footprints and no LAS/LAZ CRS among the inputs; "
                         "pass --crs with a metric projected CRS (e.g. the local UTM zone, EPSG:326zz north)")
    return ranked[0].crs, str(ranked[0].path)


# --- EXIF GPS -----------------------------------------------------------------------------------
def scan_exif(images: str, inputs: tuple[Input, ...]) -> ExifScan:
    from toolkit.io.exif import scan_images

    folder = absolute(images)
    if not folder.is_dir():
        raise SceneError(f"--images {images}: {folder} is not a folder")
    names = next(i.image_names for i in inputs if i.option == "sparse")
    if not names:
        raise SceneError(f"--images {images}: the COLMAP model names no image")
    scan = scan_images(folder, names)
    if scan.found == 0:
        raise SceneError(f"--images {images}: none of the {len(names)} images of the COLMAP model is in "
                         f"{folder} (looked for {names[0]!r} there and as a file name)")
    if not scan.fixes:
        raise SceneError(f"--images {images}: none of the {scan.found} images found has an EXIF GPS position "
                         "(GPSLatitude, GPSLongitude); give the fixes as a CSV with --gps")
    return scan


# --- writing and checking -----------------------------------------------------------------------
def compose(root: Path, name: str, crs: str, inputs: tuple[Input, ...], exif: ExifScan | None) -> dict:
    doc: dict[str, Any] = {"scene": 1, "name": name, "crs": crs}
    for item in inputs:
        section, key = item.entry.split(".")
        doc.setdefault(section, {})[key] = manifest_path(item.path, root)
    if exif is not None:
        doc.setdefault("street", {})["gps"] = GPS_FILE
    return doc


def write_checked(root: Path, manifest: dict, exif: ExifScan | None) -> tuple[Scene, Any]:
    """Write scene.yaml (and gps.csv) under ``.partial`` names, check them, then rename them; on any
    error remove what was written, folders included."""
    from toolkit.io.exif import write_gps_csv
    from toolkit.scene import load_scene

    made = make_folders(root / "street" if exif is not None else root)
    gps_partial, yaml_partial = root / f"{GPS_FILE}{PARTIAL}", root / f"scene.yaml{PARTIAL}"
    try:
        draft = manifest
        if exif is not None:
            write_gps_csv(gps_partial, exif.fixes)
            draft = {**manifest, "street": {**manifest["street"], "gps": f"{GPS_FILE}{PARTIAL}"}}
        yaml_partial.write_text(yaml.safe_dump(draft, sort_keys=False, allow_unicode=True))
        gps = check_files(load_scene(yaml_partial))
        yaml_partial.write_text(yaml.safe_dump(manifest, sort_keys=False, allow_unicode=True))
        if exif is not None:
            gps_partial.replace(root / GPS_FILE)
        yaml_partial.replace(root / "scene.yaml")
    except BaseException:
        for path in (gps_partial, yaml_partial):
            path.unlink(missing_ok=True)
        for folder in reversed(made):
            with contextlib.suppress(OSError):  # the original error matters, not a folder left behind
                folder.rmdir()
        raise
    return load_scene(root), gps


def make_folders(folder: Path) -> list[Path]:
    """Create ``folder`` and its missing parents; the ones created, outermost first."""
    missing = [p for p in [folder, *folder.parents] if not p.exists()][::-1]
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"{folder}: cannot create the folder ({exc.strerror or exc})") from exc
    return missing


def check_files(scene: Scene) -> Any:
    """``validate``'s checks of every file the scene names (the stages' own checks need a recipe:
    ``crossview validate``); the GPS match when the scene has fixes and a model."""
    from toolkit.capture import StreetCapture
    from toolkit.validate import check_gps, check_scene_files

    keys = [f.name for f in dataclasses.fields(SceneFiles) if scene.has(f.name)]
    check_scene_files(scene, keys)
    return check_gps(StreetCapture(scene)) if scene.has("gps") and scene.has("sparse") else None


# --- the command --------------------------------------------------------------------------------
def summary_lines(result: InitResult, dir_arg: str) -> list[str]:
    scene = result.scene
    lines = [f"{scene.root / 'scene.yaml'}: scene {scene.name!r}, CRS {scene.crs} (from {result.crs_from})"]
    listed = scene.manifest
    for item in result.inputs:
        section, key = item.entry.split(".")
        lines.append(f"  {item.entry:20s} {listed[section][key]}: {item.what}")
    if result.exif is not None:
        e = result.exif
        lines.append(f"  {'street.gps':20s} {GPS_FILE}: {len(e.fixes)} of {e.images} images have EXIF GPS "
                     f"({e.found} found in the images folder)")
    gps = f"; gps: {result.gps.matched} of {result.gps.fixes} fixes match images" if result.gps else ""
    lines.append(f"validate: ok (every file checked){gps}")
    recipe = suggested_recipe(scene)
    lines.append(f"next: crossview validate {recipe} --scene {dir_arg}" if recipe else
                 "next: add an over-view source (--dsm, --footprints or --labels) for a recipe to match against")
    return lines


def suggested_recipe(scene: Scene) -> str | None:
    """The shipped recipe for the scene's over-view source."""
    if scene.has("dsm"):
        return "recipes/dsm.yaml" + ("" if scene.has("ortho") else " -s steps.overview.params.use_ortho=false")
    if scene.has("footprints") or scene.has("osm"):
        return "recipes/osm.yaml"
    if scene.has("labels"):
        return "recipes/label_map.yaml"
    return None


def cmd_init(args: argparse.Namespace) -> int:
    for line in summary_lines(init_scene(args), args.dir):
        print(line)
    return 0


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("scene", help="make a scene folder (crossview scene init)",
                              description="Scene folders (contract: docs/formats.md).")
    actions = p.add_subparsers(dest="scene_command", metavar="ACTION")
    actions.required = True
    init = actions.add_parser(
        "init", help="write DIR/scene.yaml from files anywhere and check it",
        description="Write DIR/scene.yaml naming the given files (inside DIR: relative paths, else absolute), "
                    "detect their formats and CRSs, and run validate's file checks. Nothing is written when a "
                    "check fails.")
    init.add_argument("dir", help="scene folder (created when missing)")
    init.add_argument("--cloud", required=True, help="dense street cloud: PLY, LAS/LAZ or PCD")
    init.add_argument("--sparse", required=True, help="COLMAP model folder, text or binary (or sparse/ holding 0/)")
    init.add_argument("--dsm", help="DSM GeoTIFF (heights in m, any CRS)")
    init.add_argument("--ortho", help="orthophoto GeoTIFF (bands red, green, blue, nir)")
    init.add_argument("--labels", help="building label map GeoTIFF (1 building, 0 other, 255 nodata)")
    init.add_argument("--dem", help="terrain DEM GeoTIFF (recorded as overview.dem)")
    init.add_argument("--footprints", help="building footprints: GeoJSON, GeoPackage, Shapefile, OSM XML or PBF")
    gps = init.add_mutually_exclusive_group()
    gps.add_argument("--gps", help="GPS fixes CSV: image_name,lon,lat[,sigma_m], or exiftool -csv -n output")
    gps.add_argument("--images", help="folder of the photos: their EXIF GPS goes to DIR/street/gps.csv")
    init.add_argument("--crs", help="scene CRS (default: the DSM's, else another raster's, else projected "
                      "footprints', else a LAS/LAZ cloud's)")
    init.add_argument("--name", help="scene name (default: the folder name)")
    init.add_argument("--overwrite", action="store_true",
                      help="replace an existing scene.yaml (and street/gps.csv with --images)")
    init.set_defaults(func=cmd_init)
