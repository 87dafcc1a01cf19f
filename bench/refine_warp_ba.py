"""Refine + warp + bundle adjustment on scene folders: accuracy against the truth and timings.

The upstream stages (overview … match) of a recipe run once per scene and recipe and are cached
(pickle under data/.bench-cache/<code stamp>/, keyed by scene, step specs and the source of toolkit/ and
plugins/; only the KEEP_STAMPS newest code stamps are kept); then, timed: refine.exhaustive with the recipe's refine parameters (and refine.icp with --icp),
warp.inverse_log and warp.nearest, adjust.constrained_ba with pycolmap/Ceres (and scipy with
--scipy), adjust.none. Printed per run:
- per-point error vs truth/street_points.npy: horizontal median, 3D mean and p95; the best single
  rigid transform fitted with the truth (its mean 3D error) as the bar to beat;
- p95 3D error at segment borders (points about as close to a second valid segment as to the
  nearest one: d2 − d1 < --border-m) for inverse_log vs nearest;
- cameras: centre error vs truth/cameras.txt (warped vs adjusted), reprojection RMS before/after
  vs the injected pixel noise (scene.yaml synth.config.pixel_noise_px), BA time per backend;
- time of refine + warp + BA (the issue's budget: ≤ 2 min for campus on 2 cores); refine and warp
  also in CPU seconds (user + system, all threads), which drift less than wall seconds on a busy machine.

usage: python bench/refine_warp_ba.py [SCENE ...] [--recipe dsm.yaml ...] [--scipy] [--icp] [--segments]
       [--refine KEY=VALUE ...] [--warp KEY=VALUE ...] [--adjust KEY=VALUE ...]
       (default: data/campus if present else data/tiny; recipe dsm.yaml)
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _common import kabsch_error
from toolkit.observe import NullObserver
from toolkit.recipe import load_recipe
from toolkit.runner import build
from toolkit.scene import load_array, load_points, load_sparse

UPSTREAM = ("overview", "street", "graph", "unary", "match")
CACHE_ROOT = REPO / "data" / ".bench-cache"
KEEP_STAMPS = 3


def code_stamp() -> str:
    """Hash of the stages' source: a cached upstream output is stale once any of it changes
    (parameter defaults live in the code, not in the recipe)."""
    h = hashlib.sha1()
    for f in sorted([*REPO.glob("plugins/*.py"), *REPO.glob("toolkit/**/*.py")]):
        h.update(f.read_bytes())
    return h.hexdigest()[:12]


def cache_path(plan, scene_dir: Path, kind: str) -> Path:
    """Where step ``kind``'s output is cached: keyed by the scene, the stages' source and the specs of
    the step and of every step it depends on (street is shared by recipes that differ only in the
    over-view source)."""
    from toolkit.stage import KIND_INPUTS, KIND_OUTPUT, RUN_INPUTS

    kind_of = {v: k for k, v in KIND_OUTPUT.items()}
    specs = {spec.name: f"{spec.use}{sorted(spec.params.items())}" for spec, _ in plan.stages}
    stamp = f"{scene_dir.resolve()}|{(scene_dir / 'scene.yaml').stat().st_mtime_ns}|{code_stamp()}"

    def key(k: str) -> str:
        deps = [kind_of[n] for n in KIND_INPUTS[k] if n not in RUN_INPUTS]
        return specs[k] + "|" + "|".join(key(d) for d in deps)

    h = hashlib.sha1((stamp + key(kind)).encode()).hexdigest()[:16]
    return CACHE_ROOT / code_stamp() / f"{scene_dir.name}-{kind}-{h}.pkl"


def prune_cache(current: Path, keep: int = KEEP_STAMPS) -> None:
    """Delete the cache folders of all but the ``keep`` most recently used code stamps (``current``
    among them): every code change starts a new folder, and the cache once grew to 24 GB."""
    current.mkdir(parents=True, exist_ok=True)
    current.touch()
    stamps = sorted((d for d in CACHE_ROOT.iterdir() if d.is_dir()), key=lambda d: d.stat().st_mtime, reverse=True)
    for old in stamps[keep:]:
        if old != current:
            shutil.rmtree(old, ignore_errors=True)
    for loose in CACHE_ROOT.glob("*.pkl"):     # the flat layout of earlier versions
        loose.unlink()


def upstream(recipe_path: Path, scene_dir: Path, refresh: bool) -> dict:
    """Outputs of the recipe's overview … match steps, each cached on disk (``cache_path``)."""
    from toolkit.stage import KIND_INPUTS, KIND_OUTPUT

    plan = build(load_recipe(recipe_path), scene=scene_dir)
    results = {"scene": plan.scene, "capture": plan.capture}
    for spec, stage in plan.stages:
        if spec.name not in UPSTREAM:
            continue
        cache = cache_path(plan, scene_dir, spec.name)
        prune_cache(cache.parent)
        if cache.is_file() and not refresh:
            with open(cache, "rb") as fh:
                results[KIND_OUTPUT[spec.name]] = pickle.load(fh)
            continue
        t0 = time.perf_counter()
        kwargs = {n: results[n] for n in KIND_INPUTS[spec.name]}
        out = stage(**kwargs, obs=NullObserver())
        print(f"  ({spec.name} {spec.use} ran in {time.perf_counter() - t0:.1f} s)", flush=True)
        cache.parent.mkdir(parents=True, exist_ok=True)
        with open(cache, "wb") as fh:
            pickle.dump(out, fh)
        results[KIND_OUTPUT[spec.name]] = out
    return results


