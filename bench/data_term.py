"""Benchmark: the data term (graph.knn + unary.distance_map) on a scene folder, then the solver and
the segment-match precision / recall against the scene's truth.

    python bench/data_term.py [SCENE] [--overview overview.osm] [--match match.loopy_bp]
                              [-u key=value ...] [--no-cache]

SCENE defaults to data/campus when the generator marked it ready (data/READY_CAMPUS), otherwise a
campus scene generated once under data/bench-campus-0. Over-view and street segments are cached
(pickle under data/cache/) so that repeated runs time only the stages under test.
Acceptance (issue 6): the data term ≤ 60 s on the campus scene (2 cores).
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import time
from pathlib import Path

from _common import REPO, peak_rss_mb
from _common import scene as synth_scene


def _default_scene() -> Path:
    if (REPO / "data" / "READY_CAMPUS").exists() and (REPO / "data" / "campus" / "scene.yaml").is_file():
        return REPO / "data" / "campus"
    return synth_scene("campus")


def _stage(registry, key: str, params: dict):
    return registry.get(key).from_config(params)


def _cached(path: Path, make, use_cache: bool):
    if use_cache and path.is_file():
        with open(path, "rb") as f:
            return pickle.load(f), 0.0
    t0 = time.perf_counter()
    value = make()
    seconds = time.perf_counter() - t0
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump(value, f)
    return value, seconds


def _parse_params(items: list[str]) -> dict:
    import yaml

    out = {}
    for item in items:
        key, _, value = item.partition("=")
        out[key.strip()] = yaml.safe_load(value)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", type=Path)
    ap.add_argument("--overview", default="overview.osm")
    ap.add_argument("--match", default="match.loopy_bp")
    ap.add_argument("-u", "--unary", action="append", default=[], help="unary.distance_map param key=value")
    ap.add_argument("-k", type=int, default=4)
    ap.add_argument("--overview-k", type=int, default=None)
    ap.add_argument("--no-gps", action="store_true", help="hide street/gps.csv from the unary stage")
    ap.add_argument("--no-cache", action="store_true")
    args = ap.parse_args()

    import numpy as np

    from toolkit.capture import StreetCapture
    from toolkit.observe import NullObserver
    from toolkit.registry import Registry
    from toolkit.scene import load_array, load_scene

    root = args.scene or _default_scene()
    scene = load_scene(root)
    reg = Registry()
    obs = NullObserver()
    cache = REPO / "data" / "cache"
    import hashlib

    stamp = (scene.root / "scene.yaml").read_bytes() + str(
        [(f.stat().st_size, f.stat().st_mtime_ns) for f in (scene.files.street_cloud, scene.files.footprints)
         if f]).encode()
    from refine_warp_ba import code_stamp  # stages changed since the cache was written: recompute

    tag = f"{scene.root.name}-{hashlib.sha1(stamp + code_stamp().encode()).hexdigest()[:10]}"
    overview, t_ov = _cached(cache / f"{tag}-{args.overview}.pkl",
                             lambda: _stage(reg, args.overview, {})(scene, obs), not args.no_cache)
    street, t_st = _cached(cache / f"{tag}-street.region_growing.pkl",
                           lambda: _stage(reg, "street.region_growing", {})(scene, StreetCapture(scene), obs),
                           not args.no_cache)

    c0, t0 = time.process_time(), time.perf_counter()
    gparams = {"k": args.k} | ({"overview_k": args.overview_k} if args.overview_k else {})
    graphs = _stage(reg, "graph.knn", gparams)(street, overview, obs)
    t_graph = time.perf_counter() - t0
    unary = _stage(reg, "unary.distance_map", _parse_params(args.unary))
    t1 = time.perf_counter()
    unary_scene = dataclasses.replace(scene, files=dataclasses.replace(scene.files, gps=None)) \
        if args.no_gps else scene
    costs = unary(graphs, street, overview, unary_scene, StreetCapture(unary_scene), obs)
    t_unary = time.perf_counter() - t1
    cpu = time.process_time() - c0
    t2 = time.perf_counter()
    matches = _stage(reg, args.match, {})(graphs, costs, obs)
    t_match = time.perf_counter() - t2

    finite = np.isfinite(costs.cost[:, :-1])
    print(f"scene {root}  over-view {args.overview}: {len(overview)} segments "
          f"({'cached' if not t_ov else f'{t_ov:.1f} s'}), street: {len(street)} segments "
          f"({'cached' if not t_st else f'{t_st:.1f} s'})")
    print(f"graph.knn {gparams}: E={graphs.n_nodes} street edges, F={len(graphs.overview_edges)} over-view "
          f"edges, L={graphs.n_labels} labels, C={len(graphs.conj_edges)} conjugate edges  {t_graph:.2f} s")
    gps = "off" if args.no_gps or not scene.has("gps") else "on"
    print(f"unary.distance_map {unary.params.search} (GPS {gps}): {int(finite.sum())} of {finite.size} "
          f"candidates scored "
          f"({finite.sum() / max(1, finite.size):.1%})  wall {t_unary:.1f} s, cpu (graph+unary) {cpu:.1f} s, "
          f"peak RSS {peak_rss_mb():.0f} MB")
    print(f"{args.match}: {matches.iterations} iterations, converged={matches.converged}  {t_match:.1f} s")
    if scene.has("truth_street_labels") and scene.has("truth_buildings"):
        from toolkit.evaluation.truth import read_true_buildings, segment_match_scores

        ids, geoms = read_true_buildings(scene.files.truth_buildings, scene.crs)
        true_labels = load_array(scene, "truth_street_labels")
        s = segment_match_scores(matches, street, overview, true_labels, ids, geoms)
        print(f"segment matches: precision {s['precision']}, recall {s['recall']} "
              f"({s['n_correct']} correct of {s['n_matched']} matched; {s['n_with_counterpart']} street "
              f"segments have an over-view counterpart of {s['n_street_segments']})")
    verdict = "ok" if t_unary + t_graph <= 60 else "SLOWER than the 60 s target"
    print(f"data term {t_graph + t_unary:.1f} s wall: {verdict}")


if __name__ == "__main__":
    main()
