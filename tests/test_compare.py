"""crossview compare: variant planning, tables, one shared rerun recording (fake stages, mini scene)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from plugins.evaluate_chamfer import Chamfer
from tests.fake_stages import FAKE_RECIPE, FakeMatch, FakeStreet, fake_registry
from toolkit.compare import (
    RunRow,
    Variant,
    aggregate,
    markdown_table,
    parse_swap,
    plan_variants,
    run_variants,
    write_tables,
)
from toolkit.errors import RecipeError
from toolkit.io.cloud import write_ply
from toolkit.metrics_model import RunMetrics


class FakeMatchNone(FakeMatch):
    """Matches nothing (a second match stage to swap in)."""
    kind, name = "match", "none"

    def __call__(self, graphs, costs, obs):
        m = super().__call__(graphs, costs, obs)
        from dataclasses import replace

        return replace(m, segment_match=np.array([-1]))


class FakeStreetOther(FakeStreet):
    kind, name = "street", "other"


@pytest.fixture
def recipe(tmp_path: Path) -> Path:
    p = tmp_path / "fake.yaml"
    p.write_text(FAKE_RECIPE + "  evaluate: {use: evaluate.chamfer}\n")
    return p


def _registry():
    reg = fake_registry()
    for cls in (FakeMatchNone, FakeStreetOther, Chamfer):
        reg.add(cls)
    return reg


def test_parse_swap_and_errors():
    assert parse_swap("match=match.icm, match.greedy") == ("match", ["match.icm", "match.greedy"])
    with pytest.raises(RecipeError, match="not a stage of kind 'match'"):
        parse_swap("match=refine.icp")
    with pytest.raises(RecipeError, match="STEP=STAGE"):
        parse_swap("match.icm")


def test_plan_one_factor_at_a_time_and_grid(recipe, tmp_path):
    other = tmp_path / "other.yaml"
    other.write_text(FAKE_RECIPE.replace("name: fake", "name: other"))
    vs = plan_variants(recipe, ["match=match.fake,match.none", "street=street.other"], [other])
    assert [v.name for v in vs] == ["fake", "none", "other", "other_2"]  # match.fake is the base itself
    assert vs[1].overrides == ("steps.match.use=match.none",)
    assert vs[3].recipe == other
    grid = plan_variants(recipe, ["match=match.none", "street=street.other"], grid=True)
    assert [v.name for v in grid] == ["fake", "other", "none", "none_other"]
    assert set(grid[3].overrides) == {"steps.match.use=match.none", "steps.street.use=street.other"}
    with pytest.raises(RecipeError, match="no step 'adjust'"):
        plan_variants(recipe, ["adjust=adjust.none"])


def test_compare_runs_variants_into_tables_and_one_recording(recipe, mini_scene, tmp_path):
    from toolkit.io.cloud import read_points
    from toolkit.viz_rerun import entity_paths

    # a reference cloud = the street cloud where FakeRefine puts it, so the metric has numbers
    ref = tmp_path / "ref.ply"
    write_ply(ref, read_points(mini_scene / "street/cloud.ply") * 0 + [500005.0, 4400010.0, 0.0])
    failing = tmp_path / "failing.yaml"
    failing.write_text(FAKE_RECIPE.replace("name: fake", "name: fail").replace(
        "street: {use: street.fake}", "street: {use: street.fake, params: {fail: true}}")
        + "  evaluate: {use: evaluate.chamfer}\n")
    overrides = [f"steps.evaluate.params.reference={ref}"]
    with pytest.raises(RecipeError, match="variant nope: .*unknown stage 'street.nope'"):
        run_variants(plan_variants(recipe, ["street=street.nope"], overrides=overrides), [mini_scene],
                     tmp_path / "never", quiet=True, registry=_registry())
    assert not (tmp_path / "never").exists()
    vs = plan_variants(recipe, ["match=match.none"], [failing], overrides=overrides)
    out = tmp_path / "cmp"
    rows = run_variants(vs, [mini_scene], out, quiet=True, registry=_registry())
    assert [r.variant for r in rows] == ["fake", "none", "fail"]
    assert rows[0].error is None and rows[1].error is None
    assert "no façade points found" in rows[2].error
    for r in rows[:2]:
        assert (r.out_dir / "report.html").is_file() and (r.out_dir / "metrics.json").is_file()
        assert r.metrics.chamfer.d3.n_pairs >= 1
    md = write_tables(out, rows, vs, 1)
    assert "| fake |" in md and "| none |" in md and "failed" in md
    with open(out / "table.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [t["variant"] for t in table] == ["fake", "none", "fail"]
    assert table[0]["n_runs"] == "1" and table[2]["n_failed"] == "1"
    assert float(table[0]["chamfer_3d_mean_m"]) >= 0 and table[0]["time_total_s"]
    with open(out / "runs.csv") as fh:
        assert len(list(csv.DictReader(fh))) == 3
    paths = entity_paths(out / "recording.rrd")
    for v in ("fake", "none"):
        assert f"/{v}/overview/segments" in paths and f"/{v}/warp/cloud" in paths and f"/{v}/recipe" in paths
    assert not any(p.startswith("/overview") for p in paths)


def test_aggregate_mean_and_std_over_scenes():
    vs = [Variant("a", Path("x.yaml"))]
    rows = [RunRow("a", f"s{k}", metrics=RunMetrics.model_validate({"chamfer": {"3d": {"mean_m": m}},
                                                                    "matching": {"precision": p}}),
                   timings={"match": 1.0, "refine": t}) for k, (m, p, t) in enumerate([(1.0, 0.5, 2.0), (3.0, 1.0, 4.0)])]
    rows.append(RunRow("a", "s2", error="boom"))
    agg = aggregate(rows, vs)[0]
    assert agg["chamfer_3d_mean_m"] == pytest.approx(2.0) and agg["chamfer_3d_mean_m__std"] == pytest.approx(1.0)
    assert agg["match_precision"] == pytest.approx(0.75)
    assert agg["time_total_s"] == pytest.approx(4.0) and agg["time_refine_s"] == pytest.approx(3.0)
    assert agg["n_runs"] == 2 and agg["n_failed"] == 1
    md = markdown_table([agg], 3)
    assert "2.00 ± 1.00" in md and "75 % ± 25" in md


def test_seed_scenes_regenerate_with_same_config_once(tmp_path, monkeypatch):
    import shutil

    import toolkit.synth.generate as gen
    from toolkit.compare import seed_scenes
    from toolkit.errors import SceneError
    from toolkit.scene import write_manifest

    base = tmp_path / "campus"
    base.mkdir()
    write_manifest(base, "c", "EPSG:32617", {}, extra={"synth": {"preset": "tiny", "seed": 4,
                                                                  "config": {"route_length_m": 123.0}}})
    calls = []

    def fake_generate(preset, seed, out, **overrides):
        calls.append((preset, seed, Path(out).name, overrides))
        out.mkdir()
        shutil.copy(base / "scene.yaml", out / "scene.yaml")
        return out

    monkeypatch.setattr(gen, "generate", fake_generate)
    scenes = seed_scenes(base, 3)
    assert [s.name for s in scenes] == ["campus", "campus-seed5", "campus-seed6"]
    assert calls == [("tiny", 5, "campus-seed5", {"route_length_m": 123.0}),
                     ("tiny", 6, "campus-seed6", {"route_length_m": 123.0})]
    seed_scenes(base, 3)
    assert len(calls) == 2  # generated once, then reused
    plain = tmp_path / "plain"
    plain.mkdir()
    write_manifest(plain, "p", "EPSG:32617", {})
    with pytest.raises(SceneError, match="--seeds needs a synthetic scene"):
        seed_scenes(plain, 2)
