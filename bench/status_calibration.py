"""How well the run status (toolkit/status.py) tells failed runs from good ones, city by city.

Reads the runs of bench/cities.py (``--out-dir``, repeatable: e.g. every replica and the held-out
matrix; ``--all``: every output folder of both matrices, also those bench/cities.py slimmed to their
metrics and logs; <dir>/*/metrics.json: the truth-free ``assessment`` and the truth figures; a run found twice
counts once), and prints:
- the confusion table (flagged × accurate) of the current rule (StatusRule's defaults), and its gross
  failures (horizontal median > 2 m) that were not flagged;
- a leave-one-city-out choice of the rule's main hard limits (façade distance and support, registered
  point share, median segment scale, neighbour disagreement) and of ``min_confidence``: for each city, the limits are chosen on the other
  cities' runs only (every gross failure there flagged, then the fewest accurate runs flagged,
  then the limits farthest from the runs that decided them), and the held-out city's runs are
  judged with them. Nothing is re-run: ``StatusRule.judge`` works from the stored figures.
- a leave-one-city-out choice of ``min_confidence`` alone, the other limits at their defaults:
  every gross failure flagged, then the fewest accurate runs flagged, then the most
  inaccurate runs flagged, then the middle of the values that do equally well (the confidence
  limit is the rule's catch-all for runs no hard limit names; the full grid above takes minutes on
  several hundred runs, ``--confidence-only`` skips it).
- ``--limit NAME``: a leave-one-city-out choice of that one hard limit alone, with the balanced
  objective: every gross failure flagged, at most a tenth of the accurate runs flagged, then the
  fewest runs judged wrong either way (a run that misses the bar's p95 counts as inaccurate).

usage: python bench/status_calibration.py [--out-dir data/cities/out ...] [--all [--holdout2]]
       [--confidence-only | --limit NAME]
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
    """The runs of one output folder of bench/cities.py; their scenes are its parent's folders."""
    runs = []
    for m_path in sorted(out_dir.glob("*/metrics.json")):
        m = json.loads(m_path.read_text())
        truth = m.get("truth") or {}
        if not truth or "assessment" not in m:
            continue
        name = m_path.parent.name
        stamp_path = out_dir.parent / _scene_of(name) / "stamp.json"  # data/cities or data/cities-holdout
        stamp = json.loads(stamp_path.read_text()) if stamp_path.is_file() else {}
        h = truth["horizontal"]["median_m"]
        recipe = name.removesuffix("-gps")[len(_scene_of(name)) + 1:]
        p95 = truth["error_3d"]["p95_m"] if recipe == "dsm" else truth["horizontal"]["p95_m"]
        rigid = stamp.get("rigid_mean_m")
        accurate = h <= 0.5 and p95 <= 1.5 and (rigid is None or truth["error_3d"]["mean_m"] < rigid)
        runs.append({"name": name, "city": _city_of(name), "h": h, "accurate": accurate,
                     "gross": h > GROSS_M, "figures": m["assessment"], "status": m["status"], "dir": f"{out_dir.parent.name}/{out_dir.name}",
                     "same": (out_dir.parent.name, name, h, truth["error_3d"]["mean_m"])})
    return runs


def load_all(out_dirs: list[Path]) -> list[dict]:
    """The runs of several output folders; a run found twice (the same scene of the same matrix with
    the same truth errors: the same registration, e.g. a code change that did not touch it) counts once."""
    seen, runs = set(), []
    for out_dir in out_dirs:
        for r in load_runs(out_dir):
            if r["same"] not in seen:
                seen.add(r["same"])
                runs.append(r)
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


def flags(rule, runs: list[dict]) -> list[bool]:
    """Whether ``rule`` judges each run unreliable."""
    return [rule.judge(r["figures"]).status != "ok" for r in runs]


def tally(runs: list[dict], flagged: list[bool]) -> tuple[int, int, int]:
    """(gross failures not flagged, accurate runs flagged, inaccurate runs flagged)."""
    return (sum(r["gross"] and not f for r, f in zip(runs, flagged)),
            sum(r["accurate"] and f for r, f in zip(runs, flagged)),
            sum(not r["accurate"] and f for r, f in zip(runs, flagged)))


def choose_value(runs: list[dict], base, name: str, grid: list[float], balanced: bool = False) -> tuple[float, tuple]:
    """The value of the rule's field ``name`` on ``runs``: no gross failure missed, then fewest
    accurate runs flagged, then most inaccurate runs flagged (``balanced``: no gross failure missed,
    at most a tenth of the accurate runs flagged, then the fewest runs judged wrong either way, an
    inaccurate run being one that misses the bar's median or p95); among the values that do equally
    well, the middle one (farthest from the runs that decided the range)."""
    n_accurate = sum(r["accurate"] for r in runs)
    n_inaccurate = len(runs) - n_accurate
    keys = []
    for value in grid:
        missed, false, caught = tally(runs, flags(dataclasses.replace(base, **{name: value}), runs))
        keys.append((missed, false > 0.1 * n_accurate, false + n_inaccurate - caught) if balanced
                    else (missed, false, -caught))
    best = min(keys)
    equal = [v for v, k in zip(grid, keys) if k == best]
    middle = (equal[0] + equal[-1]) / 2
    return min(equal, key=lambda v: (round(abs(v - middle), 6), v)), best + ((equal[0], equal[-1]),)


