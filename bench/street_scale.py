"""Unknown street scale: the same scene with its street frame scaled, with and without GPS.

    .venv/bin/python bench/street_scale.py [--scenes campus0,denhaag-short,schaan-short]
        [--scales 0.1,0.3,1,3,10] [--recipe dsm] [--gps both|yes|no] [--camera-height-m H]

Each scene is generated once per scale under data/scale/<scene>-s<S>[-h<H>]/ (cloud, COLMAP points
and camera positions × S; the truth unchanged): ``campus0`` is ``crossview synth --preset campus
--seed 0``, the others are bench/cities.py matrix scenes (same city, seed and knobs);
``--camera-height-m`` builds them with the cameras at H m above the road instead of the
generator's 2 m (the no-GPS estimate's first guess assumes 2 m, so this leaves the scale to the
matching). Every scale runs with street/gps.csv and without (``street_scale: auto``), or only one
of them (``--gps``), and one table is printed: the truth scale (the best similarity of the input
street cloud onto truth/street_points.npy, the route's mean scale drift included) over S, the
estimate (GPS or matching) over the truth scale, the scale the run used over the truth scale, its
source, horizontal median and p95 (3D for dsm), status and exit code, seconds, and for each run
the ratio of its horizontal median and p95 to the same scene's at scale 1 (same GPS setting).
Each run's stdout and stderr go to data/scale/out/<run>.log. The scene folders stay (about
0.2-0.5 GB each); delete data/scale/ to free them.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import yaml

from _common import REPO, slim_run

OUT = REPO / "data" / "scale"


def build(name: str, scale: float, camera_height_m: float | None = None) -> Path:
    root = OUT / f"{name}-s{scale:g}{'' if camera_height_m is None else f'-h{camera_height_m:g}'}"
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
    extra = [] if camera_height_m is None else ["--set", f"camera_height_m={camera_height_m:g}"]
    proc = subprocess.run(cmd + ["--set", f"street_scale={scale:g}", *extra, "--out", str(root), "--overwrite"],
                          capture_output=True, text=True)
    if proc.returncode:
        sys.exit(proc.stdout + proc.stderr)
    manifest = yaml.safe_load((root / "scene.yaml").read_text())
    manifest["street"].pop("gps", None)
    (root / "scene-nogps.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return root


def truth_scale(root: Path, n: int = 200_000) -> float:
    """The input street cloud's units per metre: the best similarity onto its truth (n points)."""
    import numpy as np

    from _common import similarity_scale
    from toolkit.io.cloud import read_points

    pts, truth = read_points(root / "street" / "cloud.ply"), np.load(root / "truth" / "street_points.npy")
    idx = np.random.default_rng(0).choice(len(pts), min(n, len(pts)), replace=False)
    return similarity_scale(np.asarray(pts, np.float64)[idx], np.asarray(truth, np.float64)[idx])


def run(root: Path, recipe: str, gps: bool) -> dict:
    out = OUT / "out" / f"{root.name}-{recipe}{'-gps' if gps else ''}"
    if out.exists():
        shutil.rmtree(out)
    exe = str(Path(sys.executable).parent / "crossview")
    t0 = time.perf_counter()
    proc = subprocess.run([exe, "run", str(REPO / "recipes" / f"{recipe}.yaml"), "--scene",
                           str(root / ("scene.yaml" if gps else "scene-nogps.yaml")), "--out", str(out),
                           "--no-rerun", "-q"], capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.log").write_text(proc.stdout + proc.stderr)  # an exit 1 or 2 says why here
    m = json.loads((out / "metrics.json").read_text()) if (out / "metrics.json").is_file() else {}
    slim_run(out)  # the PLY copy of registered.laz
    truth = m.get("truth") or {}
    kind = "error_3d" if recipe == "dsm" else "horizontal"
    return {"exit": proc.returncode, "status": m.get("status"), "scale": (m.get("street_scale") or {}),
            "seconds": seconds, "scale_seconds": _timing(out, "scale"),
            "h": (truth.get("horizontal") or {}).get("median_m"), "p95": (truth.get(kind) or {}).get("p95_m")}


def _timing(out: Path, step: str) -> float | None:
    path = out / "timings.json"
    return json.loads(path.read_text()).get(step) if path.is_file() else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="campus0,denhaag-short,schaan-short")
    ap.add_argument("--scales", default="0.1,0.3,1,3,10")
    ap.add_argument("--recipe", default="dsm")
    ap.add_argument("--gps", choices=("both", "yes", "no"), default="both", help="runs with GPS, without, or both")
    ap.add_argument("--camera-height-m", type=float, help="build the scenes with the cameras this high (m)")
    a = ap.parse_args()
    scales = [float(x) for x in a.scales.split(",")]
    if 1.0 not in scales:
        scales = [1.0] + scales
    settings = {"both": (True, False), "yes": (True,), "no": (False,)}[a.gps]
    rows = []
    for name in a.scenes.split(","):
        for s in scales:
            root = build(name, s, a.camera_height_m)
            truth = truth_scale(root)
            for gps in settings:
                r = run(root, a.recipe, gps)
                rows.append({"scene": name, "S": s, "gps": gps, "truth": truth, **r})
                print(f"  {name} S={s:g} {'gps' if gps else 'no gps'}: exit {r['exit']} {r['status']} "
                      f"h {r['h']} p95 {r['p95']} truth scale {truth:.5f} scale {r['scale']} "
                      f"{r['seconds']:.0f} s", flush=True)
    ref = {(r["scene"], r["gps"]): r for r in rows if r["S"] == 1.0}
    fmt = (lambda v, f="{:.2f}": "-" if v is None else f.format(v))
    print(f"\n{'scene':14s} {'S':>5s} {'GPS':4s} {'truth/S':>7s} {'est/tr':>7s} {'used/tr':>7s} {'source':8s} "
          f"{'h med':>6s} {'p95':>6s} {'h/h1':>5s} {'p95/p1':>6s} {'status':10s} exit {'s':>4s} {'scale s':>7s}")
    for r in rows:
        base = ref.get((r["scene"], r["gps"]))
        sc = r["scale"]
        est = sc.get("gps_estimate", sc.get("matching_estimate"))
        ratio = (lambda k, r=r, base=base: f"{r[k] / base[k]:.2f}" if base and r[k] and base[k] else "-")
        print(f"{r['scene']:14s} {r['S']:5g} {'yes' if r['gps'] else 'no':4s} {r['truth'] / r['S']:7.4f} "
              f"{fmt(None if est is None else est / r['truth'], '{:.4f}'):>7s} "
              f"{fmt(None if sc.get('value') is None else sc['value'] / r['truth'], '{:.4f}'):>7s} "
              f"{sc.get('source', '-'):8s} {fmt(r['h']):>6s} {fmt(r['p95']):>6s} {ratio('h'):>5s} {ratio('p95'):>6s} "
              f"{str(r['status']):10s} {r['exit']:4d} {r['seconds']:4.0f} {fmt(r['scale_seconds'], '{:.1f}'):>7s}")


if __name__ == "__main__":
    main()
