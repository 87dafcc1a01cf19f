"""How well the run status (toolkit/status.py) tells failed runs from good ones, city by city.

Reads the runs of bench/cities.py (data/cities/out/*/metrics.json: the truth-free ``assessment`` and
the truth figures), and prints:
- the confusion table (flagged × accurate) of the rule the runs were judged with, and its gross
  failures (horizontal median > 2 m) that were not flagged;
- a leave-one-city-out choice of the rule's main hard limits (façade distance and support, registered
  point share, median segment scale, neighbour disagreement) and of ``min_confidence``: for each city, the limits are chosen on the other
  cities' runs only (every gross failure there flagged, then the fewest accurate runs flagged,
  then the limits farthest from the runs that decided them), and the held-out city's runs are
  judged with them. Nothing is re-run: ``StatusRule.judge`` works from the stored figures.

usage: python bench/status_calibration.py [--out-dir data/cities/out]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np

from _common import REPO

GROSS_M = 2.0


def load_runs(out_dir: Path) -> list[dict]:
    runs = []
    for m_path in sorted(out_dir.glob("*/metrics.json")):
        m = json.loads(m_path.read_text())
        truth = m.get("truth") or {}
        if not truth or "assessment" not in m:
            continue
        name = m_path.parent.name
        stamp = json.loads((REPO / "data" / "cities" / _scene_of(name) / "stamp.json").read_text()) \
            if (REPO / "data" / "cities" / _scene_of(name) / "stamp.json").is_file() else {}
        h = truth["horizontal"]["median_m"]
        recipe = name.removesuffix("-gps")[len(_scene_of(name)) + 1:]
        p95 = truth["error_3d"]["p95_m"] if recipe == "dsm" else truth["horizontal"]["p95_m"]
        rigid = stamp.get("rigid_mean_m")
        accurate = h <= 0.5 and p95 <= 1.5 and (rigid is None or truth["error_3d"]["mean_m"] < rigid)
        runs.append({"name": name, "city": _city_of(name), "h": h, "accurate": accurate,
                     "gross": h > GROSS_M, "figures": m["assessment"], "rule": m.get("status_rule", {}),
                     "status": m["status"]})
    return runs


def _scene_of(run_name: str) -> str:
    for suffix in ("-label_map", "-dsm", "-osm"):
        base = run_name.removesuffix("-gps")
        if base.endswith(suffix):
            return base[: -len(suffix)]
    return run_name


def _city_of(run_name: str) -> str:
    return _scene_of(run_name).rsplit("-", 1)[0]


def confusion(runs: list[dict], flagged: list[bool]) -> str:
    a = np.array([r["accurate"] for r in runs])
    f = np.array(flagged)
    g = np.array([r["gross"] for r in runs])
    return (f"flagged & accurate {int((f & a).sum())}, flagged & not accurate {int((f & ~a).sum())}, "
            f"ok & accurate {int((~f & a).sum())}, ok & not accurate {int((~f & ~a).sum())}; "
            f"gross failures {int(g.sum())}, unflagged {int((g & ~f).sum())}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out-dir", type=Path, default=REPO / "data" / "cities" / "out")
    args = ap.parse_args()
    from toolkit.status import StatusRule

    runs = load_runs(args.out_dir)
    if not runs:
        raise SystemExit(f"{args.out_dir}: no runs with truth and an assessment (run bench/cities.py first)")
    base = StatusRule.from_dict(runs[0]["rule"]) if runs[0]["rule"] else StatusRule()
    flagged = [base.judge(r["figures"]).status != "ok" for r in runs]
    print(f"{len(runs)} runs; the rule they were judged with: {confusion(runs, flagged)}")
    for r, f in zip(runs, flagged):
        if r["gross"] and not f:
            print(f"  unflagged gross failure: {r['name']} (h median {r['h']:.1f} m)")
        if r["accurate"] and f:
            print(f"  flagged accurate run: {r['name']}: {base.judge(r['figures']).reasons[:1]}")

    grid = {"max_facade_distance_median_m": [0.8, 1.0, 1.2, 1.5, 2.0],
            "min_facade_support_share": [0.2, 0.3, 0.4, 0.5, 0.6],
            "min_registered_point_share": [0.2, 0.3, 0.4, 0.5],
            "max_segment_scale_deviation": [0.02, 0.025, 0.035, 0.05, 0.07],
            "max_neighbour_disagree_share": [0.2, 0.3, 0.4, 0.5, 0.6],
            "min_confidence": [0.3, 0.4, 0.5, 0.6]}
    cities = sorted({r["city"] for r in runs})
    held_flags: dict[str, bool] = {}
    print("\nleave one city out (limits chosen on the other cities):")
    for city in cities:
        train = [r for r in runs if r["city"] != city]
        best, best_key = None, None
        for values in itertools.product(*grid.values()):
            rule = dataclasses.replace(base, **dict(zip(grid, values)))
            f = [rule.judge(r["figures"]).status != "ok" for r in train]
            missed = sum(r["gross"] and not x for r, x in zip(train, f))
            false = sum(r["accurate"] and x for r, x in zip(train, f))
            # then the middle of the grid among equals: limits away from the runs that decided them
            spread = sum(abs(v - np.median(g)) for v, g in zip(values, grid.values()))
            key = (missed, false, spread)
            if best_key is None or key < best_key:
                best, best_key = rule, key
        test = [r for r in runs if r["city"] == city]
        for r in test:
            held_flags[r["name"]] = best.judge(r["figures"]).status != "ok"
        chosen = {k: getattr(best, k) for k in grid}
        print(f"  {city:12s} chosen {chosen}  train missed {best_key[0]}, false flags {best_key[1]}; "
              f"held out: {confusion(test, [held_flags[r['name']] for r in test])}")
    print(f"\nheld-out, all cities: {confusion(runs, [held_flags[r['name']] for r in runs])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
