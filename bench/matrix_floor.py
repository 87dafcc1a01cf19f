"""Is a variant of the real-city matrix better than the matrix's own run-to-run spread?

    .venv/bin/python bench/matrix_floor.py --base KEY [KEY ...] [--variant KEY [KEY ...]]

Each KEY is one matrix run of data/cities/results.json (``bench/cities.py --tag``). The keys of
``--base`` are replicas of one code state, run on inputs that should not matter, e.g. without
``--set`` and with ``--set street_scale=1.001`` and ``0.999`` (the frame's units scaled by 0.1 %;
every such run settles at scale 1); those of ``--variant`` the same replicas of the changed code.
The method's discrete steps (route-placement cells, search pixels, which segments pass the
consistency check) turn such changes into different picks, so a run's figures have a spread with
no change of code at all, and one matrix run per state cannot tell a change from that spread.

Printed: the bar count of every key; the runs that flip the bar between base replicas (the floor);
per run, the base replicas' horizontal median and p95; then, with a variant, its mean bar count
against the base's, and the runs whose median over the variant's replicas lies below / above the
base replicas' range (better / worse), for the horizontal median and for the p95.

``--retry``: what "run an unreliable registration again on the next replica's input, keep the first
``ok`` one (else the first, or else the most confident)" would give, the base keys taken in the
order given (bench/RESULTS.md, the retry section).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import statistics

from cities import RESULTS, meets_bar, status_cells


def rows_of(results: dict, key: str) -> dict[tuple, dict]:
    """(scene, source, gps) → row of one matrix run."""
    if key not in results:
        raise SystemExit(f"{key}: not in {RESULTS}")
    return {(r["scene"], r["source"], bool(r["gps"])): r for r in results[key]["rows"]}


def figures(row: dict) -> tuple[float, float]:
    """(horizontal median, p95), inf for a run without a result."""
    h, p = row.get("horizontal_median_m"), row.get("p95_m")
    return (float("inf") if h is None else h, float("inf") if p is None else p)


def bar_count(state: dict, runs: list[tuple]) -> int:
    return sum(meets_bar(state[r]) for r in runs)


def beyond(variant: list[dict], base: list[dict], runs: list[tuple], f: int) -> tuple[int, int]:
    """Runs whose median over the variant replicas of figure f lies below / above the base replicas' range."""
    below = above = 0
    for r in runs:
        v = statistics.median(figures(s[r])[f] for s in variant)
        below += v < min(figures(s[r])[f] for s in base)
        above += v > max(figures(s[r])[f] for s in base)
    return below, above


def summary(rows: list[dict]) -> str:
    """Bar count, runs > 2 m off, those `ok`, `ok` runs with p95 > 3 m, geometric mean of the
    horizontal medians and the status × accuracy confusion of one set of runs."""
    h = [figures(r)[0] for r in rows]
    ok = [r.get("status") == "ok" for r in rows]
    bar = [meets_bar(r) for r in rows]
    conf = status_cells(ok, bar)
    geo = math.exp(statistics.mean(math.log(min(v, 1e3)) for v in h))
    return (f"bar {sum(bar):2d}  > 2 m {sum(v > 2 for v in h)}  ok & > 2 m {sum(o and v > 2 for o, v in zip(ok, h))}  "
            f"ok & p95 > 3 m {sum(o and figures(r)[1] > 3 for o, r in zip(ok, rows))}  geo-mean h {geo:.3f} m  "
            f"flagged&acc / flagged&not / ok&acc / ok&not {'/'.join(map(str, conf))}")


def retried(base: list[dict], runs: list[tuple], fallback) -> list[dict]:
    """Each run's first `ok` replica in the order given, else ``fallback`` of its replicas."""
    return [next((s[r] for s in base if s[r].get("status") == "ok"), None) or fallback([s[r] for s in base])
            for r in runs]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--base", nargs="+", required=True, help="replicas of the base code (matrix-run keys)")
    ap.add_argument("--variant", nargs="*", default=[], help="the same replicas of the changed code")
    ap.add_argument("--retry", action="store_true", help="simulate retrying unreliable runs on the next base replica")
    args = ap.parse_args()
    results = json.loads(RESULTS.read_text())
    base = [rows_of(results, k) for k in args.base]
    variant = [rows_of(results, k) for k in args.variant]
    runs = sorted(set(base[0]).intersection(*map(set, base[1:] + variant)))
    print(f"{len(runs)} runs in every key")
    for i, (key, state) in enumerate(zip(args.base + args.variant, base + variant)):
        print(f"  {'base' if i < len(base) else 'variant':7s} {key:36s} meet the bar {bar_count(state, runs):3d}")
    pairs = list(itertools.combinations(range(len(base)), 2))
    flips = [sum(meets_bar(base[i][r]) != meets_bar(base[j][r]) for r in runs) for i, j in pairs]
    print(f"the floor: runs that flip the bar between two base replicas: {flips}" if flips
          else "the floor: one base replica, no spread to show (give two or more)")
    print(f"\n{'scene':17s} {'source':9s} gps  h median, base replicas    p95, base replicas")
    for r in runs:
        h = " ".join(f"{figures(s[r])[0]:6.2f}" for s in base)
        p = " ".join(f"{figures(s[r])[1]:6.2f}" for s in base)
        print(f"{r[0]:17s} {r[1]:9s} {'yes' if r[2] else 'no ':3s}  {h:24s}  {p}")
    if args.retry:
        print("\nretry an unreliable run on the next replica's input (base keys in the order given):")
        for i, key in enumerate(args.base):
            print(f"  {key:36s} {summary([base[i][r] for r in runs])}")
        for n in range(2, len(base) + 1):
            for name, pick in (("the first", lambda rs: rs[0]),
                               ("the most confident", lambda rs: max(rs, key=lambda r: r.get("confidence") or 0))):
                print(f"  {n} tries, else {name:18s} {summary(retried(base[:n], runs, pick))}")
    if variant:
        mean = [statistics.mean(bar_count(s, runs) for s in g) for g in (base, variant)]
        hb, ha = beyond(variant, base, runs, 0)
        pb, pa = beyond(variant, base, runs, 1)
        print(f"\nmean bar count: base {mean[0]:.1f}, variant {mean[1]:.1f}; runs whose variant median lies "
              f"outside the base range, better / worse: h median {hb} / {ha}, p95 {pb} / {pa}")


if __name__ == "__main__":
    main()
