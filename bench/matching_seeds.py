"""Segment matching on the campus seeds × over-view sources: precision / recall and energies per solver.

    .venv/bin/python bench/matching_seeds.py [--scenes campus,bench-campus-1,...]
        [--recipes dsm.yaml,osm.yaml,label_map.yaml] [--solvers loopy_bp,trws,icm,greedy]
        [--no-gps] [--diagnose] [-s steps.unary.params.KEY=VALUE] [--cache-dir /tmp/cv_match]

For each scene and recipe: overview and street (cached: street per scene, overview per scene and
recipe, under --cache-dir, seeded from data/.bench-cache when bench/refine_warp_ba.py made them),
then graph.knn and unary.distance_map (cached under a key that includes the source of the matching
modules, so editing them recomputes), then every solver with the recipe's match parameters.
Precision / recall are ``toolkit.evaluation.truth.segment_match_scores`` (what evaluate.chamfer
reports). --no-gps hides street/gps.csv from the unary stage. --diagnose lists the wrong matches
of loopy_bp with what they hit (another building, a non-building segment) and their confidence.
Acceptance (issue 6): loopy_bp precision ≥ 0.95 and recall ≥ 0.85; E(trws) ≤ E(bp) ≤ E(icm).
The default scenes (seeds 0-4) are the acceptance set; parameters are chosen on the held-out seeds
(--scenes bench-campus-5,bench-campus-6,bench-campus-7) and only then run on seeds 0-4.
The graph+unary cache key includes the street and over-view segment centroids, so a street step
recomputed by changed code never meets graphs built on the old segments.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import logging
import pickle
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from refine_warp_ba import cache_path  # noqa: E402
from toolkit.capture import StreetCapture  # noqa: E402
from toolkit.observe import NullObserver  # noqa: E402
from toolkit.recipe import load_recipe  # noqa: E402
from toolkit.runner import build  # noqa: E402

SOLVERS = {"loopy_bp": "match.loopy_bp", "trws": "match.trws", "icm": "match.icm", "greedy": "match.greedy"}
MATCHING_SOURCES = ["plugins/graph_knn.py", "plugins/unary_distance_map.py", "toolkit/matching/chamfer.py",
                    "toolkit/matching/anchors.py", "toolkit/matching/atlas.py", "toolkit/matching/gps.py",
                    "toolkit/matching/conjugate.py"]


def _load_or_run(path: Path, seed_path: Path | None, make, label: str):
    for p in (path, seed_path):
        if p is not None and p.is_file():
            with open(p, "rb") as fh:
                value = pickle.load(fh)
            if p != path:
                path.parent.mkdir(parents=True, exist_ok=True)
                with open(path, "wb") as fh:
                    pickle.dump(value, fh)
            return value
    t0 = time.perf_counter()
    value = make()
    print(f"  ({label} ran in {time.perf_counter() - t0:.1f} s)", flush=True)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        pickle.dump(value, fh)
    return value


def front(recipe_path: Path, scene_dir: Path, cache_dir: Path, use_gps: bool, overrides: tuple[str, ...] = ()):
    """(plan, street, overview, graphs, costs, unary seconds or None when cached)."""
    plan = build(load_recipe(recipe_path, overrides), scene=scene_dir)
    stages = {spec.name: (spec, st) for spec, st in plan.stages}
    scene = plan.scene
    obs = NullObserver()
    # local copies carry cache_path's key (scene, every stage's source, the step specs): a street step
    # cached under another configuration (e.g. the terrace split on) is never reused
    street_key, ov_key = cache_path(plan, scene_dir, "street"), cache_path(plan, scene_dir, "overview")
    street = _load_or_run(cache_dir / street_key.name, street_key,
                          lambda: stages["street"][1](scene=scene, capture=plan.capture, obs=obs),
                          f"{scene_dir.name} street")
    ov_spec = stages["overview"][0]
    overview = _load_or_run(cache_dir / ov_key.name, ov_key,
                            lambda: stages["overview"][1](scene=scene, obs=obs), f"{scene_dir.name} {ov_spec.use}")
    src = b"".join((REPO / f).read_bytes() for f in MATCHING_SOURCES)
    spec_txt = "|".join(f"{stages[k][0].use}{sorted(stages[k][0].params.items())}" for k in ("graph", "unary"))
    # the street / over-view segments are part of the key: a cached street step made by other code
    # (its stage changed) must not meet graphs and costs built on the old segments
    data = b"".join(np.ascontiguousarray(np.asarray(x.centroids, dtype=np.float64)).tobytes()
                    for x in (street, overview))
    h = hashlib.sha1(src + spec_txt.encode() + str(use_gps).encode() + data).hexdigest()[:12]
    unary_scene = scene if use_gps else dataclasses.replace(scene, files=dataclasses.replace(scene.files, gps=None))
    timing = {}

    def make_front():
        graphs = stages["graph"][1](street=street, overview=overview, obs=obs)
        t0 = time.perf_counter()
        costs = stages["unary"][1](graphs=graphs, street=street, overview=overview, scene=unary_scene,
                                   capture=StreetCapture(unary_scene), obs=obs)
        timing["unary"] = time.perf_counter() - t0
        return graphs, costs

    graphs, costs = _load_or_run(cache_dir / f"{scene_dir.name}-{ov_spec.use}-gu-{h}.pkl", None, make_front,
                                 f"{scene_dir.name} {ov_spec.use} graph+unary")
    return plan, street, overview, graphs, costs, timing.get("unary")


def cover_precision(m, truth, sc: dict) -> float | None:
    """Share of matched street segments whose true building lies ≥ 50 % inside the matched over-view
    segment. Unlike the official metric (the over-view segment's best-IoU building must be the
    street segment's), it accepts one over-view segment covering several buildings (merged OSM
    footprints, label-map blobs)."""
    from toolkit.evaluation.truth import rasterise_buildings

    street, overview, _, ids, geoms = truth
    key = id(overview)
    if key not in _COVER_CACHE:
        bi = rasterise_buildings(ids, geoms, overview.grid).ravel()
        seg = overview.label_image.ravel().astype(np.int64)
        both = (bi >= 0) & (seg >= 0)
        nb = len(ids)
        inter = np.bincount(seg[both] * nb + bi[both], minlength=len(overview) * nb).reshape(len(overview), nb)
        area = np.bincount(bi[bi >= 0], minlength=nb)
        _COVER_CACHE.clear()
        _COVER_CACHE[key] = (inter / np.maximum(area, 1)[None, :], {int(b): i for i, b in enumerate(ids)})
    share, index = _COVER_CACHE[key]
    tb = sc["_per_segment"]["true_building"]
    matched = np.flatnonzero(m.segment_match >= 0)
    if len(matched) == 0:
        return None
    ok = [tb[s] >= 0 and share[m.segment_match[s], index[int(tb[s])]] >= 0.5 for s in matched]
    return float(np.mean(ok))


_COVER_CACHE: dict = {}


def truth_of(scene, street, overview):
    from toolkit.evaluation.truth import read_true_buildings

    ids, geoms = read_true_buildings(scene.files.truth_buildings, scene.crs)
    return street, overview, np.load(scene.files.truth_street_labels), ids, geoms


def diagnose(m, graphs, costs, sc: dict, street) -> list[str]:
    """One line per wrong or missed loopy_bp match."""
    per = sc["_per_segment"]
    tb, mb, ok, cp = per["true_building"], per["matched_building"], per["correct"], per["has_counterpart"]
    cent = np.asarray(street.centroids).reshape(-1, 2)
    lines = []
    for s in range(len(tb)):
        wrong = m.segment_match[s] >= 0 and not ok[s]
        missed = m.segment_match[s] < 0 and cp[s]
        if not (wrong or missed):
            continue
        deg = graphs.street_graph.degree(s)
        kind = "WRONG " if wrong else "missed"
        tgt = f"ov {m.segment_match[s]:4d} (building {mb[s]})" if wrong else "null"
        lines.append(f"    {kind} street seg {s:4d} true building {tb[s]:5d} → {tgt}  conf {m.confidence[s]:.2f} "
                     f"cost {m.cost[s]:.2f} degree {deg} centroid ({cent[s, 0]:.0f}, {cent[s, 1]:.0f})")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", default="campus,bench-campus-1,bench-campus-2,bench-campus-3,bench-campus-4")
    ap.add_argument("--recipes", default="dsm.yaml,osm.yaml,label_map.yaml")
    ap.add_argument("--solvers", default="loopy_bp,trws,icm,greedy")
    ap.add_argument("--no-gps", action="store_true")
    ap.add_argument("--diagnose", action="store_true")
    ap.add_argument("--cache-dir", default="/tmp/cv_match", type=Path)
    ap.add_argument("-s", "--set", action="append", default=[],
                    help="recipe override, e.g. -s steps.unary.params.gps_radius_m=20")
    ap.add_argument("-m", "--match-param", action="append", default=[], help="key=value for every solver")
    args = ap.parse_args()
    logging.getLogger("crossview").setLevel(logging.ERROR)

    import yaml

    from toolkit.evaluation.truth import segment_match_scores
    from toolkit.registry import default_registry

    registry = default_registry()
    extra = {k: yaml.safe_load(v) for k, v in (s.split("=", 1) for s in args.match_param)}
    solvers = args.solvers.split(",")
    rows = []
    print(f"GPS pruning: {'off (--no-gps)' if args.no_gps else 'street/gps.csv'}", flush=True)
    for scene_name in args.scenes.split(","):
        scene_dir = REPO / "data" / scene_name
        for recipe in args.recipes.split(","):
            plan, street, overview, graphs, costs, t_unary = front(REPO / "recipes" / recipe, scene_dir,
                                                                   args.cache_dir, not args.no_gps,
                                                                   tuple(args.set))
            match_params = next(spec.params for spec, _ in plan.stages if spec.name == "match")
            smooth = {k: v for k, v in match_params.items() if k in ("c1", "c2", "theta_th_deg", "t_th_m")}
            truth = truth_of(plan.scene, street, overview)
            head = (f"{scene_name:15s} {recipe:15s} {len(street):4d} street / {len(overview):4d} ov segs, "
                    f"{graphs.n_nodes} nodes {graphs.n_labels} labels"
                    + (f", unary {t_unary:.1f} s" if t_unary else ""))
            print(head, flush=True)
            res = {}
            for name in solvers:
                cls = registry.get(SOLVERS[name])
                params = dict(smooth, **{k: v for k, v in extra.items() if k in cls.Params.model_fields})
                t0 = time.perf_counter()
                m = cls.from_config(params)(graphs=graphs, costs=costs, obs=NullObserver())
                dt = time.perf_counter() - t0
                sc = segment_match_scores(m, *truth)
                sc["cover"] = cover_precision(m, truth, sc)
                res[name] = (m, sc)
                lb = f" LB {m.lower_bound:9.3f}" if m.lower_bound is not None else ""
                print(f"    {name:9s} P {sc['precision']:.3f} R {sc['recall']:.3f} "
                      f"({sc['n_correct']}/{sc['n_matched']} of {sc['n_with_counterpart']}) Pcover {sc['cover']:.3f} "
                      f"E {m.energy:9.3f}{lb} it {m.iterations:3d} conv {m.converged!s:5} {dt:5.2f} s", flush=True)
                if args.diagnose and name == "loopy_bp":
                    print("\n".join(diagnose(m, graphs, costs, sc, street)), flush=True)
            rows.append((scene_name, recipe, res))

    print("\nSummary (P / R against truth; energies with the recipe's c1, c2):")
    print(f"{'scene':15s} {'recipe':15s} " + " ".join(f"{n:>13s}" for n in solvers)
          + "   E(trws)  LB(trws)     E(bp)    E(icm)  order")
    for scene_name, recipe, res in rows:
        cells = " ".join(f"{res[n][1]['precision']:.3f}/{res[n][1]['recall']:.3f}" for n in solvers)
        e = {n: res[n][0].energy for n in res}
        lb = res["trws"][0].lower_bound if "trws" in res else None
        order = ""
        if {"trws", "loopy_bp", "icm"} <= set(e):
            order = "ok" if e["trws"] <= e["loopy_bp"] + 1e-9 and e["loopy_bp"] <= e["icm"] + 1e-9 else "VIOLATED"
        print(f"{scene_name:15s} {recipe:15s} {cells} " + " ".join(
            f"{e.get(n, float('nan')):9.3f}" if n != "lb" else f"{(lb if lb is not None else float('nan')):9.3f}"
            for n in ("trws", "lb", "loopy_bp", "icm")) + f"  {order}")
    print("\nPcover (matched segment's true building ≥ 50 % inside the matched over-view segment):")
    for scene_name, recipe, res in rows:
        print(f"{scene_name:15s} {recipe:15s} " + " ".join(f"{res[n][1]['cover']:13.3f}" for n in solvers))
    for n in solvers:
        p = [r[2][n][1]["precision"] for r in rows]
        r_ = [r[2][n][1]["recall"] for r in rows]
        print(f"  {n:9s} precision min {min(p):.3f} mean {np.mean(p):.3f}   recall min {min(r_):.3f} "
              f"mean {np.mean(r_):.3f}")


if __name__ == "__main__":
    main()
