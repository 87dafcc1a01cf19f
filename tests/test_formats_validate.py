"""``validate`` (and ``build()``) rejects, from headers and before any step runs, the orthos the
run would reject later; ``--version``; the float32 street-cloud warning."""

from __future__ import annotations

import logging
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, synthetic_scene
from tests.test_bad_inputs import _rewrite_raster
from toolkit.cli import main

DSM = str(REPO / "recipes/dsm.yaml")


@pytest.fixture(scope="module")
def tiny() -> Path:
    return synthetic_scene("tiny")


def _copy(tiny: Path, dst: Path) -> Path:
    return Path(shutil.copytree(tiny, dst, copy_function=os.link))


def _strip_descriptions(path: Path) -> None:
    import rasterio

    with rasterio.open(path) as ds:
        data, profile = ds.read(), ds.profile
    path.unlink()
    with rasterio.open(path, "w", **profile) as ds:
        ds.write(data)


def _describe(path: Path, names: tuple[str, ...]) -> None:
    import rasterio

    with rasterio.open(path, "r+") as ds:
        for i, name in enumerate(names, 1):
            ds.set_band_description(i, name)


def _run(root: Path, tmp_path: Path, capsys, *extra: str) -> tuple[int, list[str]]:
    """``crossview run`` (quiet): a failure at build() prints one line and starts no step."""
    out = tmp_path / "out"
    code = main(["run", DSM, "--scene", str(root), "--out", str(out), "-q", "--no-rerun", *extra])
    err = capsys.readouterr().err.strip().splitlines()
    if code == 2:
        assert len(err) == 1 and "Traceback" not in err[0], err
        assert not out.exists() and not [p for p in tmp_path.iterdir() if ".partial" in p.name]
    return code, err


def test_ortho_without_band_descriptions_says_what_is_expected(tiny, tmp_path, capsys):
    root = _copy(tiny, tmp_path / "s")
    _strip_descriptions(root / "overview/ortho.tif")
    code, err = _run(root, tmp_path, capsys)
    assert code == 2
    assert "ortho.tif: cannot find the red and nir band(s) of this 4-band ortho (band descriptions: none)" in err[0]
    assert "describe its bands in the GeoTIFF (red, green, blue, nir)" in err[0]
    assert "overview.dsm_tophat params.bands" in err[0] and "use_ortho" not in err[0]


@pytest.mark.parametrize("names", [("red", "green", "blue"), ()])
def test_rgb_only_ortho_names_use_ortho_false(tiny, tmp_path, capsys, names):
    from plugins.overview_dsm_tophat import DsmTophat

    assert "use_ortho" in DsmTophat.Params.model_fields  # the parameter the message names
    root = _copy(tiny, tmp_path / "s")
    _rewrite_raster(root, "ortho.tif", bands=3)
    _describe(root / "overview/ortho.tif", names)
    code, err = _run(root, tmp_path, capsys)
    assert code == 2 and re.search(r"ortho.tif: cannot find the (red and )?nir band\(s\) of this 3-band ortho", err[0])
    assert "an RGB-only ortho has no near-infrared band for NDVI: set use_ortho: false in the params of " \
           "overview.dsm_tophat" in err[0]
    assert main(["validate", DSM, "--scene", str(root), "-s", "steps.overview.params.use_ortho=false"]) == 0


def test_ortho_bands_named_by_the_parameter_pass_validate(tiny, tmp_path, capsys):
    root = _copy(tiny, tmp_path / "s")
    _strip_descriptions(root / "overview/ortho.tif")
    ok = main(["validate", DSM, "--scene", str(root), "-s", "steps.overview.params.bands=[red,green,blue,nir]"])
    assert ok == 0, capsys.readouterr().err


def test_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0
    assert capsys.readouterr().out.strip() == f"crossview {version('crossview-toolkit')}"


def _float32_ply(path: Path, xyz: np.ndarray) -> None:
    rec = np.empty(len(xyz), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    rec["x"], rec["y"], rec["z"] = xyz.T
    with open(path, "wb") as f:
        f.write(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(xyz)}\nproperty float x\n"
                "property float y\nproperty float z\nend_header\n".encode())
        rec.tofile(f)


def test_float32_cloud_with_large_coordinates_warns_with_the_precision(tmp_path, caplog):
    from toolkit.io.cloud import read_points

    xyz = np.random.default_rng(0).uniform(0, 50, (1000, 3))
    _float32_ply(tmp_path / "near.ply", xyz)
    _float32_ply(tmp_path / "far.ply", xyz + [4.4e6, 330_000, 0])
    with caplog.at_level(logging.WARNING, logger="crossview"):
        read_points(tmp_path / "near.ply")
        assert not caplog.records  # small float32 coordinates are fine
        read_points(tmp_path / "far.ply")
    [msg] = [r.getMessage() for r in caplog.records]
    assert "far.ply: x, y, z are stored as float32 with coordinates up to 4400050 m" in msg
    assert "500 mm steps" in msg


def test_float32_street_cloud_warning_is_shown_by_the_run(tiny, tmp_path, capsys):
    from toolkit.io.cloud import read_points

    root = _copy(tiny, tmp_path / "s")
    xyz = read_points(tiny / "street/cloud.ply")[::10] + [0, 1.5e5, 0]
    (root / "street/cloud.ply").unlink()
    _float32_ply(root / "street/cloud.ply", xyz)
    recipe = tmp_path / "street.yaml"
    recipe.write_text("recipe: 1\nname: street\nsteps:\n  street: {use: street.region_growing}\n")
    main(["run", str(recipe), "--scene", str(root), "--out", str(tmp_path / "out"), "--no-rerun"])
    warnings = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("crossview: warning:")]
    assert len(warnings) == 1, warnings
    assert "street/cloud.ply: x, y, z are stored as float32" in warnings[0] and "15.625 mm steps" in warnings[0]
