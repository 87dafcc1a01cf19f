"""toolkit.metrics_model: metrics.json written from the model as given, older files loaded, and the
readers' tables naming figures the model has."""

from __future__ import annotations

import dataclasses
import json

import pytest
from pydantic import ValidationError

from toolkit.metrics_model import KeyFigures, RunMetrics
from toolkit.types import Metrics


def _stats(median: float, n: int = 4) -> dict:
    return {"mean_m": median + 0.5, "median_m": median, "p90_m": 2.0, "p95_m": 2.5, "max_m": 3.0, "n": n}


def _written() -> dict:
    """metrics.json of a run on a scene with truth, shortened (one segment, two bins)."""
    histogram = {"edges_m": [0.0, 0.1], "counts": [3, 1]}
    return {
        "status": "unreliable", "confidence": 0.25, "reasons": ["façades off"],
        "assessment": {"n_street_segments": 1, "registered_share": 1.0, "bp_converged": None, "prior": "gps",
                       "prior_window_score": 0.5},
        "status_rule": {"min_confidence": 0.4, "matched_share": {"good": 0.4, "bad": 0.0}},
        "schema": "crossview.metrics/1", "cutoff_m": 10.0,
        "street": {"n_points": 4, "n_used": 4},
        "reference": {"source": "truth_lidar", "path": "/s/truth/lidar.ply", "n_points": 9, "n_used": 9},
        "chamfer": {d: {"mean_m": m, "std_m": 0.1, "median_m": m, "p95_m": 0.3, "n_pairs": 4, "paired_fraction": 1.0,
                        "paired_fraction_reference": 0.444444, "histogram": histogram}
                    for d, m in (("3d", 0.2), ("2d", 0.1))},
        "truth": {"error_3d": _stats(1.5), "horizontal": _stats(1.25),
                  "within_m": {"0.5": {"horizontal": 0.25, "3d": 0.0}, "1": {"horizontal": 0.75, "3d": None}},
                  "histogram": {"edges_m": [0.0, 0.1, None], "counts": [0, 1, 3]}},
        "matching": {"precision": 0.5, "recall": None, "precision_iou": 0.5, "recall_iou": None,
                     "n_street_segments": 1, "n_matched": 1, "n_correct": 0, "n_with_counterpart": 0,
                     "n_overview_segments": 2, "n_overview_with_building": 2},
        "cameras": {"source": "registered", "centre_error_mean_m": 0.3, "centre_error_median_m": 0.25,
                    "centre_error_p95_m": 0.5, "centre_error_horizontal_median_m": 0.2,
                    "registered": {"n": 4, "n_missing": 0, "error_3d": _stats(0.25), "horizontal": _stats(0.2)},
                    "adjusted": None},
        "segments": [{"index": 0, "id": 7, "n_points": 4, "overview_match": None, "overview_id": None,
                      "match_cost": 1.0, "match_confidence": 0.0, "refine_valid": False, "refine_cost": 3.0,
                      "true_building": -1, "matched_building": -1, "correct": None, "error_mean_m": 1.75,
                      "error_median_m": 1.5}],
        "notes": [],
        "coverage": {"n_street_segments": 1, "n_matched": None, "n_registered": 1, "registered_share": 1.0,
                     "points_on_registered_segments_share": 1.0, "points_without_carrier_share": 0.0},
        "crs": "EPSG:32617",
        "street_scale": {"value": 1.0, "source": "gps", "gps_estimate": 0.99, "gps_pairs": 12},
        "heights": "relative",
        "segment_scale": None,
        "warnings": ["refine: segment 7 rejected"],
        "input_notes": [],
    }


def _text(value: dict) -> str:
    return json.dumps(value, indent=2)


def test_the_written_entries_come_back_in_order_with_their_nulls():
    written = _written()
    assert _text(RunMetrics.checked(written).to_json()) == _text(written)
    del written["coverage"], written["segment_scale"]  # absent (nothing refined) is not null
    assert _text(RunMetrics.checked(written).to_json()) == _text(written)