def recipe_params(recipe_path: Path, step: str, stage) -> dict:
    """The recipe's parameters of ``step`` when it uses ``stage`` (e.g. a per-source refine setting in
    recipes/osm.yaml), else none: the stage's defaults."""
    for spec in load_recipe(recipe_path).steps:
        if spec.name == step and spec.use == stage.key():
            return dict(spec.params)
    return {}


def border_mask(street, transforms, scene, border_m: float) -> np.ndarray:
    from toolkit.warp.blend import SegmentIndex

    idx = SegmentIndex.build(street, transforms, 1)
    xy = street.level(load_points(scene, "street_cloud"))[:, :2]
    d, nn = idx.all_tree.query(xy, k=min(24, len(idx.all_seg)), workers=-1)
    seg = idx.all_seg[nn]
    first = seg[:, :1]
    other = np.where(seg != first, d, np.inf).min(axis=1)
    return (other - d[:, 0]) < border_m


def truth_centres(scene, names) -> np.ndarray | None:
    from toolkit.io.colmap import _read_images_txt, qvec_to_rotmat

    p = scene.files.truth_cameras
    if p is None:
        return None
    by_name = {}
    for _, q, t, _, name, *_ in _read_images_txt(p):
        R = qvec_to_rotmat(q)
        by_name[name] = -R.T @ t
    return np.array([by_name[n] for n in names])


def point_errors(points, truth):
    d = points - truth
    h = np.linalg.norm(d[:, :2], axis=1)
    e = np.linalg.norm(d, axis=1)
    return h, e


def segment_report(matches, street, transforms, scene, truth):
    from toolkit.refine.transforms import apply

    pts = load_points(scene, "street_cloud")
    print("    seg  match  valid  n_pts   err_h   err_z   cost  conf")
    for i in range(len(street)):
        sel = np.asarray(street.carrier) == i
        if not sel.any():
            continue
        d = apply(transforms.T[i], pts[sel]) - truth[sel]
        print(f"    {i:3d} {int(matches.segment_match[i]):5d} {bool(transforms.valid[i])!s:>6} {sel.sum():6d} "
              f"{np.linalg.norm(d[:, :2], axis=1).mean():7.3f} {np.abs(d[:, 2]).mean():7.3f} "
              f"{transforms.cost[i]:6.3f} {transforms.confidence[i]:5.2f}")


