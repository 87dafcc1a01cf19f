"""No-GPS matching (graph + unary + match) time ÷ one Open3D estimate_normals pass on the same cloud.

Target: ≤ 2× on a 1.5 km real-city loop. With ``street_scale: auto`` (the default) a run without GPS
also checks the street scale against the over-view once after the street step (the scan of
``toolkit.matching.route_scale``): it is timed as well, and "ratio+scale" divides the two together. The over-view and street steps are run first (not timed);
the normals pass (KNN 20) is timed right before and right after the matching and the two averaged,
so that a change of machine load biases the ratio less. street/gps.csv is hidden from the data term.
Also prints the route placement's summary and, when the scene has truth, the segment-match
precision/recall.

usage: python bench/matching_vs_normals.py SCENE_DIR [--recipe recipes/osm.yaml ...]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

from _common import REPO, normals_pass_seconds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--recipe", action="append", default=[], help="recipes whose steps are used (default: all three)")
    args = ap.parse_args()

    from toolkit.capture import StreetCapture
    from toolkit.observe import NullObserver
    from toolkit.recipe import load_recipe
    from toolkit.runner import build
    from toolkit.scene import load_array, load_points

    recipes = args.recipe or [str(REPO / "recipes" / f"{r}.yaml") for r in ("dsm", "osm", "label_map")]
    from toolkit.street_scale import resolve_street_scale, scale_from_matching
    from toolkit.threads import thread_budget

    print(f"{'recipe':10s} {'normals s':>9s} {'match s':>8s} {'ratio':>6s}  {'unary':>6s} {'bp':>5s} "
          f"{'scale s':>7s} {'ratio+scale':>11s} {'conv':>5s} {'prec':>5s} {'rec':>5s}  route placement")
    worst = worst_all = 0.0
    for path in recipes:
        plan = build(load_recipe(path), scene=args.scene)
        scene = dataclasses.replace(plan.scene, files=dataclasses.replace(plan.scene.files, gps=None))
        scene = resolve_street_scale(scene, plan.recipe.street_scale, plan.recipe.path)  # as without gps.csv
        stages = {spec.name: stage for spec, stage in plan.stages}
        obs = NullObserver()
        overview = stages["overview"](scene=scene, obs=obs)
        capture = StreetCapture(scene)
        street = stages["street"](scene=scene, capture=capture, obs=obs)
        points = load_points(scene)
        before = normals_pass_seconds(points)
        ts = time.perf_counter()
        if not capture.scale.settled:  # the run's one check of the scale (a second street pass if it moves)
            unary_cfg = stages["unary"].params.route_prior
            scale_from_matching(capture.scale, street, overview, capture, unary_cfg, workers=thread_budget())
        t0 = time.perf_counter()
        graphs = stages["graph"](street=street, overview=overview, obs=obs)
        t1 = time.perf_counter()
        costs = stages["unary"](graphs=graphs, street=street, overview=overview, scene=scene, capture=capture,
                                obs=obs)
        t2 = time.perf_counter()
        matches = stages["match"](graphs=graphs, costs=costs, obs=obs)
        t3 = time.perf_counter()
        after = normals_pass_seconds(points)
        normals = (before + after) / 2
        ratio = (t3 - t0) / normals
        ratio_all = (t3 - ts) / normals
        worst, worst_all = max(worst, ratio), max(worst_all, ratio_all)
        prec = rec = float("nan")
        if scene.has("truth_street_labels") and scene.has("truth_buildings"):
            from toolkit.evaluation.truth import read_true_buildings, segment_match_scores

            ids, geoms = read_true_buildings(scene.files.truth_buildings, scene.crs)
            s = segment_match_scores(matches, street, overview, load_array(scene, "truth_street_labels"), ids, geoms)
            prec, rec = s["precision"], s["recall"]
        placement = next((w for w in obs.warnings if "route placement" in w), "used")
        print(f"{Path(path).stem:10s} {normals:9.2f} {t3 - t0:8.2f} {ratio:6.2f}  {t2 - t1:6.2f} {t3 - t2:5.2f} "
              f"{t0 - ts:7.2f} {ratio_all:11.2f} {str(matches.converged):>5s} {prec:5.2f} {rec:5.2f}  {placement}",
              flush=True)
    print(f"worst ratio {worst:.2f}, with the scale check {worst_all:.2f} (target ≤ 2)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
