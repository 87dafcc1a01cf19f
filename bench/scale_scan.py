"""The no-GPS street-scale scan with its default search and with variants, on the same segments.

    .venv/bin/python bench/scale_scan.py SCENE_DIR ... [--recipes dsm,osm,label_map]
        [--variant coarse_factor=3,fine_rotation_reach_deg=15 ...] [--jobs 2]

For every scene folder and recipe the over-view and street steps run once (street/gps.csv hidden,
``street_scale: auto``), then the first pass of ``toolkit.street_scale.scale_from_matching`` (the
scan of ``toolkit.matching.route_scale``) runs with the default ``ScaleSearchConfig`` and then with
each variant (its fields set as given), back to back in the same process. One row per scan: the
scan's factor, prominence and the scale the run would go on at ("again": the street step runs
again at it; "*": the prominence is below the threshold, the first guess stays), and each variant's time ÷ the default's on the same
segments. The summary counts the runs whose decision changed (a scale 0.5 % or more apart, or a
street pass more or less), the largest change of a factor the default took, and the time ratio over all runs (sum ÷ sum).
With ``--jobs 2`` two runs go at once, one thread each (the ratios still compare scans of one
process; absolute seconds are then slower).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from _common import REPO


def parse_variant(text: str) -> dict:
    out = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        out[key.strip()] = float(value)
    return out


def scan_run(task: tuple[str, str, list[dict], int]) -> list[dict]:
    from toolkit.capture import StreetCapture
    from toolkit.matching.route_scale import ScaleSearchConfig
    from toolkit.observe import NullObserver
    from toolkit.recipe import load_recipe
    from toolkit.runner import build
    from toolkit.street_scale import resolve_street_scale, scale_from_matching

    scene_dir, recipe, variants, workers = task
    plan = build(load_recipe(str(REPO / "recipes" / f"{recipe}.yaml")), scene=Path(scene_dir))
    scene = dataclasses.replace(plan.scene, files=dataclasses.replace(plan.scene.files, gps=None))
    scene = resolve_street_scale(scene, plan.recipe.street_scale, plan.recipe.path)
    stages = {spec.name: stage for spec, stage in plan.stages}
    obs = NullObserver()
    overview = stages["overview"](scene=scene, obs=obs)
    capture = StreetCapture(scene)
    street = stages["street"](scene=scene, capture=capture, obs=obs)
    cfg = stages["unary"].params.route_prior
    rows = []
    for variant in [{}, *variants]:
        t0 = time.perf_counter()
        new = scale_from_matching(capture.scale, street, overview, capture, cfg, workers=workers,
                                  search=ScaleSearchConfig(**variant))
        seconds = time.perf_counter() - t0
        scan = new.matching.get("pass_1", {})
        rows.append({"scene": Path(scene_dir).name, "recipe": recipe, "variant": variant, "seconds": seconds,
                     "factor": scan.get("factor"), "prominence": scan.get("prominence"),
                     "at": capture.scale.value, "next": new.value, "settled": new.settled,
                     "kept": new.matching.get("reason", "").startswith("no distinct")})
    return rows


def decision(row: dict) -> str:
    """The scale the run goes on at ('again': the street step runs again at it); '*': no distinct
    peak, the first guess stays (a warning, the same scale)."""
    return f"{row['next']:.4g}{'' if row['settled'] else ' again'}{'*' if row['kept'] else ''}"


def moved(row: dict, base: dict) -> bool:
    """Whether a variant sends the run on differently: another scale (beyond 0.5 %), or a street pass
    more or less."""
    return row["settled"] != base["settled"] or abs(row["next"] / base["next"] - 1) > 0.005


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenes", nargs="+", type=Path)
    ap.add_argument("--recipes", default="dsm,osm,label_map")
    ap.add_argument("--variant", action="append", default=[], help="ScaleSearchConfig fields, e.g. fine_rotation_reach_deg=15")
    ap.add_argument("--jobs", type=int, default=1)
    args = ap.parse_args()
    from toolkit.threads import thread_budget

    variants = [parse_variant(v) for v in args.variant]
    workers = 1 if args.jobs > 1 else thread_budget()
    tasks = [(str(s), r, variants, workers) for s in args.scenes for r in args.recipes.split(",")]
    names = ["default", *(",".join(f"{k}={v:g}" for k, v in v.items()) for v in variants)]
    print(f"{'scene':18s} {'recipe':9s} " + " ".join(f"{n[:30]:>40s}" for n in names), flush=True)
    changed = [0] * len(variants)
    dfactor = [0.0] * len(variants)
    seconds = [0.0] * (1 + len(variants))
    with ProcessPoolExecutor(max(args.jobs, 1)) as pool:
        for rows in pool.map(scan_run, tasks):
            cells = []
            for i, row in enumerate(rows):
                seconds[i] += row["seconds"]
                ratio = "" if i == 0 else f" {row['seconds'] / rows[0]['seconds']:.2f}x"
                cells.append(f"{row['factor'] or 0:.4f} z{row['prominence'] or 0:5.1f} {decision(row):>14s}"
                             f" {row['seconds']:5.1f}s{ratio}")
                if i:
                    changed[i - 1] += moved(row, rows[0])
                    if row["factor"] and rows[0]["factor"] and not rows[0]["kept"]:
                        dfactor[i - 1] = max(dfactor[i - 1], abs(row["factor"] / rows[0]["factor"] - 1))
            print(f"{rows[0]['scene']:18s} {rows[0]['recipe']:9s} " + " ".join(f"{c:>40s}" for c in cells), flush=True)
    for i, name in enumerate(names[1:]):
        print(f"{name}: decision changed in {changed[i]} of {len(tasks)} runs; largest change of a factor taken "
              f"{dfactor[i]:.2%}; time {seconds[i + 1] / seconds[0]:.2f}x the default's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
