"""Terrain model (overview.dem): absolute heights for 2D-only sources, any CRS, partial coverage;
without any height source the heights are relative (street ground at 0 m)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from toolkit.cli import main

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "osm.yaml"


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    from toolkit.synth.generate import generate

    root = tmp_path_factory.mktemp("dem") / "tiny"
    generate("tiny", 0, root)
    return root


def _scene_2d(root: Path, name: str, dem: str | None) -> Path:
    """Footprints and street only (no DSM, ortho, label map or over-view cloud), no GPS."""
    m = yaml.safe_load((root / "scene.yaml").read_text())
    m["overview"] = {k: v for k, v in m["overview"].items() if k in ("footprints", "osm")}
    if dem:
        m["overview"]["dem"] = dem
    m["street"] = {k: v for k, v in m["street"].items() if k != "gps"}
    m.pop("synth", None)
    path = root / name
    path.write_text(yaml.safe_dump(m, sort_keys=False))
    return path


def _reprojected_dem(root: Path, crs: str, keep_west_half: bool = False) -> str:
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    with rasterio.open(root / "overview/dem.tif") as src:
        z = src.read(1)
        if keep_west_half:
            z = z.copy()
            z[:, z.shape[1] // 2:] = -9999.0
        tr, w, h = calculate_default_transform(src.crs, crs, src.width, src.height, *src.bounds)
        out = np.full((h, w), -9999.0, np.float32)
        reproject(z, out, src_transform=src.transform, src_crs=src.crs, src_nodata=-9999.0, dst_transform=tr,
                  dst_crs=crs, dst_nodata=-9999.0, resampling=Resampling.bilinear)
    name = f"overview/dem-{crs.replace(':', '')}{'-half' if keep_west_half else ''}.tif"
    with rasterio.open(root / name, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs=crs,
                       transform=tr, nodata=-9999.0) as dst:
        dst.write(out, 1)
    return name


def _run(scene: Path, out: Path) -> dict:
    assert main(["run", str(RECIPE), "--scene", str(scene), "--out", str(out), "--no-rerun", "-q"]) == 0
    return json.loads((out / "metrics.json").read_text())


def test_the_generator_writes_a_coarse_bare_earth_dem(tiny):
    import rasterio

    assert yaml.safe_load((tiny / "scene.yaml").read_text())["overview"]["dem"] == "overview/dem.tif"
    with rasterio.open(tiny / "overview/dem.tif") as dem, rasterio.open(tiny / "overview/dsm.tif") as dsm:
        assert dem.res[0] >= 5 * dsm.res[0]
        assert abs(np.median(dem.read(1)) - np.percentile(dsm.read(1), 10)) < 3.0   # terrain, not roofs


def test_footprints_with_a_dem_in_wgs84_give_absolute_heights(tiny, tmp_path):
    m = _run(_scene_2d(tiny, "scene-dem.yaml", _reprojected_dem(tiny, "EPSG:4326")), tmp_path / "dem")
    assert m["heights"] == "absolute"
    assert m["truth"]["error_3d"]["p95_m"] <= 1.5
    assert not [w for w in m["warnings"] if "cover" in w or "ground height" in w]


def test_without_a_height_source_heights_are_relative_with_the_ground_at_zero(tiny, tmp_path):
    m = _run(_scene_2d(tiny, "scene-2d.yaml", None), tmp_path / "none")
    assert m["heights"] == "relative"
    assert any("heights are relative" in w for w in m["warnings"])
    import laspy

    las = laspy.read(tmp_path / "none" / "registered.laz")
    ground = np.load(tiny / "truth/street_labels.npy") == -1
    assert abs(float(np.median(np.asarray(las.z)[ground]))) < 0.5


def test_a_dem_covering_part_of_the_route_warns_with_the_uncovered_share(tiny, tmp_path):
    crs = yaml.safe_load((tiny / "scene.yaml").read_text())["crs"]
    m = _run(_scene_2d(tiny, "scene-half.yaml", _reprojected_dem(tiny, crs, keep_west_half=True)),
             tmp_path / "half")
    warned = [w for w in m["warnings"] if "terrain model does not cover" in w]
    assert len(warned) == 1 and "%" in warned[0]
    assert m["heights"] == "absolute" and m["truth"]["error_3d"]["p95_m"] <= 2.0