def run(scene_dir: Path, recipe: str, args) -> None:
    from plugins.adjust_constrained_ba import ConstrainedBA
    from plugins.adjust_none import NoAdjust
    from plugins.refine_exhaustive import Exhaustive
    from plugins.refine_icp import IcpRefine
    from plugins.warp_inverse_log import InverseLog
    from plugins.warp_nearest import Nearest

    print(f"== {scene_dir.name} / {recipe}", flush=True)
    res = upstream(REPO / "recipes" / recipe, scene_dir, args.refresh)
    scene, street, overview, matches, graphs = (res["scene"], res["street"], res["overview"], res["matches"],
                                                res["graphs"])
    capture = res["capture"]
    truth = load_array(scene, "truth_street_points")
    inp = load_points(scene, "street_cloud")
    rigid = kabsch_error(inp, truth)
    noise = float(scene.manifest.get("synth", {}).get("config", {}).get("pixel_noise_px", float("nan")))
    print(f"  street points {len(inp)}, segments {len(street)} (matched {(matches.segment_match >= 0).sum()}), "
          f"rigid oracle mean 3D {rigid.mean():.3f} m, pixel noise {noise} px")
    refine_params = {**recipe_params(REPO / "recipes" / recipe, "refine", Exhaustive), **_overrides(args.refine)}
    refiners = [Exhaustive.from_config(refine_params)] \
        + ([IcpRefine()] if args.icp else [])
    for refiner in refiners:
        obs = NullObserver()
        t0, c0 = time.perf_counter(), time.process_time()
        tr = refiner(matches, street, overview, scene, capture, obs, graphs=graphs)
        t_refine = time.perf_counter() - t0
        print(f"  {refiner.key()}: {t_refine:.2f} s ({time.process_time() - c0:.2f} s CPU), "
              f"valid {tr.valid.sum()}/{len(tr.valid)}", flush=True)
        if args.segments:
            segment_report(matches, street, tr, scene, truth)
        border = border_mask(street, tr, scene, args.border_m)
        regs = {}
        warp_params = {**recipe_params(REPO / "recipes" / recipe, "warp", InverseLog), **_overrides(args.warp)}
        for warp in (InverseLog.from_config(warp_params), Nearest()):
            t0, c0 = time.perf_counter(), time.process_time()
            reg = warp(tr, street, scene, capture, NullObserver())
            t_warp = time.perf_counter() - t0
            c_warp = time.process_time() - c0
            regs[warp.name] = (reg, t_warp)
            h, e = point_errors(reg.points, truth)
            print(f"    {warp.key():18s} {t_warp:6.2f} s ({c_warp:5.2f} s CPU)  horiz median {np.median(h):.3f}  3D mean {e.mean():.3f}"
                  f"  p95 {np.percentile(e, 95):.3f}  border p95 {np.percentile(e[border], 95):.3f}"
                  f" ({border.sum()} pts)  beats rigid: {e.mean() < rigid.mean()}", flush=True)
        reg, t_warp = regs["inverse_log"]
        if not scene.has("sparse"):
            continue
        model = load_sparse(scene)
        C_true = truth_centres(scene, model.image_names)
        ba = {**recipe_params(REPO / "recipes" / recipe, "adjust", ConstrainedBA), **_overrides(args.adjust)}
        adjusters = [NoAdjust(), ConstrainedBA.from_config(ba)] \
            + ([ConstrainedBA.from_config({**ba, "backend": "scipy"})] if args.scipy else [])
        for adj in adjusters:
            t0 = time.perf_counter()
            out = adj(reg, scene, capture, NullObserver())
            t_adj = time.perf_counter() - t0
            extra = ""
            if C_true is not None:
                ce = np.linalg.norm(out.model.centres - C_true, axis=1)
                extra = f"  centre err median {np.median(ce):.3f} mean {ce.mean():.3f}"
            label = adj.key() + ("/" + adj.params.backend if hasattr(adj.params, "backend") else "")
            print(f"    {label:30s} {t_adj:6.2f} s  rms {out.rms_before_px:.3f} -> {out.rms_after_px:.3f} px"
                  f" (≤ {1.2 * noise:.2f}: {out.rms_after_px <= 1.2 * noise}), it {out.iterations}{extra}",
                  flush=True)
            if adj.name == "constrained_ba" and adj.params.backend == "ceres":
                print(f"    refine + warp + BA: {t_refine + t_warp + t_adj:.1f} s", flush=True)


def _overrides(pairs: list[str]) -> dict:
    """KEY=VALUE pairs (YAML values) as stage parameters, parsed as the CLI's ``-s``."""
    from toolkit.recipe import parse_override

    return {".".join(key): value for key, value in map(parse_override, pairs)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    default = REPO / "data" / ("campus" if (REPO / "data" / "campus" / "scene.yaml").is_file() else "tiny")
    ap.add_argument("scenes", nargs="*", default=[str(default)])
    ap.add_argument("--recipe", action="append", default=None, help="recipe file under recipes/ (repeatable)")
    ap.add_argument("--scipy", action="store_true", help="also run the scipy bundle adjustment")
    ap.add_argument("--icp", action="store_true", help="also run refine.icp")
    ap.add_argument("--segments", action="store_true", help="per-segment transform errors")
    ap.add_argument("--border-m", type=float, default=5.0)
    ap.add_argument("--refresh", action="store_true", help="re-run the cached upstream stages")
    ap.add_argument("--refine", action="append", default=[], metavar="KEY=VALUE",
                    help="refine.exhaustive parameter over the recipe's (YAML value; repeatable), for sweeps")
    ap.add_argument("--warp", action="append", default=[], metavar="KEY=VALUE",
                    help="warp.inverse_log parameter (YAML value; repeatable), for sweeps")
    ap.add_argument("--adjust", action="append", default=[], metavar="KEY=VALUE",
                    help="adjust.constrained_ba parameter (YAML value; repeatable), for sweeps")
    args = ap.parse_args()
    for s in args.scenes:
        for r in args.recipe or ["dsm.yaml"]:
            run(Path(s), r, args)


if __name__ == "__main__":
    main()
