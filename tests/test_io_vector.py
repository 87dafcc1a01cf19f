"""toolkit.io.vector: footprints from GeoJSON / OSM XML / OSM PBF, projected, repaired, with ids and heights."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import shapely

from tests.conftest import RAW, needs_shared
from tests.overview_scene import CRS, buildings, osm_to_pbf, to_world, write_geojson, write_osm_xml
from toolkit.errors import SceneError
from toolkit.io.vector import RELATION_ID_OFFSET, building_height_m, read_footprints


def _fc(features: list[dict], **extra) -> dict:
    return {"type": "FeatureCollection", "features": features, **extra}


def _feature(coords, fid=None, **props) -> dict:
    f = {"type": "Feature", "properties": props, "geometry": {"type": "Polygon", "coordinates": coords}}
    if fid is not None:
        f["id"] = fid
    return f


@pytest.fixture(scope="module")
def osm_files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("vec")
    blds = buildings()
    write_geojson(d / "b.geojson", blds)
    write_osm_xml(d / "b.osm", blds)
    osm_to_pbf(d / "b.osm", d / "b.osm.pbf")
    write_osm_xml(d / "unsorted.osm", blds, sort=False)
    return {"geojson": d / "b.geojson", "xml": d / "b.osm", "pbf": d / "b.osm.pbf", "unsorted": d / "unsorted.osm"}


def test_geojson_lonlat_is_projected_to_the_scene_crs(osm_files):
    fp = read_footprints(osm_files["geojson"], CRS)
    truth = {b.id: to_world(b.poly) for b in buildings()}
    assert sorted(fp.ids.tolist()) == sorted(truth)
    for g, i in zip(fp.geometries, fp.ids):
        # 1e-7° rounding of the coordinates is ~1 cm
        assert shapely.hausdorff_distance(g, truth[int(i)]) < 0.03
    assert fp.crs == CRS and fp.repaired == 0 and not fp.skipped


@pytest.mark.parametrize("kind", ["xml", "pbf", "unsorted"])
def test_osm_files_give_the_geojson_geometries_and_ids(osm_files, kind):
    ref = read_footprints(osm_files["geojson"], CRS)
    fp = read_footprints(osm_files[kind], CRS)
    order_r, order_f = np.argsort(ref.ids), np.argsort(fp.ids)
    assert np.array_equal(ref.ids[order_r], fp.ids[order_f])
    for a, b in zip(ref.geometries[order_r], fp.geometries[order_f]):
        assert shapely.hausdorff_distance(a, b) < 1e-3
    court = fp.geometries[fp.ids == 104][0]
    assert len(court.interiors) == 1  # the multipolygon relation keeps its hole
    assert np.allclose(np.sort(fp.height_m), np.sort([b.height_m for b in buildings()]))


def test_geojson_crs_member_is_honoured(tmp_path):
    ring = [[0, 0], [20, 0], [20, 10], [0, 10], [0, 0]]
    coords = [[[500000 + x, 4400000 + y] for x, y in ring]]
    doc = _fc([_feature(coords, 7)], crs={"type": "name", "properties": {"name": "urn:ogc:def:crs:EPSG::32617"}})
    (tmp_path / "p.geojson").write_text(json.dumps(doc))
    fp = read_footprints(tmp_path / "p.geojson", CRS)
    assert fp.geometries[0].bounds == pytest.approx((500000, 4400000, 500020, 4400010))
    # to another CRS: area is preserved to well under 1 %
    fp33 = read_footprints(tmp_path / "p.geojson", "EPSG:32616")
    assert fp33.geometries[0].area == pytest.approx(200, rel=1e-2)
    assert fp33.geometries[0].bounds[0] > 900000  # west of 17N's zone in 16N's coordinates


def test_ids_from_overpass_style_and_properties(tmp_path):
    sq = lambda x: [[[x, 0], [x + 1e-4, 0], [x + 1e-4, 1e-4], [x, 1e-4], [x, 0]]]
    feats = [_feature(sq(-81.0), "way/12"), _feature(sq(-81.001), "relation/12"),
             _feature(sq(-81.002), None, **{"@id": "way/40"}), _feature(sq(-81.003), None, osm_id=41),
             _feature(sq(-81.004))]
    (tmp_path / "ids.geojson").write_text(json.dumps(_fc(feats)))
    fp = read_footprints(tmp_path / "ids.geojson", CRS)
    # relation 12 collides with way 12 → offset; unnamed feature numbered after the largest id
    assert fp.ids.tolist() == [12, 12 + RELATION_ID_OFFSET, 40, 41, 12 + RELATION_ID_OFFSET + 1]


def test_invalid_polygon_is_repaired_and_non_polygons_are_skipped(tmp_path):
    bowtie = [[[-81.0, 40.0], [-80.9998, 40.0002], [-80.9998, 40.0], [-81.0, 40.0002], [-81.0, 40.0]]]
    feats = [_feature(bowtie, 1),
             {"type": "Feature", "id": 2, "properties": {},
              "geometry": {"type": "LineString", "coordinates": [[-81, 40], [-80.9, 40]]}},
             {"type": "Feature", "id": 3, "properties": {}, "geometry": None},
             _feature([[1, 2]], 4)]
    (tmp_path / "bad.geojson").write_text(json.dumps(_fc(feats)))
    fp = read_footprints(tmp_path / "bad.geojson", CRS)
    assert fp.repaired == 1 and len(fp) == 1
    assert fp.geometries[0].is_valid and fp.geometries[0].area > 100
    assert len(fp.skipped) == 3 and "LineString" in fp.skipped[0] and "None" in fp.skipped[1]
    assert "bad coordinates" in fp.skipped[2]


def test_empty_geojson_gives_no_footprints(tmp_path):
    (tmp_path / "empty.geojson").write_text(json.dumps(_fc([])))
    assert len(read_footprints(tmp_path / "empty.geojson", CRS)) == 0


@pytest.mark.parametrize("text, match", [
    ("{not json", "invalid GeoJSON"),
    ('{"features": []}', "no 'type' member"),
    ('{"type": "FeatureCollection"}', "without a 'features' list"),
])
def test_malformed_geojson_is_a_one_line_error(tmp_path, text, match):
    (tmp_path / "x.geojson").write_text(text)
    with pytest.raises(SceneError, match=match) as err:
        read_footprints(tmp_path / "x.geojson", CRS)
    assert "\n" not in str(err.value) and "x.geojson" in str(err.value)


def test_duplicate_ids_and_unknown_format_are_errors(tmp_path):
    sq = [[[-81, 40], [-80.9999, 40], [-80.9999, 40.0001], [-81, 40.0001], [-81, 40]]]
    (tmp_path / "dup.geojson").write_text(json.dumps(_fc([_feature(sq, 5), _feature(sq, 5)])))
    with pytest.raises(SceneError, match="duplicate building ids"):
        read_footprints(tmp_path / "dup.geojson", CRS)
    (tmp_path / "x.kml").write_text("")
    with pytest.raises(SceneError, match="unknown footprint format"):
        read_footprints(tmp_path / "x.kml", CRS)
    (tmp_path / "garbage.osm").write_text("this is not xml")
    with pytest.raises(SceneError, match="cannot read OSM data"):
        read_footprints(tmp_path / "garbage.osm", CRS)


@pytest.mark.parametrize("tags, expected", [
    ({"height": "12.5"}, 12.5), ({"height": "12 m"}, 12.0), ({"height": "30 ft"}, 9.144),
    ({"height": 7}, 7.0), ({"building:levels": "4"}, 12.0), ({"height": "x", "building:levels": "2"}, 6.0),
    ({"building:levels": "3 m"}, None), ({}, None),
])
def test_heights_from_tags(tags, expected):
    h = building_height_m(tags)
    assert (np.isnan(h) if expected is None else h == pytest.approx(expected))


@needs_shared("helsinki-osm")
def test_real_helsinki_pbf():
    fp = read_footprints(RAW / "helsinki-osm/Helsinki.osm.pbf", "EPSG:32635")
    # 385 building ways + 61 multipolygon relations assemble into valid areas
    assert len(fp) == 446
    assert shapely.is_valid(fp.geometries).all()
    # the relations are courtyard blocks: outer + inner rings
    assert sum(1 for g in fp.geometries if any(len(p.interiors) for p in getattr(g, "geoms", [g]))) == 61
    area = shapely.area(fp.geometries)
    assert 5 < np.median(area) < 5000  # m², i.e. really projected to metres
    minx, miny, maxx, maxy = shapely.total_bounds(fp.geometries)
    assert 385_000 < minx < maxx < 387_000 and 6_671_000 < miny < maxy < 6_673_500  # central Helsinki, UTM 35N
    assert np.isfinite(fp.height_m).sum() == 154  # height or building:levels tags


def test_rejected_osm_areas_are_rebuilt_like_geojson(tmp_path):
    """Relations whose outer rings overlap and self-intersecting ways: osmium's assembler
    rejects them; they are rebuilt from their rings and repaired like the same GeoJSON."""
    a = [(-81.0, 40.0), (-80.9998, 40.0), (-80.9998, 40.0002), (-81.0, 40.0002)]
    b = [(-80.9999, 40.0001), (-80.9996, 40.0001), (-80.9996, 40.0003), (-80.9999, 40.0003)]  # overlaps a
    bow = [(-80.999, 40.0), (-80.9988, 40.0002), (-80.9988, 40.0), (-80.999, 40.0002)]
    nodes, nid = [], 1
    ways = []
    for wid, ring in ((1, a), (2, b), (3, bow)):
        refs = []
        for lon, lat in ring:
            nodes.append(f'<node id="{nid}" version="1" lat="{lat:.7f}" lon="{lon:.7f}"/>')
            refs.append(nid)
            nid += 1
        tags = '<tag k="building" v="yes"/>' if wid == 3 else ""
        nds = "".join(f'<nd ref="{r}"/>' for r in refs + refs[:1])
        ways.append(f'<way id="{wid}" version="1">{nds}{tags}</way>')
    rel = ('<relation id="9" version="1"><member type="way" ref="1" role="outer"/>'
           '<member type="way" ref="2" role="outer"/><tag k="type" v="multipolygon"/>'
           '<tag k="building" v="yes"/></relation>')
    (tmp_path / "bad.osm").write_text('<?xml version="1.0"?>\n<osm version="0.6">\n'
                                      + "\n".join(nodes + ways + [rel]) + "\n</osm>\n")
    close = lambda r: [list(p) for p in r + r[:1]]
    geo = _fc([{"type": "Feature", "id": "relation/9", "properties": {"building": "yes"},
                "geometry": {"type": "MultiPolygon", "coordinates": [[close(a)], [close(b)]]}},
               _feature([close(bow)], "way/3", building="yes")])
    (tmp_path / "bad.geojson").write_text(json.dumps(geo))
    osm = read_footprints(tmp_path / "bad.osm", CRS)
    ref = read_footprints(tmp_path / "bad.geojson", CRS)
    assert sorted(osm.ids.tolist()) == sorted(ref.ids.tolist()) == [3, 9] and not osm.skipped
    for i in (3, 9):
        g, h = osm.geometries[osm.ids == i][0], ref.geometries[ref.ids == i][0]
        assert g.is_valid and shapely.equals_exact(shapely.normalize(g), shapely.normalize(h), 1e-6)
    joined = osm.geometries[osm.ids == 9][0]
    assert joined.geom_type == "Polygon"  # the two halves are one building


def test_projected_coordinates_without_crs_member(tmp_path):
    ring = [[500000, 4400000], [500020, 4400000], [500020, 4400010], [500000, 4400010], [500000, 4400000]]
    (tmp_path / "p.geojson").write_text(json.dumps(_fc([_feature([ring], 1)])))
    with pytest.raises(SceneError, match="p.geojson: coordinates are not lon/lat .* 'crs' member") as err:
        read_footprints(tmp_path / "p.geojson", CRS)
    assert "\n" not in str(err.value)
