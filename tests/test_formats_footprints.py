"""Footprints from GeoPackage and Shapefile (pyogrio) in any CRS, besides GeoJSON and OSM; the
checks ``validate`` makes on footprint files (format, CRS, lon/lat range)."""

from __future__ import annotations

import dataclasses
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import shapely

from plugins.overview_osm import OsmFootprints
from tests.conftest import needs_shared
from tests.overview_scene import CRS, write_scene
from toolkit.cli import main
from toolkit.errors import SceneError
from toolkit.io.vector import check_footprints, read_footprints
from toolkit.observe import NullObserver
from toolkit.scene import load_scene

FEET_CRS = "EPSG:3735"  # NAD83 / Ohio South (ftUS)
IGN_SHP = Path(__file__).resolve().parents[2] / "shared/data/raw/ign-lidarhd-building/870000_6618000.subset.postIA.shp"


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory) -> Path:
    return write_scene(tmp_path_factory.mktemp("fp") / "scene")


def write_layer(path: Path, geoms, crs: str | None, fields: dict | None = None, layer: str | None = None,
                geometry_type: str = "Polygon", append: bool = False) -> Path:
    import pyogrio.raw
    from pyproj import CRS as ProjCRS

    fields = fields or {}
    wkt = ProjCRS.from_user_input(crs).to_wkt() if crs else None
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "'crs' was not provided")  # on purpose, when crs is None
        pyogrio.raw.write(path, shapely.to_wkb(np.asarray(geoms, dtype=object)), [np.asarray(v) for v in fields.values()],
                          list(fields), layer=layer, geometry_type=geometry_type, crs=wkt, append=append,
                          promote_to_multi=False)
    return path


def _osm_fields(fp) -> dict:
    rel = np.array([t.get("osm_type") == "relation" for t in fp.tags])
    return {"osm_id": fp.ids, "osm_type": np.where(rel, "relation", "way"),
            "height": np.array([t.get("height", "") for t in fp.tags], dtype=object)}


@pytest.fixture(scope="module")
def reference(scene_root):
    return read_footprints(scene_root / "overview/footprints.geojson", CRS)


@pytest.mark.parametrize("suffix", [".gpkg", ".shp"])
def test_geopackage_and_shapefile_in_feet_are_projected_to_the_scene_crs(scene_root, reference, tmp_path, suffix):
    feet = read_footprints(scene_root / "overview/footprints.geojson", FEET_CRS)
    path = write_layer(tmp_path / f"b{suffix}", feet.geometries, FEET_CRS, _osm_fields(feet))
    fp = read_footprints(path, CRS)
    assert fp.crs == CRS and fp.ids.tolist() == reference.ids.tolist() and not fp.skipped
    assert shapely.equals_exact(shapely.normalize(fp.geometries), shapely.normalize(reference.geometries), 1e-6).all()
    assert np.allclose(fp.height_m, reference.height_m, equal_nan=True)  # the height field is read
    check_footprints(path, CRS)


def test_osm_stage_reads_a_geopackage_like_the_geojson(scene_root, reference, tmp_path):
    feet = read_footprints(scene_root / "overview/footprints.geojson", FEET_CRS)
    path = write_layer(tmp_path / "b.gpkg", feet.geometries, FEET_CRS, _osm_fields(feet))
    scene = load_scene(scene_root)
    ref = OsmFootprints()(scene, NullObserver())
    got = OsmFootprints()(dataclasses.replace(scene, files=dataclasses.replace(scene.files, footprints=path)),
                          NullObserver())
    assert got.ids.tolist() == ref.ids.tolist()
    assert np.array_equal(got.label_image, ref.label_image)


@needs_shared("ign-lidarhd-building")
def test_real_ign_building_shapefile_lambert93():
    """IGN LiDAR HD building footprints: 40 PolygonZ in Lambert-93 (EPSG:2154, its .prj)."""
    assert IGN_SHP.is_file(), f"real data not present: {IGN_SHP}"
    same = read_footprints(IGN_SHP, "EPSG:2154")
    utm = read_footprints(IGN_SHP, "EPSG:32631")
    assert len(same) == len(utm) == 40 and not utm.skipped
    assert not shapely.has_z(utm.geometries).any()  # Z dropped
    minx, miny, maxx, maxy = shapely.total_bounds(same.geometries)
    assert (minx, miny, maxx, maxy) == pytest.approx((870157.6, 6616964.8, 870357.8, 6617202.4), abs=0.05)
    uminx, uminy, _, _ = shapely.total_bounds(utm.geometries)
    assert 600_000 < uminx < 800_000 and 5_000_000 < uminy < 5_300_000  # reprojected to UTM 31N
    ratio = shapely.area(utm.geometries) / shapely.area(same.geometries)
    assert np.allclose(ratio, ratio[0], rtol=1e-4) and 0.99 < ratio[0] < 1.01  # conformal: areas scale alike