def test_key_figures_read_the_nested_entries():
    figures = RunMetrics.checked(_written()).key_figures()
    assert figures == KeyFigures(
        chamfer_3d_mean_m=0.2, chamfer_3d_std_m=0.1, chamfer_2d_mean_m=0.1, chamfer_2d_std_m=0.1,
        paired_fraction=1.0, error_h_median_m=1.25, error_h_mean_m=1.75, error_3d_median_m=1.5,
        error_3d_mean_m=2.0, error_3d_p95_m=2.5, within_1m_h=0.75, match_precision=0.5, match_recall=None,
        camera_median_m=0.25)
    m = RunMetrics.checked(_written())
    assert m.chamfer.d3.histogram.counts == [3, 1] and m.truth.within_m["0.5"].d3 == 0.0
    assert m.segments[0].id == 7 and m.segments[0].correct is None and m.segment_scale is None


def test_checked_refuses_a_value_of_another_type():
    for entry in ({"street": {"n_points": 4.0}}, {"segments": [{"refine_valid": 1}]}, {"confidence": True},
                  {"reasons": "one"}):
        with pytest.raises(ValidationError):
            RunMetrics.checked(entry)


def test_older_and_newer_files_load(tmp_path):
    older = {"schema": "crossview.metrics/1", "cutoff_m": 10.0, "chamfer": None, "truth": None,
             "timings_s": {"overview": 1.5}, "warnings": []}
    path = tmp_path / "metrics.json"
    path.write_text(_text(older))
    m = RunMetrics.load(path)
    assert m.status is None and m.timings_s == {"overview": 1.5} and m.key_figures() == KeyFigures()
    assert m.to_json() == older
    newer = {**_written(), "drift": {"p95_m": 0.5}}
    newer["truth"]["error_3d"]["p99_m"] = 3.0
    path.write_text(_text(newer))
    m = RunMetrics.load(path)
    assert m.model_extra == {"drift": {"p95_m": 0.5}} and m.truth.error_3d.model_extra == {"p99_m": 3.0}
    assert m.key_figures().error_3d_p95_m == 2.5
    assert m.to_json() == newer and list(m.to_json())[-1] == "drift"  # kept, after the known keys


def test_the_evaluation_of_a_run_and_of_none():
    m = RunMetrics.of(Metrics(values={"truth": {"horizontal": {"median_m": 0.5}}}))
    assert m.key_figures() == KeyFigures(error_h_median_m=0.5)
    assert RunMetrics.of(None).to_json() == {}


def test_the_readers_tables_name_key_figures():
    from toolkit.batch import COLUMNS
    from toolkit.compare import MD_HEADERS, METRIC_COLUMNS
    from toolkit.report import HEADLINE
    from toolkit.summary import SUMMARY_ROWS

    names = {f.name for f in dataclasses.fields(KeyFigures)}
    used = ({n for _, n, _ in SUMMARY_ROWS} | {n for _, n in COLUMNS} | set(METRIC_COLUMNS)
            | {n for _, ns, _ in HEADLINE for n in ns})
    assert used <= names, used - names
    assert set(METRIC_COLUMNS) <= set(MD_HEADERS)


def test_a_runs_file_loads_and_writes_the_same_bytes():
    from tests.registered_runs import tiny_run
    from toolkit.outputs import _jsonable

    res, _ = tiny_run("ply")  # the key the other tests cache the run under
    raw = (res.out_dir / "metrics.json").read_text()
    m = RunMetrics.load(res.out_dir / "metrics.json")
    assert json.dumps(_jsonable(m.to_json()), indent=2) + "\n" == raw
    written = json.loads(raw)
    assert m.status == res.assessment.status == written["status"]
    assert m.key_figures().error_h_median_m == written["truth"]["horizontal"]["median_m"] is not None
