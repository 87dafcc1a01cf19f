"""Unknown street scale: the same scene with its street frame scaled, with and without GPS.

    .venv/bin/python bench/street_scale.py [--scenes campus0,denhaag-short,schaan-short]
        [--scales 0.1,0.3,1,3,10] [--recipe dsm]

Each scene is generated once per scale under data/scale/<scene>-s<S>/ (cloud, COLMAP points and
camera positions × S; the truth unchanged): ``campus0`` is ``crossview synth --preset campus
--seed 0``, the others are bench/cities.py matrix scenes (same city, seed and knobs). Every scale
runs with street/gps.csv and without (``street_scale: auto``), and one table is printed: estimated
scale / S, its source, horizontal median and p95 (3D for dsm), status and exit code, and for each
run the ratio of its horizontal median and p95 to the same scene's at scale 1 (same GPS setting).
Each run's stdout and stderr go to data/scale/out/<run>.log. The scene folders stay (about
0.2-0.5 GB each); delete data/scale/ to free them.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import yaml

from _common import REPO

OUT = REPO / "data" / "scale"


def build(name: str, scale: float) -> Path:
    root = OUT / f"{name}-s{scale:g}"
    if (root / "scene.yaml").is_file():
        return root
    exe = str(Path(sys.executable).parent / "crossview")
    if name == "campus0":
        cmd = [exe, "synth", "--preset", "campus", "--seed", "0"]
    else:
        sys.path.insert(0, str(REPO / "bench"))
        from cities import CITIES, scenes

        s = next((x for x in scenes() if x.name == name), None)
        if s is None:
            sys.exit(f"{name}: not a bench/cities.py scene")
        cfg = OUT / f"{name}.yaml"
        OUT.mkdir(parents=True, exist_ok=True)
        cfg.write_text(yaml.safe_dump({k: list(v) if isinstance(v, tuple) else v for k, v in s.knobs.items()}))
        cmd = [exe, "synth", "--city", str(CITIES[s.city].path), "--seed", str(s.seed), "--config", str(cfg)]
    print(f"building {root.name} ...", flush=True)
    proc = subprocess.run(cmd + ["--set", f"street_scale={scale:g}", "--out", str(root), "--overwrite"],
                          capture_output=True, text=True)
    if proc.returncode:
        sys.exit(proc.stdout + proc.stderr)
    manifest = yaml.safe_load((root / "scene.yaml").read_text())
    manifest["street"].pop("gps", None)
    (root / "scene-nogps.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return root


def run(root: Path, recipe: str, gps: bool) -> dict:
    out = OUT / "out" / f"{root.name}-{recipe}{'-gps' if gps else ''}"
    if out.exists():
        shutil.rmtree(out)
    exe = str(Path(sys.executable).parent / "crossview")
    proc = subprocess.run([exe, "run", str(REPO / "recipes" / f"{recipe}.yaml"), "--scene",
                           str(root / ("scene.yaml" if gps else "scene-nogps.yaml")), "--out", str(out),
                           "--no-rerun", "-q"], capture_output=True, text=True)
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.log").write_text(proc.stdout + proc.stderr)  # an exit 1 or 2 says why here
    m = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    truth = m.get("truth") or {}
    kind = "error_3d" if recipe == "dsm" else "horizontal"
    return {"exit": proc.returncode, "status": m.get("status"), "scale": (m.get("street_scale") or {}),
            "h": (truth.get("horizontal") or {}).get("median_m"), "p95": (truth.get(kind) or {}).get("p95_m")}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="campus0,denhaag-short,schaan-short")
    ap.add_argument("--scales", default="0.1,0.3,1,3,10")
    ap.add_argument("--recipe", default="dsm")
    a = ap.parse_args()
    scales = [float(x) for x in a.scales.split(",")]
    if 1.0 not in scales:
        scales = [1.0] + scales
    rows = []
    for name in a.scenes.split(","):
        for s in scales:
            root = build(name, s)
            for gps in (True, False):
                r = run(root, a.recipe, gps)
                rows.append({"scene": name, "S": s, "gps": gps, **r})
                print(f"  {name} S={s:g} {'gps' if gps else 'no gps'}: exit {r['exit']} {r['status']} "
                      f"h {r['h']} p95 {r['p95']} scale {r['scale']}", flush=True)
    ref = {(r["scene"], r["gps"]): r for r in rows if r["S"] == 1.0}
    print(f"\n{'scene':14s} {'S':>5s} {'GPS':4s} {'est/S':>7s} {'source':8s} {'h med':>6s} {'p95':>6s} "
          f"{'h/h1':>5s} {'p95/p1':>6s} {'status':10s} exit")
    for r in rows:
        base = ref.get((r["scene"], r["gps"]))
        est = r["scale"].get("gps_estimate", r["scale"].get("value"))
        rel = "-" if est is None else f"{est / r['S']:.4f}"
        ratio = (lambda k, r=r, base=base: f"{r[k] / base[k]:.2f}" if base and r[k] and base[k] else "-")
        fmt = (lambda v: "-" if v is None else f"{v:.2f}")
        print(f"{r['scene']:14s} {r['S']:5g} {'yes' if r['gps'] else 'no':4s} "
              f"{rel:>7s} {r['scale'].get('source', '-'):8s} "
              f"{fmt(r['h']):>6s} {fmt(r['p95']):>6s} {ratio('h'):>5s} {ratio('p95'):>6s} "
              f"{str(r['status']):10s} {r['exit']}")


if __name__ == "__main__":
    main()
