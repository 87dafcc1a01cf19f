"""DSM, ortho and label map in any CRS and on any grid: reprojected onto the scene grid
(rasterio.warp.reproject: DSM and ortho bilinear, labels nearest, nodata kept) with a one-line note;
rasters already on the scene grid are read exactly as they are."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, synthetic_scene
from toolkit.cli import main
from toolkit.io.raster import read_raster
from toolkit.observe import NullObserver
from toolkit.scene import load_raster, load_scene, scene_grid

FEET_CRS = "EPSG:3735"  # NAD83 / Ohio South (ftUS): the tiny scene lies in Ohio
FT_PER_M = 1 / 0.30480060960121924


@pytest.fixture(scope="module")
def tiny() -> Path:
    return synthetic_scene("tiny")


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link)
    return dst


def _warp_file(path: Path, dst_crs: str, resolution: float, resampling: str) -> None:
    """Rewrite a GeoTIFF in ``dst_crs`` at ``resolution`` (its units), keeping nodata and band names."""
    import rasterio
    from rasterio.warp import Resampling, calculate_default_transform, reproject

    with rasterio.open(path) as ds:
        data, profile, desc, nodata = ds.read(), ds.profile, ds.descriptions, ds.nodata
        transform, width, height = calculate_default_transform(ds.crs, dst_crs, ds.width, ds.height,
                                                               *ds.bounds, resolution=resolution)
        out = np.full((ds.count, height, width), 0 if nodata is None else nodata, dtype=data.dtype)
        reproject(data, out, src_transform=ds.transform, src_crs=ds.crs, dst_transform=transform,
                  dst_crs=dst_crs, src_nodata=nodata, dst_nodata=nodata, resampling=getattr(Resampling, resampling))
    profile.update(crs=dst_crs, transform=transform, width=width, height=height)
    _write(path, out, profile, desc)


def _upsample_file(path: Path, factor: int) -> None:
    """Rewrite a GeoTIFF at 1/factor of its pixel size (each pixel repeated factor × factor times)."""
    import rasterio
    from rasterio.transform import Affine

    with rasterio.open(path) as ds:
        data, profile, desc = ds.read(), ds.profile, ds.descriptions
    t = profile["transform"]
    fine = data.repeat(factor, axis=1).repeat(factor, axis=2)
    profile.update(transform=Affine(t.a / factor, t.b, t.c, t.d, t.e / factor, t.f),
                   width=fine.shape[2], height=fine.shape[1], blockxsize=256, blockysize=256, tiled=True)
    _write(path, fine, profile, desc)


def _write(path: Path, data: np.ndarray, profile: dict, desc) -> None:
    import rasterio

    path.unlink()
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(data)
        for i, d in enumerate(desc, 1):
            if d:
                ds.set_band_description(i, d)


def _notes(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.startswith("crossview") and "resampled" in r.getMessage()]


def test_rasters_on_the_scene_grid_are_read_as_they_are(tiny, caplog):
    scene = load_scene(tiny)
    with caplog.at_level(logging.INFO, logger="crossview"):
        for key in ("dsm", "ortho", "labels"):
            got, direct = load_raster(scene, key), read_raster(getattr(scene.files, key))
            assert got.grid == direct.grid == scene_grid(scene).grid
            assert got.data.dtype == direct.data.dtype and np.array_equal(got.data, direct.data)
            assert np.array_equal(got.nodata_mask, direct.nodata_mask) and got.band_names == direct.band_names
    assert scene_grid(scene).source == "dsm" and not _notes(caplog)


def test_fine_ortho_is_resampled_onto_the_dsm_grid(tiny, tmp_path, caplog):
    """A 0.25 m ortho beside the 0.5 m DSM: resampled (GDAL's bilinear kernel, widened when
    downsampling) it is the 0.5 m ortho it was made from, smoothed a little."""
    from toolkit.recipe import load_recipe
    from toolkit.runner import build

    root = _copy(tiny, tmp_path / "s")
    _upsample_file(root / "overview/ortho.tif", 2)
    build(load_recipe(REPO / "recipes/dsm.yaml"), scene=root)  # validate accepts it
    scene = load_scene(root)
    with caplog.at_level(logging.INFO, logger="crossview"):
        ortho = load_raster(scene, "ortho")
    original = read_raster(tiny / "overview/ortho.tif")
    assert ortho.grid == original.grid and ortho.band_names == original.band_names
    a, b = ortho.data[:, 1:-1, 1:-1].astype(float), original.data[:, 1:-1, 1:-1].astype(float)
    assert np.abs(a - b).mean() < 6 and np.corrcoef(a.ravel(), b.ravel())[0, 1] > 0.9
    [note] = _notes(caplog)
    assert "ortho.tif" in note and "0.25m" in note and "bilinear" in note and "0.5m in EPSG:32617" in note


@pytest.fixture(scope="module")
def feet_dsm_scene(tiny, tmp_path_factory) -> Path:
    """tiny with its DSM in US survey feet (0.5 m pixels), ortho and labels left in the scene CRS."""
    root = _copy(tiny, tmp_path_factory.mktemp("feet") / "s")
    _warp_file(root / "overview/dsm.tif", FEET_CRS, 0.5 * FT_PER_M, "bilinear")
    return root


def test_dsm_in_another_crs_defines_the_grid_at_its_own_gsd(feet_dsm_scene, tiny):
    scene = load_scene(feet_dsm_scene)
    found = scene_grid(scene)
    assert found.source == "dsm" and found.grid.crs == "EPSG:32617"
    assert found.grid.gsd_m == pytest.approx(0.5, abs=1e-9)
    dsm = load_raster(scene, "dsm")
    assert dsm.grid == found.grid and dsm.data.dtype == np.float32
    # the heights, twice resampled, agree with the original DSM at the same places
    original = read_raster(tiny / "overview/dsm.tif")
    rows, cols = np.nonzero(~dsm.nodata_mask)
    xy = dsm.grid.pixel_to_world(rows, cols)
    rc = np.round(original.grid.world_to_pixel(xy)).astype(int)
    inside = (rc >= 0).all(axis=1) & (rc[:, 0] < original.grid.height) & (rc[:, 1] < original.grid.width)
    ref_valid = ~original.nodata_mask[rc[inside, 0], rc[inside, 1]]
    diff = dsm.data[0, rows, cols][inside][ref_valid] - original.data[0, rc[inside, 0], rc[inside, 1]][ref_valid]
    assert np.median(np.abs(diff)) < 0.2 and inside.mean() > 0.97  # DSM noise is 0.25 m
    assert dsm.nodata_mask.any()  # the rotated extent leaves uncovered corners, masked
    assert dsm.data[0][~dsm.nodata_mask].min() > 100  # no -9999 bled into the heights


def test_labels_and_ortho_follow_a_reprojected_dsm(feet_dsm_scene, tiny):
    scene = load_scene(feet_dsm_scene)
    grid = scene_grid(scene).grid
    labels, ortho = load_raster(scene, "labels"), load_raster(scene, "ortho")
    assert labels.grid == ortho.grid == grid
    original = read_raster(tiny / "overview/labels.tif")
    assert set(np.unique(labels.data[0][~labels.nodata_mask])) <= set(np.unique(original.data))  # nearest
    assert labels.data.dtype == np.uint8 and ortho.data.shape[0] == 4


def test_segments_from_a_reprojected_dsm_match_the_original(feet_dsm_scene, tiny):
    from plugins.overview_dsm_tophat import DsmTophat

    ref = DsmTophat()(load_scene(tiny), NullObserver())
    got = DsmTophat()(load_scene(feet_dsm_scene), NullObserver())
    assert abs(len(got) - len(ref)) <= max(2, 0.1 * len(ref))
    d = np.linalg.norm(ref.centroids[:, None] - got.centroids[None], axis=-1).min(axis=1)
    assert np.median(d) < 0.5


def _reproject(raster, grid):
    """``raster``'s first band put onto ``grid`` by rasterio alone (bilinear; NaN where it has no data)."""
    from rasterio.transform import Affine
    from rasterio.warp import Resampling, reproject

    out = np.full((grid.height, grid.width), np.nan, np.float64)
    reproject(np.where(raster.nodata_mask, np.nan, raster.data[0].astype(np.float64)), out,
              src_transform=Affine(*raster.grid.transform), src_crs=raster.grid.crs, src_nodata=np.nan,
              dst_transform=Affine(*grid.transform), dst_crs=grid.crs, dst_nodata=np.nan,
              resampling=Resampling.bilinear)
    return out


