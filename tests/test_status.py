"""Self-assessment without truth (toolkit.status): the rule from figure dicts, and through the CLI a
good tiny run is ok (exit 0) while a forced wrong labelling is unreliable (exit 4, outputs written)."""

from __future__ import annotations

import dataclasses
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from plugins.match_loopy_bp import LoopyBP
from tests.conftest import REPO, synthetic_scene
from toolkit.matching.solvers_common import vote
from toolkit.registry import Registry
from toolkit.status import HARD_CHECKS, SCORED, StatusRule, Verdict

RECIPE = REPO / "recipes" / "dsm.yaml"
LEADING_KEYS = ["status", "confidence", "reasons", "assessment"]

# the figures of a good tiny run (dsm.yaml on test-tiny, seed 0)
GOOD = {
    "n_street_segments": 20, "registered_share": 0.95, "registered_point_share": 0.9687, "bp_converged": True,
    "bp_iterations": 3, "matched_share": 1.0, "match_confidence_mean": 0.9542, "neighbour_tol_m": 5.0,
    "neighbour_pairs": 40, "neighbour_gap_median_m": 0.1755, "neighbour_gap_p90_m": 0.9696,
    "neighbour_disagree_share": 0.0, "facade_radius_m": 1.5, "facade_points": 68555,
    "facade_support_share": 0.9998, "facade_distance_median_m": 0.3468, "outside_grid_share": 0.0,
    "camera_spread_median_m": 0.3249, "camera_spread_p95_m": 1.1852, "ba_rms_before_px": 3.4288,
    "ba_rms_after_px": 0.4251, "ba_iterations": 10, "gps_fixes": 201, "gps_sigma_m": 3.0,
    "gps_residual_median_m": 3.4629, "gps_residual_p90_m": 5.4902, "prior_links": 4, "prior_links_broken": 0,
}


class WrongLabels(LoopyBP):
    """loopy_bp, then each conjugate node relabelled with its cheapest candidate pairing other buildings."""

    kind, name = "match", "wrong_labels"

    def __call__(self, graphs, costs, obs):
        m = super().__call__(graphs, costs, obs)
        pairs = np.asarray(graphs.label_pairs)
        cost = np.asarray(costs.cost)[:, :-1]
        labels = m.edge_label.copy()
        for e, label in enumerate(m.edge_label):
            if label == graphs.null_label:
                continue
            others = ~np.isin(pairs, pairs[label]).any(axis=1) & np.isfinite(cost[e])
            labels[e] = int(np.argmin(np.where(others, cost[e], np.inf))) if others.any() else graphs.null_label
        match, conf, T2d, mcost = vote(graphs, costs, labels)
        return dataclasses.replace(m, edge_label=labels, segment_match=match, confidence=conf, T2d=T2d, cost=mcost)


def wrong_registry() -> Registry:
    reg = Registry()
    reg.add(WrongLabels)
    return reg


# --- the rule, from figure dicts ------------------------------------------------------------------
def test_good_figures_are_ok_with_full_confidence():
    status, confidence, reasons = StatusRule().judge(GOOD)
    assert (status, confidence, reasons) == ("ok", 1.0, ())


@pytest.mark.parametrize("change,fragment", [
    ({"gps_residual_median_m": 40.0}, "GPS fixes"),
    ({"facade_support_share": 0.1}, "façade points"),
    ({"outside_grid_share": 0.8}, "outside the over-view"),
    ({"neighbour_disagree_share": 0.7, "neighbour_gap_median_m": 35.0}, "neighbouring segments"),
    ({"registered_point_share": 0.1}, "street points"),
    ({"camera_height_median_m": 0.5}, "street scale is likely wrong"),
    ({"camera_height_median_m": 9.0}, "street scale is likely wrong"),
    ({"segment_scale_median": 0.955}, "median scale of 0.955"),
    ({"prior_links_broken": 2, "prior_links": 9, "prior_link_max_m": 1119.2}, "route placement puts 2 of its 9"),
    ({"camera_gap_p90_m": 160.3}, "a tenth of the cameras are 160 m"),
    ({"neighbour_gap_median_m": 1.85, "neighbour_gap_p90_m": 3.5}, "place each other 1.9 m apart"),
])
def test_each_hard_reason_fires_first(change, fragment):
    verdict = StatusRule().judge({**GOOD, **change})
    assert verdict.status == "unreliable"
    assert fragment in verdict.reasons[0], verdict.reasons


