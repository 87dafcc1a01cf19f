"""Bad input across the CLI: each case must exit 2 with ONE line naming the culprit, no traceback,
and leave no output folder (nor a temporary one). Cases are data: (id, recipe, mutation, fragment).

Every case starts from a hard-linked copy of the synthetic ``tiny`` scene; a mutation replaces files
(never writes through a link).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

from tests.conftest import REPO, synthetic_scene
from toolkit.cli import main

Mutation = Callable[[Path, Path], list[str]]  # (scene dir, tmp dir) → extra CLI args


def _replace(path: Path, data: bytes | str) -> None:
    path.unlink(missing_ok=True)
    path.write_bytes(data.encode() if isinstance(data, str) else data)


def _manifest(scene: Path, edit: Callable[[str], str]) -> None:
    p = scene / "scene.yaml"
    _replace(p, edit(p.read_text()))


def _cloud(scene: Path, xyz: np.ndarray, name: str = "cloud.ply") -> None:
    from toolkit.io.cloud import write_ply

    target = scene / "street" / name
    target.unlink(missing_ok=True)
    write_ply(target, xyz)
    if name != "cloud.ply":
        _manifest(scene, lambda s: s.replace("cloud: street/cloud.ply", f"cloud: street/{name}"))


def _las(scene: Path, ext: str, corrupt: str) -> None:
    import laspy

    pts = np.random.default_rng(0).uniform(0, 50, size=(1000, 3))
    target = scene / "street" / f"cloud.{ext}"
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.offsets, hdr.scales = [0, 0, 0], [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts.T
    las.write(target)
    raw = target.read_bytes()
    if corrupt == "truncated":
        _replace(target, raw[: len(raw) // 2])
    elif corrupt == "garbage":
        _replace(target, raw[:100] + os.urandom(len(raw) - 100))
    elif corrupt == "empty":
        _replace(target, b"")
    _manifest(scene, lambda s: s.replace("cloud: street/cloud.ply", f"cloud: street/cloud.{ext}"))


def _geotiff_no_crs(scene: Path) -> None:
    import rasterio

    p = scene / "overview/dsm.tif"
    with rasterio.open(p) as ds:
        data, profile = ds.read(), ds.profile
    profile.pop("crs", None)
    p.unlink()
    with rasterio.open(p, "w", **profile) as ds:
        ds.write(data)


def _rewrite_raster(scene: Path, name: str, **change) -> None:
    import rasterio
    from rasterio.transform import Affine

    p = scene / "overview" / name
    with rasterio.open(p) as ds:
        data, profile, desc = ds.read(), ds.profile, ds.descriptions
    if "bands" in change:
        data, desc = data[: change["bands"]], desc[: change["bands"]]
        profile["count"] = change["bands"]
    if "shift_px" in change:
        t = profile["transform"]
        profile["transform"] = Affine(t.a, t.b, t.c + change["shift_px"] * t.a, t.d, t.e, t.f)
    if "crs" in change:
        profile["crs"] = change["crs"]
    if "fill" in change:
        data[:] = change["fill"]
    p.unlink()
    with rasterio.open(p, "w", **profile) as ds:
        ds.write(data)
        if "bands" not in change:
            for i, d in enumerate(desc, 1):
                if d:
                    ds.set_band_description(i, d)


def _footprints(scene: Path, doc) -> None:
    _replace(scene / "overview/footprints.geojson", json.dumps(doc) if not isinstance(doc, str) else doc)


def _edit_footprints(scene: Path, edit_ring: Callable[[list], list]) -> None:
    doc = json.loads((scene / "overview/footprints.geojson").read_text())
    for f in doc["features"]:
        g = f["geometry"]
        polys = [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]
        for poly in polys:
            poly[:] = [edit_ring(ring) for ring in poly]
    _footprints(scene, doc)


def _projected_footprints(scene: Path) -> None:
    from pyproj import Transformer

    tr = Transformer.from_crs("EPSG:4326", "EPSG:32617", always_xy=True)
    _edit_footprints(scene, lambda ring: [list(tr.transform(x, y)) for x, y in ring])


def _collapsed_ring(ring: list) -> list:
    """Every vertex on one line: a polygon with no area, which make_valid cannot turn into one."""
    (x0, y0), (x1, y1) = ring[0], ring[1]
    return [[x0, y0], [x1, y1], [x0, y0], [x1, y1]]


def _images_txt(scene: Path, edit: Callable[[list[str]], list[str]]) -> None:
    p = scene / "street/sparse/images.txt"
    _replace(p, "\n".join(edit(p.read_text().splitlines())) + "\n")


def _drop_camera(scene: Path) -> None:
    p = scene / "street/sparse/cameras.txt"
    lines = p.read_text().splitlines()
    _replace(p, "\n".join(ln for ln in lines if ln.startswith("#")) + "\n")


def _drop_points(scene: Path) -> None:
    p = scene / "street/sparse/points3D.txt"
    lines = p.read_text().splitlines()
    _replace(p, "\n".join(lines[: len(lines) // 2]) + "\n")


def _recipe(tmp: Path, text: str, name: str = "bad.yaml") -> str:
    (tmp / name).write_text(text)
    return str(tmp / name)


DSM = str(REPO / "recipes/dsm.yaml")
OSM = str(REPO / "recipes/osm.yaml")
LABEL = str(REPO / "recipes/label_map.yaml")
PLANE = np.c_[np.random.default_rng(1).uniform(0, 80, (5000, 2)), np.zeros(5000)]

# (id, recipe, mutation, fragment expected in the one-line error)
CASES: list[tuple[str, str, Mutation, str]] = [
    ("missing-scene-yaml", DSM, lambda s, t: (s / "scene.yaml").unlink() or [], "scene manifest not found"),
    ("scene-unknown-key", DSM, lambda s, t: _manifest(s, lambda x: x + "colour: red\n") or [], "unknown key 'colour'"),
    ("scene-wrong-type", DSM, lambda s, t: _manifest(s, lambda x: x.replace("crs: EPSG:32617", "crs: 32617")) or [],
     "'crs' must be a string"),
    ("scene-geographic-crs", DSM, lambda s, t: _manifest(s, lambda x: x.replace("crs: EPSG:32617", "crs: EPSG:4326")) or [],
     "is not projected: its axes are in degree, not metres; use a metric projected CRS"),
    ("scene-names-missing-file", DSM, lambda s, t: (s / "street/cloud.ply").unlink() or [], "cloud.ply: file named by street.cloud"),
    ("ply-empty", DSM, lambda s, t: _replace(s / "street/cloud.ply", b"") or [], "cloud.ply: file is empty"),
    ("ply-truncated", DSM, lambda s, t: _replace(s / "street/cloud.ply", (s / "street/cloud.ply").read_bytes()[:5000]) or [],
     "cloud.ply: PLY is truncated"),
    ("ply-garbage", DSM, lambda s, t: _replace(s / "street/cloud.ply", os.urandom(4000)) or [], "cloud.ply: not a PLY file"),
    ("las-corrupt", DSM, lambda s, t: _las(s, "las", "garbage") or [], "cloud.las"),
    ("las-empty", DSM, lambda s, t: _las(s, "las", "empty") or [], "cloud.las: file is empty"),
    ("laz-truncated", DSM, lambda s, t: _las(s, "laz", "truncated") or [], "cloud.laz"),
    ("cloud-nan", DSM, lambda s, t: _cloud(s, np.array([[0, 0, 0], [np.nan, 0, 0], [1, 2, 3.0]] * 100)) or [], "NaN or Inf"),
    ("cloud-inf", DSM, lambda s, t: _cloud(s, np.array([[0, 0, 0], [np.inf, 0, 0], [1, 2, 3.0]] * 100)) or [], "NaN or Inf"),
    ("cloud-single-point", DSM, lambda s, t: _cloud(s, np.array([[1.0, 2.0, 3.0]])) or [], "steps.street"),
    ("cloud-one-plane", DSM, lambda s, t: _cloud(s, PLANE) or [], "found no building segment"),
    ("cloud-collinear", DSM, lambda s, t: _cloud(s, np.c_[np.arange(3000.0), np.zeros(3000), np.zeros(3000)]) or [],
     "steps.street"),
    ("geotiff-no-crs", DSM, lambda s, t: _geotiff_no_crs(s) or [], "dsm.tif: GeoTIFF has no CRS"),
    # a raster in another CRS is reprojected, one on another grid resampled: unless it cannot be right
    ("geotiff-wrong-crs", DSM, lambda s, t: _rewrite_raster(s, "dsm.tif", crs="EPSG:32633") or [],
     "dsm.tif: in EPSG:32633 it lies at lon 13.00..13.00"),
    ("ortho-off-the-dsm-grid", DSM, lambda s, t: _rewrite_raster(s, "ortho.tif", shift_px=100000) or [],
     "ortho.tif: does not overlap the scene grid, which dsm.tif defines"),
    ("ortho-3-bands", DSM, lambda s, t: _rewrite_raster(s, "ortho.tif", bands=3) or [], "ortho.tif"),
    ("footprints-projected-no-crs", OSM, lambda s, t: _projected_footprints(s) or [], "footprints.geojson"),
    ("footprints-invalid-json", OSM, lambda s, t: _footprints(s, "{not json") or [], "footprints.geojson: invalid GeoJSON"),
    ("footprints-all-invalid", OSM, lambda s, t: _edit_footprints(s, _collapsed_ring) or [], "footprints.geojson"),
    ("footprints-empty", OSM, lambda s, t: _footprints(s, {"type": "FeatureCollection", "features": []}) or [],
     "footprints.geojson"),
    ("osm-no-buildings", OSM, lambda s, t: _manifest(s, lambda x: x.replace("  footprints: overview/footprints.geojson\n", ""))
     or _replace(s / "overview/map.osm", "<?xml version='1.0'?><osm version='0.6'></osm>") or [], "map.osm"),
    ("labels-no-building-class", LABEL, lambda s, t: _rewrite_raster(s, "labels.tif", fill=0) or [], "labels.tif"),
    ("colmap-missing-points", DSM, lambda s, t: _drop_points(s) or [], "missing 3D point"),
    ("colmap-missing-camera", DSM, lambda s, t: _drop_camera(s) or [], "missing camera"),
    ("images-txt-odd-lines", DSM, lambda s, t: _images_txt(s, lambda ls: ls[:-1]) or [], "odd number of lines"),
    ("recipe-unknown-stage", DSM, lambda s, t: ["-s", "steps.refine.use=refine.exhaustiv"], "did you mean 'refine.exhaustive'"),
    ("recipe-unknown-param", DSM, lambda s, t: ["-s", "steps.match.params.c3=1"], "c3: Extra inputs are not permitted"),
    ("recipe-invalid-param", DSM, lambda s, t: ["-s", "steps.graph.params.k=many"], "steps.graph (graph.knn): k:"),
    ("recipe-wrong-order", "order", lambda s, t: [], "wrong step order"),
    ("recipe-python-tag", "pytag", lambda s, t: [], "invalid YAML"),
    ("recipe-base-loop", "loop", lambda s, t: [], "base: loop"),
    ("output-exists", DSM, lambda s, t: (t / "out").mkdir() or [], "already exists (pass --overwrite"),
]

RECIPES = {
    "order": "recipe: 1\nsteps:\n  street: {use: street.region_growing}\n  overview: {use: overview.dsm_tophat}\n",
    "pytag": "recipe: 1\nname: !!python/object/apply:os.getcwd []\nsteps: {overview: {use: overview.osm}}\n",
    "loop": "recipe: 1\nbase: bad.yaml\nsteps: {overview: {use: overview.osm}}\n",
}


@pytest.fixture(scope="module")
def base_scene() -> Path:
    return synthetic_scene("tiny")


def _copy_scene(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link)
    return dst


@pytest.mark.parametrize("case_id,recipe,mutate,fragment", CASES, ids=[c[0] for c in CASES])
def test_bad_input(case_id, recipe, mutate, fragment, base_scene, tmp_path, capsys):
    scene = _copy_scene(base_scene, tmp_path / "scene")
    extra = mutate(scene, tmp_path)
    if recipe in RECIPES:
        recipe = _recipe(tmp_path, RECIPES[recipe])
    out = tmp_path / "out"
    existed = out.exists()
    code = main(["run", recipe, "--scene", str(scene), "--out", str(out), "-q", "--no-rerun", *extra])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1, err
    assert fragment in err[0], err[0]
    assert "Traceback" not in err[0]
    assert out.exists() == existed  # nothing written (an existing folder is left alone)
    assert not [p for p in tmp_path.iterdir() if ".partial" in p.name]


def test_suite_has_at_least_30_cases():
    assert len(CASES) >= 30


def test_footprints_far_from_the_route_end_unreliable_not_as_bad_input(base_scene, tmp_path, capsys):
    """Footprints ~300 m east of the route: readable input that registers nothing is a failed
    registration (exit 4, assessed and written, no registered cloud), not an exit-2 input error."""
    import json

    scene = _copy_scene(base_scene, tmp_path / "scene")
    _edit_footprints(scene, lambda r: [[x + 0.004, y] for x, y in r])
    out = tmp_path / "out"
    code = main(["run", OSM, "--scene", str(scene), "--out", str(out), "-q", "--no-rerun"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 4, err
    assert err[-1].startswith("registration unreliable:"), err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "unreliable"
    assert not list(out.glob("registered.*"))
