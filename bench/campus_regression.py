"""Campus regression check: seeds × recipes, a variant against the default, figure by figure.

Runs ``crossview run recipes/<recipe>.yaml`` on the campus test seeds (scenes generated once under
data/campus<seed>, outputs under data/campus-out/<tag>/), the default first and then the variant
given by ``--set`` overrides, each run in its own process, and prints per run the horizontal
median, horizontal p95, 3D p95 and 3D mean (m) and the adjusted camera centres' median error, with
each figure's change. The campus is a regression check, not a tuning set: the issue's bar is that
no figure gets more than 10 % worse. Each run's registered.ply is deleted once it has run (its
registered.laz and registered.sha256 stay), and a new tag keeps the newest KEEP_VARIANTS − 1 variant
folders besides default whole and older ones with their metrics and logs only (JSON, log and YAML files).

usage: python bench/campus_regression.py [--seeds 0,1,2,3,4] [--recipes dsm,osm,label_map]
       [--set KEY=VALUE ...] [--tag NAME] [--reuse-default]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from _common import REPO, bound_folders, slim_run

OUT = REPO / "data" / "campus-out"
KEEP_VARIANTS = 3  # data/campus-out/<tag> folders kept whole besides default (each run keeps registered.laz, not the PLY)
KEEP_SLIM = 20     # older <tag> folders kept with their metrics and logs only
FIGURES = (("h med", ("truth", "horizontal", "median_m")), ("h p95", ("truth", "horizontal", "p95_m")),
           ("3D p95", ("truth", "error_3d", "p95_m")), ("3D mean", ("truth", "error_3d", "mean_m")),
           ("cam med", ("cameras", "centre_error_median_m")))


def campus(seed: int) -> Path:
    root = REPO / "data" / f"campus{seed}"
    if not (root / "scene.yaml").is_file():
        subprocess.run([sys.executable, "-m", "toolkit.cli", "synth", "--preset", "campus", "--seed", str(seed),
                        "--out", str(root)], cwd=REPO, check=True)
    return root


def run(seed: int, recipe: str, tag: str, overrides: list[str], reuse: bool = False) -> tuple[dict, float]:
    out = OUT / tag / f"{seed}-{recipe}"
    if reuse and (out / "metrics.json").is_file():
        return json.loads((out / "metrics.json").read_text()), float("nan")
    cmd = [sys.executable, "-m", "toolkit.cli", "run", str(REPO / "recipes" / f"{recipe}.yaml"),
           "--scene", str(campus(seed)), "--out", str(out), "--overwrite", "--no-rerun", "-q"]
    for kv in overrides:
        cmd += ["-s", kv]
    t0 = time.perf_counter()
    done = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True)
    if done.returncode not in (0, 4):
        sys.exit(f"seed {seed} {recipe} ({tag}): exit {done.returncode}\n{done.stderr[-2000:]}")
    seconds = time.perf_counter() - t0
    digest = slim_run(out)  # the PLY goes; the LAZ's digest stays
    if digest:
        (out / "registered.sha256").write_text(digest + "\n")
    return json.loads((out / "metrics.json").read_text()), seconds


def figure(metrics: dict, path: tuple[str, ...]) -> float:
    for key in path:
        metrics = metrics[key]
    return float(metrics)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="0,1,2,3,4")
    ap.add_argument("--recipes", default="dsm,osm,label_map")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="the variant's recipe override")
    ap.add_argument("--tag", default="variant", help="the variant's output folder under data/campus-out/")
    ap.add_argument("--reuse-default", action="store_true",
                    help="take the default runs from data/campus-out/default/ when they are there (same code)")
    args = ap.parse_args()
    if not (OUT / args.tag).exists():  # room for this variant: the default and the newest variants stay
        bound_folders([d for d in OUT.glob("*") if d.name != "default"], KEEP_VARIANTS - 1, KEEP_SLIM)
    worst = (0.0, "")
    head = "  ".join(f"{name:>16s}" for name, _ in FIGURES)
    print(f"{'seed recipe':16s} {head}   seconds (default → variant)")
    for seed in map(int, args.seeds.split(",")):
        for recipe in args.recipes.split(","):
            base, t_base = run(seed, recipe, "default", [], args.reuse_default)
            var, t_var = run(seed, recipe, args.tag, args.set)
            cells = []
            for name, path in FIGURES:
                a, b = figure(base, path), figure(var, path)
                change = (b - a) / a if a > 0 else 0.0
                if change > worst[0]:
                    worst = (change, f"seed {seed} {recipe} {name} {a:.3f} → {b:.3f} m")
                cells.append(f"{a:.3f}→{b:.3f} {100 * change:+4.0f}%")
            print(f"{seed} {recipe:14s} {'  '.join(f'{c:>16s}' for c in cells)}   {t_base:.0f} → {t_var:.0f}",
                  flush=True)
    print(f"largest rise: {100 * worst[0]:+.1f} % ({worst[1] or 'none'}); bar: ≤ +10 % on every figure")


if __name__ == "__main__":
    main()