NO_GPS = {**GOOD, "gps_fixes": None, "gps_sigma_m": None, "gps_residual_median_m": None, "gps_residual_p90_m": None}


def test_a_route_placement_that_overrules_half_its_windows_is_unreliable_without_gps():
    """Without GPS, windows whose own façades fit best elsewhere than the chain put them: one in
    three is ok (accurate short routes have it), half is not; with GPS the fixes may overrule them."""
    rule = StatusRule()
    half = {"prior_overruled_share": 0.5455, "prior_alone_max_m": 684.8}
    verdict = rule.judge({**NO_GPS, **half})
    assert verdict.status == "unreliable" and "in 55% of the route placement's windows" in verdict.reasons[0]
    assert rule.judge({**NO_GPS, "prior_overruled_share": 0.3333}).status == "ok"
    assert rule.judge({**GOOD, **half}).status == "ok"


def test_neighbours_a_metre_apart_are_ok():
    verdict = StatusRule().judge({**GOOD, "neighbour_gap_median_m": 1.3, "neighbour_gap_p90_m": 3.5})
    assert verdict.status == "ok", verdict.reasons


def test_gps_tolerance_grows_with_sigma():
    rule = StatusRule()
    assert rule.judge({**GOOD, "gps_residual_median_m": 14.0}).status == "ok"   # tolerance max(9, 15) = 15 m
    assert rule.judge({**GOOD, "gps_residual_median_m": 25.0, "gps_sigma_m": 10.0}).status == "ok"   # 30 m
    assert rule.judge({**GOOD, "gps_residual_median_m": 31.0, "gps_sigma_m": 10.0}).status == "unreliable"


def test_hard_reasons_most_important_first():
    verdict = StatusRule().judge({**GOOD, "registered_point_share": 0.1, "facade_support_share": 0.1,
                                  "gps_residual_median_m": 200.0})
    assert [r.split()[0] for r in verdict.reasons[:3]] == ["camera", "only", "only"]
    assert "façade" in verdict.reasons[1] and "street points" in verdict.reasons[2]


def test_low_confidence_alone_is_unreliable():
    verdict = StatusRule().judge({**GOOD, "matched_share": 0.2, "match_confidence_mean": 0.25})
    assert verdict.status == "unreliable" and verdict.confidence < 0.5
    assert verdict.reasons[0].startswith("confidence ") and "matched" in verdict.reasons[0]


def test_a_run_with_no_hard_reason_but_weak_figures_is_unreliable():
    # the figures of a real-city run 2.4 m off (helsinki-s-short, label map, GPS σ 5 m every 5th image):
    # every hard limit holds, a fifth of the segments matched and the façades 0.89 m from the outlines
    silent = {**GOOD, "registered_share": 0.4, "registered_point_share": 0.7571, "matched_share": 0.2,
              "match_confidence_mean": 0.3875, "facade_support_share": 0.645, "facade_distance_median_m": 0.8868,
              "camera_spread_p95_m": 2.9322, "camera_gap_p90_m": 46.3968, "gps_sigma_m": 5.0,
              "gps_residual_median_m": 8.0551, "bp_iterations": 2}
    rule = StatusRule()
    assert not any(check(rule, silent) for check in HARD_CHECKS.values())
    verdict = rule.judge(silent)
    assert verdict.status == "unreliable" and verdict.confidence < rule.min_confidence
    assert verdict.reasons[0].startswith("confidence ") and "matched" in verdict.reasons[0]


