"""Unknown street scale (toolkit.street_scale): GPS estimate, the matching's estimate, a given number."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from toolkit.cli import main

RECIPE = Path(__file__).resolve().parents[1] / "recipes" / "dsm.yaml"


@pytest.fixture(scope="module")
def scaled_scenes(tmp_path_factory):
    """tiny seed 0 with its street frame at scale 1, 0.25 and 4 (truth unchanged)."""
    from toolkit.synth.generate import generate

    root = tmp_path_factory.mktemp("scaled")
    out = {}
    for s in (1.0, 0.25, 4.0):
        out[s] = root / f"tiny-{s:g}"
        generate("tiny", 0, out[s], street_scale=s)
    return out


def _run(scene: Path, out: Path, *extra: str) -> tuple[int, dict]:
    code = main(["run", str(RECIPE), "--scene", str(scene), "--out", str(out), "--no-rerun", "-q", *extra])
    return code, json.loads((out / "metrics.json").read_text())


def _without_gps(scene: Path) -> Path:
    text = (scene / "scene.yaml").read_text()
    path = scene / "scene-nogps.yaml"
    path.write_text("\n".join(line for line in text.splitlines() if "gps:" not in line) + "\n")
    return path


def test_synth_scales_the_street_frame_and_not_the_truth(scaled_scenes):
    from toolkit.io.cloud import read_points

    a, b = (read_points(scaled_scenes[s] / "street/cloud.ply") for s in (1.0, 4.0))
    assert np.allclose(b, 4.0 * a, rtol=1e-6, atol=1e-3)
    ta, tb = (np.load(scaled_scenes[s] / "truth/street_points.npy") for s in (1.0, 4.0))
    assert np.array_equal(ta, tb)


@pytest.mark.parametrize("scale", [0.25, 4.0])
def test_gps_estimates_the_scale_and_the_run_matches_the_metric_one(scaled_scenes, tmp_path, scale):
    code1, m1 = _run(scaled_scenes[1.0], tmp_path / "one")
    code, m = _run(scaled_scenes[scale], tmp_path / "scaled")
    assert code == code1 == 0 and m["status"] == "ok"
    est = m["street_scale"]
    assert est["source"] == "gps" and abs(est["value"] / (scale * m1["street_scale"]["gps_estimate"]) - 1) < 0.01
    assert m1["street_scale"]["value"] == 1.0      # an estimate within 5 % of 1 is taken as metric
    # the drift's mean scale is part of the estimate: within 1.5 % of the generator's factor
    assert abs(est["value"] / scale - 1) < 0.015
    h1, h = m1["truth"]["horizontal"]["median_m"], m["truth"]["horizontal"]["median_m"]
    assert abs(h - h1) <= max(0.1 * h1, 0.05), (h, h1)
    from toolkit.warp.store import load_warp
    from toolkit.io.cloud import read_points
    from toolkit.io.attributes import open_cloud

    warp = load_warp(tmp_path / "scaled").warp
    raw = read_points(scaled_scenes[scale] / "street/cloud.ply")[:5000]
    carriers, dist = warp.carriers(raw)
    moved = warp.maps(raw, carriers).apply(raw)
    reg = open_cloud(tmp_path / "scaled" / "registered.ply")
    first = next(iter(reg.chunks(5000))).xyz
    assert dist.max() < 1e-3 and np.abs(moved - first).max() < 0.01


def test_a_given_scale_is_used_and_reported(scaled_scenes, tmp_path):
    code, m = _run(_without_gps(scaled_scenes[0.25]), tmp_path / "given", "-s", "street_scale=0.25")
    assert code == 0 and m["street_scale"] == {"value": 0.25, "source": "recipe"}
    assert m["truth"]["horizontal"]["median_m"] < 0.5


@pytest.fixture(scope="module")
def low_cameras(tmp_path_factory):
    """tiny seed 0 at scale 4 with its cameras 1.4 m up: the first guess (cameras 2 m up) is 30 % off."""
    from toolkit.synth.generate import generate

    root = tmp_path_factory.mktemp("low") / "tiny-4-low"
    generate("tiny", 0, root, street_scale=4.0, camera_height_m=1.4)
    return root


@pytest.mark.parametrize("scale", [0.25, 4.0])
def test_without_gps_the_matching_estimates_the_scale(scaled_scenes, tmp_path, scale):
    code1, m1 = _run(_without_gps(scaled_scenes[1.0]), tmp_path / "one")
    code, m = _run(_without_gps(scaled_scenes[scale]), tmp_path / "scaled")
    assert code == code1 == 0 and m["status"] == "ok"
    est, est1 = m["street_scale"], m1["street_scale"]
    assert est["source"] == est1["source"] == "matching" and est1["value"] == 1.0
    assert "tries" not in m and "tries" not in m1  # ok at once: run once
    # the same scene's estimate at scale 1 carries the route's mean drift: compare with it
    assert abs(est["matching_estimate"] / (scale * est1["matching_estimate"]) - 1) < 0.01
    h1, h = m1["truth"]["horizontal"]["median_m"], m["truth"]["horizontal"]["median_m"]
    assert abs(h - h1) <= max(0.1 * h1, 0.05), (h, h1)


def test_a_wrong_first_guess_is_corrected_by_a_second_street_pass(low_cameras, tmp_path):
    code, m = _run(_without_gps(low_cameras), tmp_path / "low")
    est = m["street_scale"]
    assert code == 0 and m["status"] == "ok"
    assert abs(est["matching"]["first_guess"] / 4.0 - 0.7) < 0.02       # cameras at 1.4 m, guessed 2 m
    assert est["matching"]["passes"] == 2 and abs(est["matching_estimate"] / 4.0 - 1) < 0.015
    assert m["truth"]["horizontal"]["median_m"] < 0.3
    timings = json.loads((tmp_path / "low" / "timings.json").read_text())
    assert timings["scale"] > 0


def test_an_unreliable_run_at_the_scans_scale_runs_again_at_the_first_guess(scaled_scenes, tmp_path, monkeypatch):
    """The façades' scan only proposes a scale: a registration it leaves unreliable is run again at
    the cameras' height first guess, kept when ok (here the scan is made to propose 0.6 × the guess)."""
    from dataclasses import replace

    import toolkit.runner as runner

    def misled(scale, *args, **kwargs):
        if scale.matching.get("passes", 0) == 0:   # the first check: a second street pass at 0.6 ×
            return replace(scale, value=0.6 * scale.value, matching={**scale.matching, "passes": 1}, settled=False)
        return replace(scale, settled=True)

    monkeypatch.setattr(runner, "scale_from_matching", misled)
    code, m = _run(_without_gps(scaled_scenes[1.0]), tmp_path / "misled")
    assert [(t["scale_from"], t["street_scale"], t["status"]) for t in m["tries"]] == [
        ("run", 0.6, "unreliable"), ("first guess", 1.0, "ok")]
    assert code == 0 and m["status"] == "ok" and m["street_scale"]["value"] == 1.0
    assert m["truth"]["horizontal"]["median_m"] < 0.3
    assert any("kept: the one at the cameras' height first guess 1" in w for w in m["warnings"])
    assert json.loads((tmp_path / "misled" / "timings.json").read_text())["retries"] > 0


