"""How much of the real-city error is the over-view source's own noise: the matrix scenes rebuilt
with exact footprints and label-map edges, run beside the default ones.

    .venv/bin/python bench/source_noise.py [--only SUBSTR] [--routes short] [--recipes osm,label_map]
        [--jobs 1] [--against CODE_STATE] [--report]

The generator gives every OSM-like footprint its own digitising offset (``footprint_shift_m``, σ
per axis) and every label-map building its own edge erosion/dilation (``label_edge_px``). A
segment's rigid fit can only average the offsets of the few buildings it sees, so these set a
floor under the horizontal error that no matching can remove. This bench rebuilds the chosen scenes
of bench/cities.py with both set to 0 (everything else — seed, drift, missing and merged
footprints, false label blobs — as in the matrix), caches them under data/cities-clean/, runs the
recipes without GPS and prints each run beside the default scene's row from data/cities/results.json
(the current code state, or ``--against``; run bench/cities.py first). It also prints the offset of
the noisy source itself: the street-point-weighted median length of the footprint offsets of the
buildings the capture sees, and the length of their weighted mean (what one rigid fit would keep).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np

import cities as C
from _common import REPO

CLEAN = {"footprint_shift_m": 0.0, "label_edge_px": 0}


def footprint_offsets(scene_dir) -> tuple[float, float]:
    """(weighted median |offset|, |weighted mean offset|) in metres of the osm footprints against the
    true ones, per building seen by the capture (weight: its street points); buildings whose osm
    outline is merged or missing (area off by > 15 %) are left out."""
    import shapely
    import yaml
    from pyproj import Transformer
    from shapely.geometry import shape

    crs = yaml.safe_load((scene_dir / "scene.yaml").read_text())["crs"]
    tr = Transformer.from_crs("EPSG:4326", crs, always_xy=True)

    def load(name):
        feats = json.loads((scene_dir / name).read_text())["features"]
        return {f["properties"]["id"]: shapely.transform(
            shape(f["geometry"]), lambda xy: np.column_stack(tr.transform(xy[:, 0], xy[:, 1]))).buffer(0)
                for f in feats}

    truth, osm = load("truth/buildings.geojson"), list(load("overview/footprints.geojson").values())
    tree = shapely.STRtree(osm)
    labels = np.load(scene_dir / "truth" / "street_labels.npy")
    ids, counts = np.unique(labels[labels >= 0], return_counts=True)
    vec, w = [], []
    for i, n in zip(ids, counts):
        t = truth.get(int(i))
        cand = tree.query(t) if t is not None else []
        if not len(cand):
            continue
        o = osm[max(cand, key=lambda k: osm[k].intersection(t).area)]
        if abs(o.area / t.area - 1) <= 0.15:
            vec.append(np.subtract(o.centroid.coords[0], t.centroid.coords[0]))
            w.append(n)
    if not vec:
        return float("nan"), float("nan")
    vec, w = np.array(vec), np.array(w, float)
    mag = np.linalg.norm(vec, axis=1)
    order = np.argsort(mag)
    median = mag[order][np.searchsorted(np.cumsum(w[order]) / w.sum(), 0.5)]
    return float(median), float(np.linalg.norm((vec * w[:, None]).sum(0) / w.sum()))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="scenes whose name contains this")
    ap.add_argument("--routes", default="short", help="comma-separated: short,long")
    ap.add_argument("--recipes", default="osm,label_map", help="comma-separated: dsm,osm,label_map")
    ap.add_argument("--jobs", type=int, default=1, help="runs side by side (the machine has 2 cores)")
    ap.add_argument("--report", action="store_true", help="print the rows saved by an earlier run of this "
                                                          "bench at the current code state; run nothing")
    ap.add_argument("--against", help="code state of the default rows in data/cities/results.json "
                                      "(default: the current one)")
    args = ap.parse_args()
    if not C.RAW.is_dir():
        sys.exit(f"{C.RAW}: real city data not present (the 'shared' folder beside the repo); nothing to run")
    default_dirs = {s.name: s.dir for s in C.scenes()}
    try:
        results = json.loads(C.RESULTS.read_text())
    except (OSError, ValueError):
        results = {}
    against = args.against or C.code_state()[0]
    default_rows = {(r["scene"], r["source"]): r for r in results.get(against, {}).get("rows", []) if not r["gps"]}
    routes = args.routes.split(",")
    recipes = [r.strip() for r in args.recipes.split(",") if r.strip()]

    C.use_root(REPO / "data" / "cities-clean")
    chosen = [replace(s, knobs={**s.knobs, **CLEAN}) for s in C.scenes()
              if s.route in routes and (not args.only or args.only in s.name)]
    code = C.generator_stamp()
    stamps = {s.name: C.build(s, code) for s in chosen} if not args.report else {}
    state = C.code_state()
    lock = threading.Lock()

    def work(job):
        s, r = job
        row = C.row_of(s, stamps[s.name], r, False, C.run_one(s, r, False))
        with lock:
            C.save([row], state)
        return row

    jobs = [(s, r) for s in chosen for r in recipes]
    if args.report:
        saved = {(r["scene"], r["source"]): r for r in json.loads(C.RESULTS.read_text())[state[0]]["rows"]}
        rows = [saved[(s.name, r)] for s, r in jobs if (s.name, r) in saved]
    else:
        with ThreadPoolExecutor(max(1, args.jobs)) as pool:
            rows = list(pool.map(work, jobs))

    print(f"\nexact sources (footprint_shift_m 0, label_edge_px 0) against the default scenes at {against}")
    print(f"{'scene':18s} {'source':9s} {'osm offset med/mean':>20s} {'h med':>14s} {'p95':>14s} "
          f"{'3D mean':>14s} {'bar':>9s}")
    meets = [0, 0]
    for row in rows:
        d = default_rows.get((row["scene"], row["source"]), {})
        off = footprint_offsets(default_dirs[row["scene"]]) if row["source"] == "osm" else None
        off_s = f"{off[0]:.2f} / {off[1]:.2f}" if off else "-"
        cells = [f"{C._f(d.get(k), '{:.3f}')} → {C._f(row[k], '{:.3f}')}"
                 for k in ("horizontal_median_m", "p95_m", "error_3d_mean_m")]
        bar = f"{C._f(d.get('meets_bar'))} → {C._f(row['meets_bar'])}"
        meets[0] += bool(d.get("meets_bar"))
        meets[1] += bool(row["meets_bar"])
        print(f"{row['scene']:18s} {row['source']:9s} {off_s:>20s} {cells[0]:>14s} {cells[1]:>14s} "
              f"{cells[2]:>14s} {bar:>9s}")
    print(f"\n{meets[0]} → {meets[1]} of {len(rows)} runs meet the bar (default scenes → exact sources); "
          f"rows written to {C.RESULTS.relative_to(REPO)} under {state[0]!r}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