def loco_one(runs: list[dict], base, name: str, grid: list[float], balanced: bool = False) -> None:
    """``choose_value`` leave one city out: each city judged with the value chosen on the others."""
    cities = sorted({r["city"] for r in runs})
    held: dict[int, bool] = {}
    objective = "balanced errors" if balanced else "fewest false flags"
    print(f"\n{name} alone, leave one city out (grid {grid[0]}-{grid[-1]}; {objective}; "
          "the other limits at their defaults):")
    for city in cities:
        value, key = choose_value([r for r in runs if r["city"] != city], base, name, grid, balanced)
        test = [r for r in runs if r["city"] == city]
        held.update(zip(map(id, test), flags(dataclasses.replace(base, **{name: value}), test)))
        print(f"  {city:12s} chosen {value:g}  train key {key[:-1]} (equally good {key[-1][0]:g}-{key[-1][1]:g}); "
              f"held out: {confusion(test, [held[id(r)] for r in test])}")
    print(f"held-out, all cities: {confusion(runs, [held[id(r)] for r in runs])}")
    value, key = choose_value(runs, base, name, grid, balanced)
    print(f"chosen on all cities: {value:g}, equally good {key[-1][0]:g}-{key[-1][1]:g} "
          f"({confusion(runs, flags(dataclasses.replace(base, **{name: value}), runs))})")
    for r in runs:
        if held[id(r)] and r["accurate"]:
            print(f"  held-out flagged accurate run: {r['dir']}/{r['name']} (confidence "
                  f"{base.judge(r['figures']).confidence:.2f})")


def confidence_only(runs: list[dict], base) -> None:
    loco_one(runs, base, "min_confidence", [round(v, 2) for v in np.arange(0.3, 0.801, 0.05)])


# one hard limit chosen alone (--limit NAME): its grid
LIMIT_GRIDS = {"max_route_overruled_share": [round(v, 2) for v in np.arange(0.0, 1.001, 0.05)],
               "max_camera_gap_p90_m": [float(v) for v in range(10, 101, 5)],
               "min_registered_point_share": [round(v, 2) for v in np.arange(0.3, 0.951, 0.05)]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out-dir", type=Path, action="append",
                    help="a bench/cities.py output folder (repeatable; default data/cities/out)")
    ap.add_argument("--all", action="store_true",
                    help="every output folder of data/cities and data/cities-holdout (whole or slimmed)")
    ap.add_argument("--confidence-only", action="store_true", help="only the min_confidence choice")
    ap.add_argument("--limit", choices=sorted(LIMIT_GRIDS),
                    help="only this hard limit, chosen alone with the balanced objective")
    ap.add_argument("--holdout2", action="store_true", help="with --all: data/cities-holdout2 too")
    args = ap.parse_args()
    from toolkit.status import StatusRule

    matrices = ("cities", "cities-holdout") + (("cities-holdout2",) if args.holdout2 else ())
    everything = [d for matrix in matrices for d in sorted((REPO / "data" / matrix).glob("out*/"))]
    out_dirs = (args.out_dir or []) + (everything if args.all else [])
    out_dirs = out_dirs or [REPO / "data" / "cities" / "out"]
    runs = load_all(out_dirs)
    if not runs:
        raise SystemExit(f"{', '.join(map(str, out_dirs))}: no runs with truth and an assessment "
                         "(run bench/cities.py first)")
    base = StatusRule()  # the current defaults (runs of older states were judged with their own rule)
    flagged = flags(base, runs)
    print(f"{len(runs)} runs; the current rule: {confusion(runs, flagged)}")
    for r, f in zip(runs, flagged):
        if r["gross"] and not f:
            print(f"  unflagged gross failure: {r['dir']}/{r['name']} (h median {r['h']:.1f} m)")
        if r["accurate"] and f:
            print(f"  flagged accurate run: {r['dir']}/{r['name']}: {base.judge(r['figures']).reasons[:1]}")
    if args.limit:
        loco_one(runs, base, args.limit, LIMIT_GRIDS[args.limit], balanced=True)
        return 0
    if args.confidence_only:
        confidence_only(runs, base)
        return 0

    grid = {"max_facade_distance_median_m": [0.8, 1.0, 1.2, 1.5, 2.0],
            "min_facade_support_share": [0.2, 0.3, 0.4, 0.5, 0.6],
            "min_registered_point_share": [0.2, 0.3, 0.4, 0.5],
            "max_segment_scale_deviation": [0.02, 0.025, 0.035, 0.05, 0.07],
            "max_neighbour_disagree_share": [0.2, 0.3, 0.4, 0.5, 0.6],
            "min_confidence": [0.3, 0.4, 0.5, 0.6]}
    cities = sorted({r["city"] for r in runs})
    held_flags: dict[int, bool] = {}
    print("\nleave one city out (limits chosen on the other cities):")
    for city in cities:
        train = [r for r in runs if r["city"] != city]
        best, best_key = None, None
        for values in itertools.product(*grid.values()):
            rule = dataclasses.replace(base, **dict(zip(grid, values)))
            missed, false, _ = tally(train, flags(rule, train))
            # then the middle of the grid among equals: limits away from the runs that decided them
            spread = sum(abs(v - np.median(g)) for v, g in zip(values, grid.values()))
            key = (missed, false, spread)
            if best_key is None or key < best_key:
                best, best_key = rule, key
        test = [r for r in runs if r["city"] == city]
        held_flags.update(zip(map(id, test), flags(best, test)))
        chosen = {k: getattr(best, k) for k in grid}
        print(f"  {city:12s} chosen {chosen}  train missed {best_key[0]}, false flags {best_key[1]}; "
              f"held out: {confusion(test, [held_flags[id(r)] for r in test])}")
    print(f"\nheld-out, all cities: {confusion(runs, [held_flags[id(r)] for r in runs])}")
    confidence_only(runs, base)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