def test_a_wrong_given_scale_ends_unreliable_with_exit_4(scaled_scenes, tmp_path, capsys):
    """A given scale is not second-guessed before matching; the status judges the result."""
    code, m = _run(_without_gps(scaled_scenes[0.25]), tmp_path / "wrong", "-s", "street_scale=1")
    assert m["street_scale"] == {"value": 1.0, "source": "recipe"}
    assert code == 4 and m["status"] == "unreliable"
    assert "street scale" in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize("value, words", [("big", "must be 'auto' or a number"), ("0.001", "outside")])
def test_a_bad_street_scale_is_one_line_and_exit_2(scaled_scenes, tmp_path, capsys, value, words):
    code = main(["run", str(RECIPE), "--scene", str(scaled_scenes[1.0]), "--out", str(tmp_path / "bad"),
                 "--no-rerun", "-q", "-s", f"street_scale={value}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and words in err[0] and "street_scale" in err[0]
    assert not (tmp_path / "bad").exists()


def test_prominence_finds_a_sharp_peak_over_a_falling_trend_and_not_the_trend_itself():
    """The raw scan favours small factors (a shrunk street fits somewhere more easily); the scale is
    the sharp peak above that trend, and a trend with noise alone has no prominent peak."""
    from toolkit.matching.route_scale import ScaleSearchConfig, prominence

    g = np.exp(np.linspace(np.log(0.5), np.log(2.0), 36))
    rng = np.random.default_rng(3)
    trend = 0.45 - 0.15 * np.log(g) + rng.normal(0, 0.02, len(g))
    peaked = trend.copy()
    at = int(np.argmin(np.abs(np.log(g / 1.1))))
    peaked[at] += 0.12
    z = prominence(g, peaked)
    assert np.argmax(peaked) != at                    # the raw maximum is at the small end
    assert np.argmax(z) == at and z[at] >= ScaleSearchConfig().min_prominence
    # a trend with independent noise alone: a prominent peak in 1-2 % of the scans
    false = [prominence(g, 0.45 - 0.15 * np.log(g) + np.random.default_rng(s).normal(0, 0.02, len(g))).max()
             >= ScaleSearchConfig().min_prominence for s in range(500)]
    assert np.mean(false) <= 0.02


def _spread_fixes(source: Path, scene: Path, factor: float) -> Path:
    """A copy of ``source`` whose GPS fixes are spread by ``factor`` about their mean."""
    import shutil

    from pyproj import Transformer

    shutil.copytree(source, scene)
    gps = scene / "street" / "gps.csv"
    lines = gps.read_text().splitlines()
    rows = [line.split(",") for line in lines[1:]]
    crs = (scene / "scene.yaml").read_text().split("crs:")[1].split()[0]
    fwd = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    east, north = fwd.transform([float(r[1]) for r in rows], [float(r[2]) for r in rows])
    xy = np.column_stack([east, north])
    xy = xy.mean(axis=0) + factor * (xy - xy.mean(axis=0))
    lon, lat = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(xy[:, 0], xy[:, 1])
    gps.write_text("\n".join([lines[0]] + [",".join([r[0], f"{a:.9f}", f"{b:.9f}", *r[3:]])
                                           for r, a, b in zip(rows, lon, lat)]) + "\n")
    return scene


@pytest.mark.parametrize("factor, metric", [(1.04, True), (1.07, False)])
def test_a_gps_scale_within_the_per_segment_reach_is_taken_as_metric(scaled_scenes, tmp_path, factor, metric):
    """Fixes spread 4 % put the estimate 4 % low: within the per-segment scale's ±5 % the frame is
    taken as metric without a check; 7 % off, the estimate is a first guess for the matching to check."""
    from toolkit.scene import load_scene
    from toolkit.street_scale import resolve_street_scale

    scene = _spread_fixes(scaled_scenes[1.0], tmp_path / "spread", factor)
    got = resolve_street_scale(load_scene(scene)).street_scale
    assert got.source == "gps" and abs(got.estimate - 1 / factor) < 0.01
    assert (got.value, got.settled) == ((1.0, True) if metric else (got.estimate, False))


def test_a_gps_scale_biased_by_its_fixes_is_replaced_by_the_matching(scaled_scenes, tmp_path):
    """Fixes spread 6 % about their mean (what metres of fix error do to the pair distances of a short
    loop) put the GPS estimate 6 % low; the matching checks it against the over-view and the run
    works at the matching's scale, close to the metric frame's."""
    scene = _spread_fixes(scaled_scenes[1.0], tmp_path / "biased", 1.06)
    code, m = _run(scene, tmp_path / "out")
    est = m["street_scale"]
    assert code == 0 and m["status"] == "ok"
    assert est["source"] == "gps" and abs(est["gps_estimate"] - 1 / 1.06) < 0.01
    assert est["matching"]["passes"] >= 2 and abs(est["value"] - 1.0) < 0.02
    assert m["truth"]["horizontal"]["median_m"] < 0.3