def _shift_px(reference: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """(columns, rows) by which ``moved`` is ``reference`` displaced, from a least-squares fit of their
    difference to the height gradients (first order), over pixels two away from any NaN in either."""
    from scipy import ndimage as ndi

    inner = ndi.binary_erosion(np.isfinite(reference) & np.isfinite(moved), iterations=2)
    d_row, d_col = np.gradient(np.where(np.isfinite(reference), reference, 0.0))
    design = np.column_stack([d_col[inner], d_row[inner]])
    return -np.linalg.lstsq(design, (moved - reference)[inner], rcond=None)[0]


def test_the_shift_estimate_sees_a_quarter_pixel(tiny):
    from dataclasses import replace

    original = read_raster(tiny / "overview/dsm.tif")
    a, b, c, d, e, f = original.grid.transform
    moved = replace(original, grid=replace(original.grid, transform=(a, b, c + 0.25 * a, d, e, f + 0.1 * e)))
    shift = _shift_px(_reproject(original, original.grid), _reproject(moved, original.grid))
    assert shift == pytest.approx([0.25, 0.1], abs=0.01)


@pytest.mark.parametrize("crs, resolution", [("EPSG:26917", 0.6), (FEET_CRS, 0.5 * FT_PER_M)])
def test_a_dsm_in_another_crs_keeps_its_place_to_a_hundredth_of_a_pixel(tiny, tmp_path, crs, resolution):
    """No half-pixel or grid-origin shift on the way in: the DSM as the scene reads it (written in
    another CRS, reprojected onto the scene grid) against the original put straight onto that grid."""
    root = _copy(tiny, tmp_path / "s")
    _warp_file(root / "overview/dsm.tif", crs, resolution, "bilinear")
    dsm = load_raster(load_scene(root), "dsm")
    direct = _reproject(read_raster(tiny / "overview/dsm.tif"), dsm.grid)
    shift = _shift_px(direct, np.where(dsm.nodata_mask, np.nan, dsm.data[0].astype(np.float64)))
    assert np.abs(shift).max() < 0.01, shift


def test_without_a_dsm_the_label_map_defines_the_grid(tiny, tmp_path):
    root = _copy(tiny, tmp_path / "s")
    manifest = root / "scene.yaml"
    text = manifest.read_text().replace("  dsm: overview/dsm.tif\n", "")
    manifest.unlink()
    manifest.write_text(text)
    _warp_file(root / "overview/labels.tif", FEET_CRS, 1.0 * FT_PER_M, "nearest")
    scene = load_scene(root)
    found = scene_grid(scene)
    assert found.source == "labels" and found.grid.gsd_m == pytest.approx(1.0) and found.grid.crs == "EPSG:32617"
    assert load_raster(scene, "ortho").grid == load_raster(scene, "labels").grid == found.grid


def test_dsm_nodata_stays_nodata(tiny, tmp_path):
    import rasterio

    root = _copy(tiny, tmp_path / "s")
    path = root / "overview/dsm.tif"
    with rasterio.open(path) as ds:
        data, profile = ds.read(), ds.profile
    data[0, 200:260, 300:380] = profile["nodata"]
    _write(path, data, profile, ())
    _warp_file(path, FEET_CRS, 0.5 * FT_PER_M, "bilinear")
    dsm = load_raster(load_scene(root), "dsm")
    hole = dsm.grid.world_to_pixel(read_raster(tiny / "overview/dsm.tif").grid.pixel_to_world(230, 340))
    r, c = np.round(hole).astype(int)
    assert dsm.nodata_mask[r - 20:r + 20, c - 30:c + 30].all()
    assert dsm.data[0][~dsm.nodata_mask].min() > 100


def test_cli_run_shows_the_note_unless_quiet(tiny, tmp_path, capsys):
    root = _copy(tiny, tmp_path / "s")
    _upsample_file(root / "overview/ortho.tif", 2)
    recipe = tmp_path / "ov.yaml"
    recipe.write_text("recipe: 1\nname: ov\nsteps:\n  overview: {use: overview.dsm_tophat}\n")
    args = ["run", str(recipe), "--scene", str(root), "--no-rerun", "--out"]
    assert main(args + [str(tmp_path / "a")]) == 0
    notes = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("crossview: note:")]
    assert len(notes) == 1 and "ortho.tif" in notes[0] and "resampled (bilinear) onto the scene grid" in notes[0]
    from toolkit.scene import _raster

    _raster.cache_clear()  # the note is given when the file is read
    assert main(args + [str(tmp_path / "b"), "-q"]) == 0
    assert "note" not in capsys.readouterr().err


def test_the_note_reaches_run_log_and_metrics_in_every_run(tiny, tmp_path):
    """The reader's note is in run.log and metrics.json, and the same in a second run in the process
    (the raster is then cached: the note is replayed, metrics.json stays the same bytes)."""
    import json

    root = _copy(tiny, tmp_path / "s")
    _upsample_file(root / "overview/ortho.tif", 2)
    recipe = tmp_path / "ov.yaml"
    recipe.write_text("recipe: 1\nname: ov\nsteps:\n  overview: {use: overview.dsm_tophat}\n")
    for out in ("a", "b"):
        assert main(["run", str(recipe), "--scene", str(root), "--no-rerun", "-q", "--out", str(tmp_path / out)]) == 0
    notes = json.loads((tmp_path / "a/metrics.json").read_text())["input_notes"]
    assert len(notes) == 1 and "ortho.tif" in notes[0] and "resampled (bilinear)" in notes[0]
    assert (tmp_path / "a/metrics.json").read_bytes() == (tmp_path / "b/metrics.json").read_bytes()
    assert f"note: {notes[0]}" in (tmp_path / "b/run.log").read_text().splitlines()