@pytest.mark.parametrize("name", [n for n in SCORED if n != "gps_residual_ratio"] + ["gps_residual_median_m"])
def test_confidence_is_monotone_in_each_figure(name):
    rule = StatusRule()
    ramp = getattr(rule, name, None) or rule.gps_residual_ratio
    lo, hi = sorted((ramp.good, ramp.bad))
    scale = 15.0 if name == "gps_residual_median_m" else 1.0  # the GPS ramp is on residual / tolerance
    values = np.linspace(lo - 0.2 * (hi - lo), hi + 0.2 * (hi - lo), 41) * scale
    conf = np.array([rule.judge({**GOOD, name: float(v)}).confidence for v in values])
    assert ((0 <= conf) & (conf <= 1)).all()
    steps = np.diff(conf) * (1 if ramp.good > ramp.bad else -1)
    assert (steps >= -1e-12).all() and conf.max() == 1.0 and conf.min() < 0.05, conf


def test_absent_figures_do_not_count_and_nothing_registered_is_said():
    none = {k: None for k in GOOD}
    status, confidence, reasons = StatusRule().judge(none)
    assert status == "ok" and confidence == 1.0 and reasons[-1].startswith("not assessed")
    assert StatusRule().judge({**GOOD, "gps_residual_median_m": None, "gps_sigma_m": None}).status == "ok"
    assert StatusRule().judge({**GOOD, "bp_converged": False}).confidence == StatusRule().bp_unconverged_score


def test_rule_round_trips_and_thresholds_rescore():
    rule = StatusRule()
    assert StatusRule.from_dict(json.loads(json.dumps(rule.to_dict()))) == rule
    strict = dataclasses.replace(rule, min_facade_support_share=0.9999)
    assert strict.judge(GOOD).status == "unreliable"
    assert isinstance(rule.judge(GOOD), Verdict)


# --- runs on the tiny scene ---------------------------------------------------------------------------
def _metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())


