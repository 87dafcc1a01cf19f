"""The scene CRS must be projected with metre axes (pyproj axis_info); otherwise one line that names
the unit and a metric CRS to use instead, exit code 2, no output folder."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.conftest import REPO
from toolkit.cli import main
from toolkit.errors import SceneError
from toolkit.io.crs import check_metric_crs


@pytest.mark.parametrize("crs, fragments", [
    ("EPSG:6549", ("US survey foot", "not metres", "use its metre twin EPSG:6548 (NAD83(2011) / Ohio North)")),
    ("EPSG:2263", ("US survey foot", "use its metre twin EPSG:32118")),
    ("ESRI:102718", ("US survey foot", "UTM zone of its area, EPSG:32618")),  # no metre twin by name
    ("EPSG:4326", ("is not projected", "degree", "such as the local UTM zone")),
    ("EPSG:4978", ("is not projected (a Geocentric CRS)", "local UTM zone")),
    ("EPSG:6549+6360", ("is not metric", "US survey foot", "EPSG:6548")),  # compound: its horizontal part
])
def test_non_metric_scene_crs_is_refused_with_a_metric_suggestion(crs, fragments):
    with pytest.raises(SceneError) as err:
        check_metric_crs("scene.yaml", crs)
    msg = str(err.value)
    assert msg.startswith(f"scene.yaml: CRS {crs} ") and "\n" not in msg
    for fragment in fragments:
        assert fragment in msg, msg


@pytest.mark.parametrize("crs", ["EPSG:32617", "EPSG:2154", "EPSG:27700", "EPSG:2154+5720", "EPSG:6548"])
def test_metric_projected_crs_is_accepted(crs):
    check_metric_crs("scene.yaml", crs)


def test_cli_refuses_a_feet_scene_in_one_line(mini_scene: Path, tmp_path, capsys):
    manifest = mini_scene / "scene.yaml"
    manifest.write_text(manifest.read_text().replace("crs: EPSG:32617", "crs: EPSG:6549"))
    out = tmp_path / "out"
    code = main(["run", str(REPO / "recipes/dsm.yaml"), "--scene", str(mini_scene), "--out", str(out), "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "scene.yaml: CRS EPSG:6549" in err[0] and "US survey foot" in err[0] and "EPSG:6548" in err[0]
    assert not out.exists()