def test_layer_without_crs_or_polygons_is_a_one_line_error(tmp_path):
    square = shapely.box(0, 0, 10, 10)
    write_layer(tmp_path / "nocrs.shp", [square], None)
    with pytest.raises(SceneError, match=r"nocrs.shp: layer 'nocrs' has no CRS; add its .prj"):
        read_footprints(tmp_path / "nocrs.shp", CRS)
    write_layer(tmp_path / "pts.gpkg", [shapely.Point(1, 2)], CRS, geometry_type="Point", layer="trees")
    with pytest.raises(SceneError, match=r"pts.gpkg: no polygon layer \(layers: trees \(Point\)\)"):
        check_footprints(tmp_path / "pts.gpkg", CRS)


def test_the_buildings_layer_of_a_geopackage_is_chosen(tmp_path):
    path = tmp_path / "city.gpkg"
    write_layer(path, [shapely.box(500000, 4400000, 500010, 4400010)], CRS, layer="parks")
    write_layer(path, [shapely.box(500020, 4400000, 500030, 4400012)] * 2, CRS, layer="buildings",
                fields={"id": np.array([7, 8])}, append=True)
    fp = read_footprints(path, CRS)
    assert fp.ids.tolist() == [7, 8]
    write_layer(path, [shapely.box(0, 0, 1, 1)], CRS, layer="houses", append=True)
    write_layer(tmp_path / "two.gpkg", [shapely.box(0, 0, 1, 1)], CRS, layer="a")
    write_layer(tmp_path / "two.gpkg", [shapely.box(0, 0, 1, 1)], CRS, layer="b", append=True)
    with pytest.raises(SceneError, match="several polygon layers"):
        read_footprints(tmp_path / "two.gpkg", CRS)


def _validate(scene: Path, capsys) -> tuple[int, list[str]]:
    recipe = scene.parent / "osm-only.yaml"
    recipe.write_text("recipe: 1\nname: osm-only\nsteps:\n  overview: {use: overview.osm}\n")
    code = main(["validate", str(recipe), "--scene", str(scene)])
    return code, capsys.readouterr().err.strip().splitlines()


def _point_manifest_at(scene: Path, name: str) -> None:
    manifest = scene / "scene.yaml"
    text = manifest.read_text().replace("footprints: overview/footprints.geojson", f"footprints: overview/{name}")
    manifest.write_text(text)


def test_validate_rejects_an_unknown_footprint_extension(scene_root, tmp_path, capsys):
    import shutil

    scene = Path(shutil.copytree(scene_root, tmp_path / "s"))
    (scene / "overview/footprints.kml").write_text("<kml/>")
    _point_manifest_at(scene, "footprints.kml")
    code, err = _validate(scene, capsys)
    assert code == 2 and len(err) == 1, err
    assert "footprints.kml: unknown footprint format '.kml'" in err[0] and ".gpkg, .shp" in err[0]


def test_validate_rejects_projected_geojson_without_crs_member_and_names_the_fix(scene_root, tmp_path, capsys):
    import shutil

    scene = Path(shutil.copytree(scene_root, tmp_path / "s"))
    fp = read_footprints(scene / "overview/footprints.geojson", CRS)
    doc = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "id": int(i), "properties": {}, "geometry": shapely.geometry.mapping(g)}
        for i, g in zip(fp.ids, fp.geometries)]}
    (scene / "overview/footprints.geojson").write_text(json.dumps(doc))
    code, err = _validate(scene, capsys)
    assert code == 2 and len(err) == 1, err
    assert "footprints.geojson: coordinates are not lon/lat" in err[0]
    assert "RFC 7946" in err[0] and '"crs": {"type": "name", "properties": {"name": "EPSG:32617"}}' in err[0]
    # with that member, the same file is read in the scene CRS
    doc["crs"] = {"type": "name", "properties": {"name": CRS}}
    (scene / "overview/footprints.geojson").write_text(json.dumps(doc))
    assert _validate(scene, capsys)[0] == 0
    assert read_footprints(scene / "overview/footprints.geojson", CRS).ids.tolist() == fp.ids.tolist()


def test_validate_accepts_a_shapefile_scene(scene_root, tmp_path, capsys):
    import shutil

    scene = Path(shutil.copytree(scene_root, tmp_path / "s"))
    feet = read_footprints(scene / "overview/footprints.geojson", FEET_CRS)
    write_layer(scene / "overview/buildings.shp", feet.geometries, FEET_CRS, _osm_fields(feet))
    _point_manifest_at(scene, "buildings.shp")
    code, err = _validate(scene, capsys)
    assert code == 0, err