def test_good_run_is_ok_through_the_cli(tmp_path, capsys):
    from toolkit.cli import main

    out = tmp_path / "good"
    code = main(["run", str(RECIPE), "--scene", str(synthetic_scene("tiny")), "--out", str(out), "--no-rerun"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    metrics = _metrics(out)
    assert list(metrics)[:4] == LEADING_KEYS and metrics["status"] == "ok"
    assert metrics["confidence"] >= 0.9
    rescored = StatusRule.from_dict(metrics["status_rule"]).judge(metrics["assessment"])  # offline
    assert tuple(rescored) == (metrics["status"], metrics["confidence"], tuple(metrics["reasons"]))
    summary = printed.out
    assert summary.index("status") < summary.index("façade support") < summary.index("per-point error")
    assert "registration unreliable" not in printed.out + printed.err
    assert "Self-assessment" in (out / "report.html").read_text()


def test_forced_wrong_labelling_is_unreliable_exit_4(tmp_path):
    out = tmp_path / "wrong"
    code = ("import sys; import toolkit.registry as r; from tests.test_status import wrong_registry; "
            "r._default = wrong_registry(); from toolkit.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.run(
        [sys.executable, "-c", code, "run", str(RECIPE), "--scene", str(synthetic_scene("tiny")), "--out", str(out),
         "--no-rerun", "-s", "steps.match.use=match.wrong_labels"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    assert proc.returncode == 4, proc.stdout
    lines = proc.stdout.strip().splitlines()
    assert lines[-1].startswith("registration unreliable: "), lines[-3:]
    for name in ("registered.ply", "transforms.json", "metrics.json", "report.html", "run.log", "sparse/images.bin"):
        assert (out / name).exists(), name
    metrics = _metrics(out)
    assert list(metrics)[:4] == LEADING_KEYS
    assert metrics["status"] == "unreliable" and lines[-1].endswith(metrics["reasons"][0])
    assert metrics["assessment"]["facade_support_share"] < 0.5
    assert metrics["truth"]["horizontal"]["median_m"] > 5  # it is indeed wrong (truth read only by the test)
    assert "tries" not in metrics  # a GPS scale: no other scale to try


def test_metrics_without_evaluate_lead_with_status_and_are_reproducible(tmp_path):
    from toolkit.runner import run_recipe
    from toolkit.summary import print_summary

    recipe = tmp_path / "no-evaluate.yaml"
    text = RECIPE.read_text().split("  adjust:")[0]
    recipe.write_text(text)
    runs = [run_recipe(recipe, scene=synthetic_scene("tiny"), out=tmp_path / k, rerun=False) for k in "ab"]
    first = (tmp_path / "a/metrics.json").read_bytes()
    assert first == (tmp_path / "b/metrics.json").read_bytes()
    metrics = json.loads(first)
    assert list(metrics)[:4] == LEADING_KEYS and "chamfer" not in metrics
    assert metrics["assessment"]["ba_rms_after_px"] is None and metrics["assessment"]["gps_fixes"] > 0
    assert runs[0].assessment.status == metrics["status"] == "ok"
    from rich.console import Console

    buf = io.StringIO()
    print_summary(runs[0], Console(file=buf, width=120))
    assert "status" in buf.getvalue() and "GPS residual" in buf.getvalue()
    assert "Self-assessment" in (tmp_path / "a/report.html").read_text()


# --- batch and compare columns ----------------------------------------------------------------------
def test_batch_rows_carry_status_and_unreliable_is_not_failed(tmp_path, mini_scene, monkeypatch):
    import toolkit.registry as registry_mod
    from tests.fake_stages import FAKE_RECIPE, fake_registry
    from toolkit.batch import exit_code, run_one, write_summary

    monkeypatch.setattr(registry_mod, "_default", fake_registry())
    recipe = tmp_path / "fake.yaml"
    recipe.write_text(FAKE_RECIPE)
    row = run_one(str(recipe), str(mini_scene), str(tmp_path / "out"), [], False)
    assert row["status"] == "ok" and 0 <= row["confidence"] <= 1, row
    rows = [row, {**row, "scene": "b", "status": "unreliable", "reason": "façades off"}]
    assert exit_code(rows) == 0
    assert exit_code(rows + [{"scene": "c", "status": "failed"}]) == 3
    write_summary(tmp_path, rows)
    header = (tmp_path / "summary.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["scene", "status", "confidence"]
    assert "| unreliable |" in (tmp_path / "summary.md").read_text()


def test_compare_tables_have_status_and_confidence(tmp_path):
    import csv

    from toolkit.compare import RunRow, Variant, write_tables

    vs = [Variant("a", Path("x.yaml")), Variant("b", Path("y.yaml"))]
    rows = [RunRow("a", "s0", status="ok", confidence=0.9), RunRow("a", "s1", status="unreliable", confidence=0.3),
            RunRow("b", "s0", status="ok", confidence=1.0)]
    md = write_tables(tmp_path, rows, vs, 2)
    assert "| variant | status | confidence |" in md
    assert "| a | 1/2 unreliable | 0.60 ± 0.30 |" in md and "| b | ok | 1.00 |" in md
    with open(tmp_path / "table.csv") as fh:
        table = list(csv.DictReader(fh))
    assert [t["status"] for t in table] == ["1/2 unreliable", "ok"] and float(table[0]["confidence"]) == 0.6
    with open(tmp_path / "runs.csv") as fh:
        assert [r["status"] for r in csv.DictReader(fh)] == ["ok", "unreliable", "ok"]


def test_the_camera_gap_limit_is_half_the_warps_bridge_span():
    # camera_gap_p90_m is a camera's distance to the nearest camera that sees a registered façade; the warp
    # bridges spans of bridge_min_gap_m between such cameras, whose middle is half a span from either end
    from plugins.warp_inverse_log import InverseLog

    span = InverseLog.Params().bridge_min_gap_m
    rule = StatusRule()
    assert rule.max_camera_gap_p90_m == span / 2
    assert rule.judge({**GOOD, "camera_gap_p90_m": 0.45 * span}).status == "ok"
    assert rule.judge({**GOOD, "camera_gap_p90_m": 0.55 * span}).status == "unreliable"
