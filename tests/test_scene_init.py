"""``crossview scene init``: a scene.yaml from scattered files (relative, absolute, ``~``), formats
and CRSs detected, validate's checks run, EXIF GPS from the photos; bad input is one line, exit 2,
and nothing written."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.conftest import synthetic_scene
from toolkit.cli import main
from toolkit.io.raster import write_geotiff
from toolkit.scene import load_scene
from toolkit.types import Grid


@pytest.fixture(scope="module")
def tiny() -> Path:
    return synthetic_scene("tiny")


def _link(src: Path, dst: Path) -> Path:
    dst.parent.mkdir(parents=True, exist_ok=True)
    os.link(src, dst)
    return dst


def _init(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["scene", "init", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def _manifest(root: Path) -> dict:
    return yaml.safe_load((root / "scene.yaml").read_text())


def _image_names(tiny: Path) -> list[str]:
    from toolkit.io.colmap import read_model

    return list(read_model(tiny / "street/sparse").image_names)


def _jpeg(path: Path, lonlat: tuple[float, float] | None, sigma_m: float | None = None) -> None:
    """An 8x8 JPEG, with EXIF GPS (degrees, minutes, seconds and the hemisphere) when ``lonlat`` is given."""
    from PIL import ExifTags, Image

    exif = Image.Exif()
    if lonlat is not None:
        gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
        for (ref_tag, tag), value, hemispheres in (((1, 2), lonlat[1], "NS"), ((3, 4), lonlat[0], "EW")):
            a = abs(value)
            gps[ref_tag] = hemispheres[value < 0]
            gps[tag] = (float(int(a)), float(int(a * 60 % 60)), round(a * 3600 % 60, 6))
        if sigma_m is not None:
            gps[31] = sigma_m  # GPSHPositioningError
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", (8, 8), (90, 120, 150)).save(path, exif=exif)


# --- a scene from scattered files ------------------------------------------------------------------
def test_init_writes_a_scene_that_loads_and_validates(tiny, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    _link(tiny / "street/cloud.ply", tmp_path / "scene/street/cloud.ply")  # inside the scene folder
    for name in ("dsm.tif", "ortho.tif", "footprints.geojson"):
        _link(tiny / "overview" / name, tmp_path / "gis" / name)  # elsewhere, given relative to the cwd
    code, out, err = _init(capsys, "scene", "--cloud", "scene/street/cloud.ply", "--sparse", tiny / "street/sparse",
                           "--dsm", "gis/dsm.tif", "--ortho", "gis/ortho.tif", "--footprints",
                           "gis/footprints.geojson", "--gps", tiny / "street/gps.csv", "--name", "mine")
    assert code == 0, err
    doc = _manifest(tmp_path / "scene")
    assert (doc["scene"], doc["name"], doc["crs"]) == (1, "mine", "EPSG:32617")
    assert doc["street"]["cloud"] == "street/cloud.ply"  # inside the folder: relative
    assert doc["overview"]["dsm"] == str(tmp_path / "gis/dsm.tif")  # outside: absolute
    assert doc["street"]["sparse"] == str(tiny / "street/sparse")
    assert f"CRS EPSG:32617 (from {tmp_path / 'gis/dsm.tif'})" in out
    assert "PLY, 175,878 points, float64 x, y, z" in out and "COLMAP text model, 201 images" in out
    assert "4 bands uint8 (red, green, blue, nir)" in out and "GeoJSON footprints, lon/lat" in out
    assert "validate: ok" in out and "gps: 201 of 201 fixes match images" in out
    assert "next: crossview validate recipes/dsm.yaml --scene scene" in out
    scene = load_scene(tmp_path / "scene")
    assert scene.files.dsm == (tmp_path / "gis/dsm.tif").resolve()
    assert scene.files.street_cloud == (tmp_path / "scene/street/cloud.ply").resolve()
    assert sorted(p.name for p in (tmp_path / "scene").rglob("*")) == ["cloud.ply", "scene.yaml", "street"]
    recipe = Path(__file__).resolve().parents[1] / "recipes/dsm.yaml"
    assert main(["validate", str(recipe), "--scene", "scene", "-q"]) == 0


def test_tilde_paths_and_the_dem_entry(tiny, tmp_path, monkeypatch, capsys):
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    _link(tiny / "street/cloud.ply", home / "data/cloud.ply")
    _link(tiny / "overview/dsm.tif", home / "data/dem.tif")
    code, out, err = _init(capsys, tmp_path / "s", "--cloud", "~/data/cloud.ply", "--sparse", tiny / "street/sparse",
                           "--dem", "~/data/dem.tif")
    assert code == 0, err
    doc = _manifest(tmp_path / "s")
    assert doc["street"]["cloud"] == str(home / "data/cloud.ply")
    assert doc["overview"] == {"dem": str(home / "data/dem.tif")}
    assert "CRS EPSG:32617 (from" in out and "overview.dem" in out
    assert load_scene(tmp_path / "s").files.dem == (home / "data/dem.tif").resolve()
    # a hand-written scene.yaml may use ~ too
    (tmp_path / "hand").mkdir()
    (tmp_path / "hand/scene.yaml").write_text(
        "scene: 1\ncrs: EPSG:32617\nstreet: {cloud: ~/data/cloud.ply}\noverview: {dem: ~/data/dem.tif}\n")
    scene = load_scene(tmp_path / "hand")
    assert scene.files.street_cloud == (home / "data/cloud.ply").resolve()
    assert scene.files.dem == (home / "data/dem.tif").resolve()


# --- formats and CRSs ------------------------------------------------------------------------------
def _footprints_gpkg(tiny: Path, path: Path, crs: str) -> Path:
    import pyogrio.raw
    import shapely
    from pyproj import CRS

    from toolkit.io.vector import read_footprints

    fp = read_footprints(tiny / "overview/footprints.geojson", crs)
    pyogrio.raw.write(path, shapely.to_wkb(fp.geometries), [fp.ids], ["osm_id"], layer="buildings",
                      geometry_type="MultiPolygon", crs=CRS.from_user_input(crs).to_wkt(), promote_to_multi=True)
    return path


def _las_with_crs(path: Path, crs: str | None) -> Path:
    import laspy
    from pyproj import CRS

    header = laspy.LasHeader(point_format=7, version="1.4")
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    if crs:
        header.add_crs(CRS.from_user_input(crs))
    las = laspy.LasData(header)
    las.x, las.y, las.z = np.random.default_rng(0).uniform(0, 50, size=(3, 500))
    las.write(path)
    return path


def test_crs_from_projected_footprints_and_formats_detected(tiny, tmp_path, capsys):
    from toolkit.io.colmap import read_model, write_model

    gpkg = _footprints_gpkg(tiny, tmp_path / "buildings.gpkg", "EPSG:32617")
    write_model(read_model(tiny / "street/sparse"), tmp_path / "sparse/0", binary=True)  # COLMAP's layout
    code, out, err = _init(capsys, tmp_path / "s", "--cloud", _las_with_crs(tmp_path / "c.laz", None),
                           "--sparse", tmp_path / "sparse", "--footprints", gpkg)
    assert code == 0, err
    doc = _manifest(tmp_path / "s")
    assert doc["crs"] == "EPSG:32617" and f"(from {gpkg})" in out
    assert doc["overview"] == {"footprints": str(gpkg)}
    assert doc["street"]["sparse"] == str(tmp_path / "sparse/0")
    assert "COLMAP binary model (in 0/), 201 images" in out and "GeoPackage footprints, EPSG:32617" in out
    assert "LAZ 1.4, point format 7, 500 points, no CRS" in out
    assert "next: crossview validate recipes/osm.yaml" in out


def test_crs_from_a_las_cloud_and_osm_footprints(tiny, tmp_path, capsys):
    code, out, err = _init(capsys, tmp_path / "s", "--cloud", _las_with_crs(tmp_path / "c.las", "EPSG:32617"),
                           "--sparse", tiny / "street/sparse", "--footprints", tiny / "overview/map.osm")
    assert code == 0, err
    doc = _manifest(tmp_path / "s")
    assert doc["crs"] == "EPSG:32617" and f"(from {tmp_path / 'c.las'})" in out
    assert doc["overview"] == {"osm": str(tiny / "overview/map.osm")}  # OSM files are overview.osm


def test_crs_flag_wins(tiny, tmp_path, capsys):
    code, out, err = _init(capsys, tmp_path / "s", "--cloud", tiny / "street/cloud.ply", "--sparse",
                           tiny / "street/sparse", "--labels", tiny / "overview/labels.tif", "--crs", "EPSG:32617")
    assert code == 0, err
    assert "(from --crs)" in out and "next: crossview validate recipes/label_map.yaml" in out


# --- GPS from EXIF and from exiftool ---------------------------------------------------------------
def test_images_exif_gps_into_gps_csv(tiny, tmp_path, capsys):
    names = _image_names(tiny)
    rng = np.random.default_rng(1)
    truth = {}
    for k, name in enumerate(names[:12]):
        lonlat = (-82.9969 + rng.uniform(-1e-3, 1e-3), 39.9670 + rng.uniform(-1e-3, 1e-3)) if k < 10 else None
        _jpeg(tmp_path / "photos" / name, lonlat, sigma_m=2.5 if k < 5 else None)
        truth[name] = lonlat
    code, out, err = _init(capsys, tmp_path / "s", "--cloud", tiny / "street/cloud.ply", "--sparse",
                           tiny / "street/sparse", "--dsm", tiny / "overview/dsm.tif", "--images", tmp_path / "photos")
    assert code == 0, err
    assert _manifest(tmp_path / "s")["street"]["gps"] == "street/gps.csv"
    assert "10 of 201 images have EXIF GPS (12 found in the images folder)" in out
    assert "gps: 10 of 10 fixes match images" in out
    with open(tmp_path / "s/street/gps.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["image_name", "lon", "lat", "sigma_m"]
    assert [r["image_name"] for r in rows] == names[:10]
    for k, r in enumerate(rows):
        lon, lat = truth[r["image_name"]]
        assert abs(float(r["lon"]) - lon) < 1e-8 and abs(float(r["lat"]) - lat) < 1e-8
        assert r["sigma_m"] == ("2.5" if k < 5 else "")
    assert not list((tmp_path / "s").rglob("*.partial"))


def test_exiftool_csv_is_accepted_as_it_is(tiny, tmp_path, capsys):
    names = _image_names(tiny)[:20]
    lines = ["SourceFile,GPSLatitude,GPSLongitude,GPSHPositioningError"]
    lines += [f"photos/{n},39.967{k:02d},-82.9968{k:02d},3" for k, n in enumerate(names)]
    (tmp_path / "exif.csv").write_text("\n".join(lines) + "\n")
    code, out, err = _init(capsys, tmp_path / "s", "--cloud", tiny / "street/cloud.ply", "--sparse",
                           tiny / "street/sparse", "--dsm", tiny / "overview/dsm.tif", "--gps", tmp_path / "exif.csv")
    assert code == 0, err
    assert _manifest(tmp_path / "s")["street"]["gps"] == str(tmp_path / "exif.csv")
    assert "GPS fixes CSV, 20 fixes" in out and "gps: 20 of 20 fixes match images" in out


# --- bad input: one line, exit 2, nothing written --------------------------------------------------
def _feet_dsm(tmp: Path) -> list[str]:
    grid = Grid((1.64, 0.0, 1_800_000.0, 0.0, -1.64, 600_000.0), 20, 20, "EPSG:6549")
    write_geotiff(tmp / "feet.tif", np.zeros((20, 20), np.float32), grid, nodata=-9999.0)
    return ["--dsm", str(tmp / "feet.tif")]


def _far_labels(tmp: Path) -> list[str]:
    grid = Grid((0.5, 0.0, 100_000.0, 0.0, -0.5, 1_000_000.0), 20, 20, "EPSG:32617")
    write_geotiff(tmp / "far.tif", np.ones((20, 20), np.uint8), grid, nodata=255)
    return ["--labels", str(tmp / "far.tif")]


def _photos(tmp: Path, names: list[str], with_gps: bool) -> list[str]:
    for name in names:
        _jpeg(tmp / "photos" / name, (-82.99, 39.96) if with_gps else None)
    return ["--images", str(tmp / "photos")]


BAD = [
    # (id, extra arguments (made in tmp), whether the defaults --dsm is passed, fragment of the line)
    ("missing-file", lambda tmp, names: ["--ortho", str(tmp / "nope.tif")], True, "nope.tif: not found"),
    ("cloud-format", lambda tmp, names: ["--cloud", str(_touch(tmp / "c.xyz"))], True,
     "unsupported point cloud format '.xyz'"),
    ("sparse-is-a-file", lambda tmp, names: ["--sparse", str(_touch(tmp / "model.txt"))], True,
     "is a file; give the COLMAP model folder"),
    ("footprint-format", lambda tmp, names: ["--footprints", str(_touch(tmp / "b.kml"))], True,
     "unknown footprint format '.kml'"),
    ("no-crs", lambda tmp, names: ["--footprints", str(synthetic_scene("tiny") / "overview/footprints.geojson")],
     False, "no scene CRS"),
    ("feet-crs", lambda tmp, names: _feet_dsm(tmp), False,
     "is not metric: its axes are in US survey foot, not metres; use its metre twin EPSG:6548"),
    ("images-not-found", lambda tmp, names: _photos(tmp, ["other.jpg"], True), True,
     "none of the 201 images of the COLMAP model is in"),
    ("images-without-gps", lambda tmp, names: _photos(tmp, names[:3], False), True,
     "none of the 3 images found has an EXIF GPS position"),
    ("raster-elsewhere", lambda tmp, names: _far_labels(tmp) + _photos(tmp, names[:3], True), True,
     "does not overlap the scene grid"),
]


def _touch(path: Path) -> Path:
    path.write_bytes(b"not much\n")
    return path


@pytest.mark.parametrize("case", BAD, ids=[c[0] for c in BAD])
def test_bad_input_is_one_line_and_writes_nothing(case, tiny, tmp_path, capsys):
    _, extra, with_dsm, fragment = case
    base = {"--cloud": str(tiny / "street/cloud.ply"), "--sparse": str(tiny / "street/sparse")}
    if with_dsm:
        base["--dsm"] = str(tiny / "overview/dsm.tif")
    args = extra(tmp_path, _image_names(tiny))
    for key in [a for a in args if a in base]:
        del base[key]
    code, out, err = _init(capsys, tmp_path / "s", *[x for kv in base.items() for x in kv], *args)
    assert code == 2 and out == ""
    assert len(err.strip().splitlines()) == 1 and fragment in err and "Traceback" not in err, err
    assert not (tmp_path / "s").exists()


def test_an_existing_scene_is_kept_without_overwrite(tiny, tmp_path, capsys):
    (tmp_path / "s").mkdir()
    (tmp_path / "s/scene.yaml").write_text("scene: 1\n")
    args = ["--cloud", tiny / "street/cloud.ply", "--sparse", tiny / "street/sparse", "--dsm", tiny / "overview/dsm.tif"]
    code, _, err = _init(capsys, tmp_path / "s", *args)
    assert code == 2 and "already exists (pass --overwrite to replace it)" in err
    assert (tmp_path / "s/scene.yaml").read_text() == "scene: 1\n"
    code, _, err = _init(capsys, tmp_path / "s", *args, "--overwrite")
    assert code == 0, err
    assert _manifest(tmp_path / "s")["crs"] == "EPSG:32617"
