"""Leave-one-city-out choice between variants of the real-city matrix (bench/cities.py rows).

    .venv/bin/python bench/choose_loco.py BASE_STATE [VARIANT_STATE ...]

Each state is a key of data/cities/results.json (``git rev-parse --short HEAD`` of the run, with
"+TAG" for a variant run with ``bench/cities.py --set … --tag TAG``); a comma-separated list of
keys is one state whose rows are merged (runs of the same code under several keys); without
variants, every "BASE_STATE+TAG" key is taken. Only (scene, source, gps) runs present in every state are compared.
For each city, the variant is chosen on the other cities' runs (the most runs meeting the bar less
gross failures, horizontal median > 2 m or no result; then the lowest median horizontal median), and
the held-out city's runs are scored with it. Printed: per city
the choice and its held-out figures, the held-out totals, and each variant's totals for reference
(those are scored on every city, so they do not choose anything).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from _common import REPO
from cities import meets_bar as meets

RESULTS = REPO / "data" / "cities" / "results.json"
GROSS_M = 2.0


def _h(row: dict) -> float:
    return row["horizontal_median_m"] if row.get("horizontal_median_m") is not None else float("inf")


def score(rows: list[dict]) -> tuple[int, float]:
    """(runs meeting the bar − gross failures, −median horizontal median): higher is better."""
    h = [_h(r) for r in rows]
    return sum(meets(r) for r in rows) - sum(v > GROSS_M for v in h), -float(np.median(h)) if h else 0.0


def describe(rows: list[dict]) -> str:
    h = np.array([_h(r) for r in rows])
    return (f"{sum(meets(r) for r in rows)}/{len(rows)} meet, {int((h > GROSS_M).sum())} gross, "
            f"median h median {np.median(h):.2f} m")


def city_of(scene: str) -> str:
    return scene.rsplit("-", 1)[0]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("base")
    ap.add_argument("variants", nargs="*")
    args = ap.parse_args()
    data = json.loads(RESULTS.read_text())
    last = args.base.split(",")[-1]
    states = [args.base] + (args.variants or sorted(k for k in data if k.startswith(last + "+")))
    missing = [k for s in states for k in s.split(",") if k not in data]
    if missing or len(states) < 2:
        sys.exit(f"{RESULTS}: states {missing or states} missing; known: {', '.join(sorted(data))}")
    key = lambda r: (r["scene"], r["source"], r["gps"])  # noqa: E731
    rows = {s: {key(r): r for k in s.split(",") for r in data[k]["rows"]} for s in states}
    common = sorted(set.intersection(*(set(v) for v in rows.values())))
    cities = sorted({city_of(k[0]) for k in common})
    print(f"{len(common)} runs in all of {', '.join(states)}")
    held: list[dict] = []
    for city in cities:
        train = [k for k in common if city_of(k[0]) != city]
        test = [k for k in common if city_of(k[0]) == city]
        best = max(states, key=lambda s: score([rows[s][k] for k in train]))
        got = [rows[best][k] for k in test]
        held += got
        print(f"  {city:12s} chosen {best:24s} held out: {describe(got)}")
    print(f"held out, all cities: {describe(held)}")
    for s in states:
        print(f"  {s:24s} (every city, for reference): {describe([rows[s][k] for k in common])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
