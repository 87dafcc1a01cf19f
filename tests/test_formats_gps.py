"""street/gps.csv in our layout or exiftool's, image names with folder prefixes matched by file name,
and ``crossview validate`` reporting how many fixes match images (none: exit code 2)."""

from __future__ import annotations

import csv
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import REPO, synthetic_scene
from toolkit.capture import StreetCapture
from toolkit.cli import main
from toolkit.errors import SceneError
from toolkit.io.gps import match_images, read_gps_csv
from toolkit.scene import load_scene
from toolkit.types import StreetSegments

DSM = str(REPO / "recipes/dsm.yaml")


@pytest.fixture(scope="module")
def tiny() -> Path:
    return synthetic_scene("tiny")


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _write_exiftool(path: Path, rows: list[dict], prefix: str = "images/") -> None:
    """What ``exiftool -csv -n -GPSLatitude -GPSLongitude -GPSHPositioningError images/`` writes."""
    lines = ["SourceFile,GPSLatitude,GPSLongitude,GPSHPositioningError"]
    lines += [f"{prefix}{r['image_name']},{r['lat']},{r['lon']},{r['sigma_m']}" for r in rows]
    path.write_text("\n".join(lines) + "\n")


def _scene_with_gps(tiny: Path, dst: Path, text: str) -> Path:
    root = Path(shutil.copytree(tiny, dst, copy_function=os.link))
    (root / "street/gps.csv").unlink()
    (root / "street/gps.csv").write_text(text)
    return root


def test_exiftool_layout_with_folder_prefix_reads_as_ours(tiny, tmp_path):
    ours = read_gps_csv(tiny / "street/gps.csv")
    _write_exiftool(tmp_path / "exif.csv", _rows(tiny / "street/gps.csv"))
    exif = read_gps_csv(tmp_path / "exif.csv")
    assert np.array_equal(exif.lonlat, ours.lonlat) and np.array_equal(exif.sigma_m, ours.sigma_m)
    assert exif.names[0] == "images/frame_000000.jpg"
    images = ours.names
    assert np.array_equal(match_images(exif.names, images), np.arange(len(images)))


def test_degrees_minutes_seconds_and_hemisphere_references(tmp_path):
    (tmp_path / "dms.csv").write_text(
        "SourceFile,GPSLatitude,GPSLatitudeRef,GPSLongitude,GPSLongitudeRef\n"
        "a.jpg,\"39 deg 58' 1.38\"\" N\",North,\"82 deg 59' 48.75\"\" W\",West\n"
        "b.jpg,33.8688,South,151.2093,East\n"
        "c.jpg,12.5 N,,-70.25,\n")
    fixes = read_gps_csv(tmp_path / "dms.csv")
    assert fixes.lonlat[0] == pytest.approx([-(82 + 59 / 60 + 48.75 / 3600), 39 + 58 / 60 + 1.38 / 3600])
    assert fixes.lonlat[1] == pytest.approx([151.2093, -33.8688])
    assert fixes.lonlat[2] == pytest.approx([-70.25, 12.5]) and np.isnan(fixes.sigma_m).all()


def test_unknown_layout_names_the_expected_columns(tmp_path):
    (tmp_path / "g.csv").write_text("photo,x,y\na.jpg,1,2\n")
    with pytest.raises(SceneError, match=r"g.csv: expected columns image_name,lon,lat\[,sigma_m\] .*SourceFile,"
                                         r"GPSLatitude,GPSLongitude.*got \['photo', 'x', 'y'\]"):
        read_gps_csv(tmp_path / "g.csv")
    (tmp_path / "h.csv").write_text("image_name,lon,lat\na.jpg,500000,4400000\n")
    with pytest.raises(SceneError, match="h.csv: fix 'a.jpg' is not WGS 84 lon/lat"):
        read_gps_csv(tmp_path / "h.csv")


def test_names_match_exactly_else_by_unique_file_name():
    images = ("seq1/f1.jpg", "seq2/f1.jpg", "seq1/f2.jpg", "f3.jpg")
    fixes = ["seq2/f1.jpg", "f1.jpg", "other/f2.jpg", "C:\\photos\\f3.jpg", "f4.jpg"]
    assert match_images(fixes, images).tolist() == [1, -1, 2, 3, -1]  # f1.jpg alone is ambiguous


def _street(model) -> StreetSegments:
    """Identity levelling, three segment centroids at camera centres."""
    cent = model.centres[[0, len(model.centres) // 2, -1], :2]
    n = len(cent)
    return StreetSegments(np.zeros(3), np.eye(3), np.zeros(0, np.int32), np.zeros(0, np.int32),
                          np.arange(n), tuple(np.zeros((1, 2)) for _ in range(n)), cent, np.ones(n),
                          np.zeros(n), np.tile([0.0, 0, 1], (n, 1)))


def test_gps_prior_is_the_same_from_exiftool_fixes(tiny, tmp_path):
    import dataclasses

    from toolkit.matching.gps import gps_prior
    from toolkit.scene import load_sparse

    scene = load_scene(tiny)
    street = _street(load_sparse(scene))
    ref = gps_prior(StreetCapture(scene), street)
    _write_exiftool(tmp_path / "exif.csv", _rows(tiny / "street/gps.csv"))
    other = dataclasses.replace(scene, files=dataclasses.replace(scene.files, gps=tmp_path / "exif.csv"))
    got = gps_prior(StreetCapture(other), street)
    assert got.n_fixes == ref.n_fixes == 201
    assert np.array_equal(got.position, ref.position) and np.array_equal(got.angle, ref.angle)


def test_validate_reports_matching_fixes(tiny, tmp_path, capsys):
    rows = _rows(tiny / "street/gps.csv")
    _write_exiftool(tmp_path / "exif.csv", rows[:150] + [dict(rows[0], image_name="not_an_image.jpg")])
    root = _scene_with_gps(tiny, tmp_path / "s", (tmp_path / "exif.csv").read_text())
    assert main(["validate", DSM, "--scene", str(root)]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert out[-1] == "gps: 150 of 151 fixes match images"


def test_no_fix_matching_an_image_is_a_one_line_error(tiny, tmp_path, capsys):
    rows = [dict(r, image_name=f"IMG_{k:04d}.JPG") for k, r in enumerate(_rows(tiny / "street/gps.csv"))]
    text = "image_name,lon,lat,sigma_m\n" + "".join(f"{r['image_name']},{r['lon']},{r['lat']},3\n" for r in rows)
    root = _scene_with_gps(tiny, tmp_path / "s", text)
    out = tmp_path / "out"
    code = main(["run", DSM, "--scene", str(root), "--out", str(out), "-q", "--no-rerun"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "gps.csv: none of its 201 fixes names an image of the COLMAP model" in err[0]
    assert not out.exists()


def test_other_gps_layout_is_a_one_line_error_at_validate(tiny, tmp_path, capsys):
    root = _scene_with_gps(tiny, tmp_path / "s", "time,easting,northing\n0,1,2\n")
    assert main(["validate", DSM, "--scene", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gps.csv: expected columns image_name,lon,lat" in err[0]
