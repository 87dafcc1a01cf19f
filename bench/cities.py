"""Real-city scene matrix: every recipe on scenes built from real city models it has never seen.

    .venv/bin/python bench/cities.py [--only SUBSTR] [--recipes dsm,osm,label_map] [--gps]
        [--build-only] [--jobs 1] [--set KEY=VALUE ... --tag NAME] [--holdout]

Six real geometries from ../shared/data/raw (Den Haag LoD2 CityJSON, Delft 3dfier LoD1 CityJSON,
two districts of Helsinki's OSM extract, two villages of Liechtenstein's OSM extract, cropped with
``city_crop_centre_lonlat``) × two closed routes (a short loop of ~0.5 km and a long one of
~1.5 km) make the scenes, each with its own seed and its own drift (heading/pitch/roll walks 1-4×
the generator's default, frame tilt up to 20°, a signed scale trend of 1-3 %), at the generator's
default density. A city that cannot host the asked loop gets a shorter or an open route (the
generator warns; the warning is kept in the scene's stamp and printed).

Scenes are cached under data/cities/<scene>/ and rebuilt only when their generation settings or
the generator's code (toolkit/synth/*.py, parsed: documentation edits do not count) changed
(stamp.json); folders of scenes no longer in the matrix are deleted, with their run outputs. Each
scene folder also holds scene-nogps.yaml: the same files without street/gps.csv, which is what
the runs use unless --gps is given.

Every scene × recipe runs as ``crossview run RECIPE --scene … --out data/cities/out/<scene>-<recipe>
[-gps] --overwrite --no-rerun -q`` (exit code and wall seconds recorded), then one table is printed
from each run's metrics.json: horizontal median, p95 (3D for dsm, horizontal for osm / label_map),
3D mean vs the best rigid fit given the truth (Kabsch of the input street cloud onto
truth/street_points.npy), match precision/recall, whether loopy BP converged (metrics.json's
assessment, else the run's warnings), the run's status and confidence ('-' when metrics.json has
none), exit code, seconds. The bar: horizontal median ≤ 0.5 m, p95 ≤ 1.5 m and 3D mean below the
rigid fit's. Rows go to data/cities/results.json (after each run) under the code state
(``git rev-parse --short HEAD``, "-dirty" when tracked files differ from it, "+NAME" for a variant
run with ``--set`` overrides and ``--tag NAME``, whose outputs go to data/cities/out-NAME/; each row also keeps
a hash of the diff). Disk: each run's registered.ply is deleted once scored (registered.laz holds the same
points; the row keeps its sha256 as ``registered_sha256``, so variants compare byte for byte after their
folders are gone), and a new variant keeps only the KEEP_VARIANTS − 1 newest out-* folders whole: older
ones keep their metrics and logs (JSON, log and YAML files; the KEEP_SLIM newest of them), what
bench/status_calibration.py --all re-scores.

``--holdout``: the held-out matrix, the same cities and routes with other seeds (+100) and each scene
given another scene's drift, cached and run under data/cities-holdout/ (its own results.json):
scenes on which no default was chosen, to check that they hold. ``--holdout 2``: a second one (seeds
+200, other drifts; data/cities-holdout2/), for a check of choices made on the first (the run
status's ``min_confidence`` was chosen on runs of both data/cities and data/cities-holdout).

``--gps-sigma-m S --gps-every N`` (with --gps, needs --tag): the runs use fixes made for the bench
from truth/cameras.txt, every N-th image with a slowly wandering error of S m per axis (the
generator's model, its own seed), written beside the scene as street/gps-s{S}-e{N}.csv with a
scene-gps-s{S}-e{N}.yaml manifest; the scene itself is not rebuilt.

``--replicas 3``: the matrix again with the street frame's units × 1.001 and × 0.999 (``--set
street_scale=…``, tags TAG-s1001 and TAG-s0999, "base-…" without --tag). Such inputs should change
nothing, yet single runs move by metres: the matrix's own spread, against which
bench/matrix_floor.py judges a variant's replicas.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from _common import REPO, bound_folders, kabsch_error, require_free_disk, slim_run

RAW = Path(__file__).resolve().parents[2] / "shared" / "data" / "raw"
ROOT = REPO / "data" / "cities"
OUT = ROOT / "out"
KEEP_VARIANTS = 4  # data/cities/out-TAG folders kept whole (the newest); each run keeps registered.laz, not the PLY
FREE_GIB, FREE_GIB_PER_RUN = 2.0, 0.1  # room asked before a matrix starts: a run keeps 30–80 MB, ~4× that while it runs
KEEP_SLIM = 40     # older out-TAG folders kept with their metrics and logs only (~3 MB each)
# --replicas: the same matrix with the street frame's units scaled by these (should change nothing;
# the spread they show is the matrix's own, bench/matrix_floor.py)
REPLICA_SCALES = (("s1001", 1.001), ("s0999", 0.999))
RESULTS = ROOT / "results.json"
RECIPES = ("dsm", "osm", "label_map")

# the generator's defaults the drift multipliers apply to (SynthConfig)
HEADING_WALK_DEG, TILT_WALK_DEG = 0.8, 0.12


@dataclass(frozen=True)
class City:
    label: str
    path: Path
    crop: str  # how the geometry was cut from the file, for the table
    knobs: dict = field(default_factory=dict)
    short_m: float = 500.0  # target of the short loop
    long_m: float = 1500.0


LIECHTENSTEIN = RAW / "liechtenstein-osm" / "liechtenstein.osm.pbf"
HELSINKI = RAW / "helsinki-osm" / "Helsinki.osm.pbf"
CITIES = {
    "denhaag": City("Den Haag LoD2", RAW / "denhaag-lod2" / "DenHaag_01.city.json", "whole tile (790 x 670 m)"),
    # the block between two canals holds one loop of streets (446 m): the short target is set to it
    "delft": City("Delft 3dfier LoD1", RAW / "delft-3dfier" / "delft_cjio_v2.0.city.json",
                  "whole file (230 x 170 m)", short_m=450.0),
    "helsinki-n": City("Helsinki (OSM) north", HELSINKI, "800 m at 24.9440E 60.1740N",
                       dict(city_crop_m=800.0, city_crop_centre_lonlat=(24.944, 60.174))),
    "helsinki-s": City("Helsinki (OSM) south", HELSINKI, "800 m at 24.9440E 60.1680N",
                       dict(city_crop_m=800.0, city_crop_centre_lonlat=(24.944, 60.168))),
    # the country's median building centre lies between villages (9 buildings within 300 m). Schaan's
    # short target picks a loop along fewer detached houses (its ~500 m loop gave 76 street segments);
    # Balzers replaced Triesen, whose loop of 0.4-0.6 km along the fewest houses (527 m) gave 52
    "schaan": City("Schaan LI (OSM)", LIECHTENSTEIN, "900 m at 9.5085E 47.1650N",
                   dict(city_crop_m=900.0, city_crop_centre_lonlat=(9.5085, 47.165), terrain_slope_pct=3.0),
                   short_m=460.0),
    "balzers": City("Balzers LI (OSM)", LIECHTENSTEIN, "900 m at 9.4990E 47.0660N",
                    dict(city_crop_m=900.0, city_crop_centre_lonlat=(9.499, 47.066), terrain_slope_pct=8.0),
                    short_m=480.0),
}

# (city, route, seed, heading walk ×, pitch/roll walk ×, max tilt deg, signed scale trend)
MATRIX = [
    ("denhaag", "short", 101, 1.0, 2.0, 5.0, +0.010),
    ("denhaag", "long", 102, 3.0, 1.0, 20.0, -0.020),
    ("delft", "short", 103, 2.0, 4.0, 10.0, +0.030),
    ("delft", "long", 104, 4.0, 2.0, 15.0, -0.010),
    ("helsinki-n", "short", 105, 1.5, 3.0, 20.0, -0.030),
    ("helsinki-n", "long", 106, 2.5, 1.0, 5.0, +0.020),
    ("helsinki-s", "short", 107, 4.0, 1.5, 15.0, +0.015),
    ("helsinki-s", "long", 108, 1.0, 4.0, 10.0, -0.025),
    ("schaan", "short", 109, 3.0, 2.5, 10.0, -0.020),
    ("schaan", "long", 110, 2.0, 3.5, 20.0, +0.010),
    ("balzers", "short", 111, 3.5, 1.0, 20.0, +0.025),
    ("balzers", "long", 112, 4.0, 4.0, 15.0, -0.030),
]


@dataclass(frozen=True)
class Scene:
    name: str
    city: str
    route: str
    seed: int
    knobs: dict

    @property
    def dir(self) -> Path:
        return ROOT / self.name

    def settings(self) -> dict:
        c = CITIES[self.city]
        return {"city": str(c.path.relative_to(RAW)), "seed": self.seed, "knobs": self.knobs}

    def drift(self) -> str:
        k = self.knobs
        return (f"walk h{k['heading_walk_deg'] / HEADING_WALK_DEG:g}x pr{k['pitch_walk_deg'] / TILT_WALK_DEG:g}x, "
                f"tilt<={k['max_tilt_deg']:g}, scale {100 * k['scale_drift']:+g}%")


# --holdout N: the same cities and routes with other seeds (+N·HOLDOUT_SEED) and each scene given the
# drift of the scene HOLDOUT_SHIFTS[N] rows further down MATRIX: scenes no default was chosen on
HOLDOUT_SEED, HOLDOUT_SHIFTS = 100, {1: 5, 2: 7}


def use_root(root: Path) -> None:
    """Scenes, run outputs and results.json under ``root`` (the helpers here read these module globals)."""
    global ROOT, OUT, RESULTS
    ROOT, OUT, RESULTS = root, root / "out", root / "results.json"


def holdout_matrix(n: int = 1) -> list[tuple]:
    drift = [row[3:] for row in MATRIX]
    return [(city, route, seed + n * HOLDOUT_SEED, *drift[(k + HOLDOUT_SHIFTS[n]) % len(MATRIX)])
            for k, (city, route, seed, *_) in enumerate(MATRIX)]


def scenes(matrix: list[tuple] | None = None) -> list[Scene]:
    out = []
    for city, route, seed, hw, prw, tilt, scale in matrix or MATRIX:
        c = CITIES[city]
        knobs = {
            **c.knobs,
            "route_length_m": c.short_m if route == "short" else c.long_m,
            "route_closed": True,
            "heading_walk_deg": round(HEADING_WALK_DEG * hw, 4),
            "pitch_walk_deg": round(TILT_WALK_DEG * prw, 4),
            "roll_walk_deg": round(TILT_WALK_DEG * prw, 4),
            "max_tilt_deg": tilt,
            "scale_drift": scale,
            "scale_drift_signed": True,
        }
        out.append(Scene(f"{city}-{route}", city, route, seed, knobs))
    return out


# --- building ------------------------------------------------------------------------------------
def generator_stamp() -> str:
    """Hash of the generator's code (toolkit/synth/*.py) as parsed, without docstrings, comments,
    formatting or ``description=`` texts: editing the knobs' documentation rebuilds nothing."""
    import ast

    h = hashlib.sha1()
    for f in sorted((REPO / "toolkit" / "synth").glob("*.py")):
        tree = ast.parse(f.read_text())
        for node in ast.walk(tree):
            body = getattr(node, "body", None)
            if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                    and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                    and isinstance(body[0].value.value, str)):
                body[0] = ast.Pass()
            if isinstance(node, ast.keyword) and node.arg == "description":
                node.value = ast.Constant(None)
        h.update(f.name.encode() + b"\0" + ast.dump(tree).encode())
    return h.hexdigest()[:12]


def settings_stamp(s: Scene) -> str:
    return hashlib.sha1(json.dumps(s.settings(), sort_keys=True).encode()).hexdigest()[:12]


def read_stamp(s: Scene) -> dict | None:
    p = s.dir / "stamp.json"
    try:
        return json.loads(p.read_text())
    except (OSError, ValueError):
        return None


def crossview() -> str:
    exe = Path(sys.executable).parent / "crossview"
    if not exe.is_file():
        sys.exit(f"{exe}: not found (run `make` first: bench/cities.py uses the checkout's .venv)")
    return str(exe)


def build(s: Scene, code: str) -> dict:
    """Generate the scene unless its stamp matches; write scene-nogps.yaml and the rigid-fit bar."""
    stamp = read_stamp(s)
    want = {"settings": settings_stamp(s), "generator": code}
    if stamp and all(stamp.get(k) == v for k, v in want.items()) and (s.dir / "scene.yaml").is_file():
        return stamp
    city = CITIES[s.city]
    with tempfile.NamedTemporaryFile("w", suffix=".yaml", delete=False) as fh:
        yaml.safe_dump({k: list(v) if isinstance(v, tuple) else v for k, v in s.knobs.items()}, fh)
        cfg = fh.name
    print(f"building {s.name} ({city.label}, {s.route} loop) ...", flush=True)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run([crossview(), "synth", "--city", str(city.path), "--seed", str(s.seed),
                               "--config", cfg, "--out", str(s.dir), "--overwrite"],
                              capture_output=True, text=True)
    finally:
        Path(cfg).unlink(missing_ok=True)
    seconds = time.perf_counter() - t0
    log = proc.stdout + proc.stderr
    if proc.returncode != 0:
        print(log, file=sys.stderr)
        sys.exit(f"{s.name}: crossview synth failed (exit {proc.returncode})")
    manifest = yaml.safe_load((s.dir / "scene.yaml").read_text())
    nogps = dict(manifest)
    nogps["street"] = {k: v for k, v in manifest["street"].items() if k != "gps"}
    (s.dir / "scene-nogps.yaml").write_text(yaml.safe_dump(nogps, sort_keys=False))
    (s.dir / "build.log").write_text(log)
    stats = manifest["synth"]["stats"]
    stamp = {
        **want,
        "seconds": round(seconds, 1),
        "warnings": [ln.strip() for ln in log.splitlines() if re.search(r"warning|no \d+ m route", ln, re.I)],
        "stats": stats,
        "rigid_mean_m": rigid_mean(s.dir),
    }
    (s.dir / "stamp.json").write_text(json.dumps(stamp, indent=1))
    print(f"  {stats['street_points']:,} points, {stats['cameras']} cameras, {stats['route_length_m']:.0f} m "
          f"{'loop' if stats.get('route_closed') else 'open route'}, {seconds:.0f} s", flush=True)
    return stamp


def rigid_mean(root: Path) -> float:
    from toolkit.io.cloud import read_points

    street = read_points(root / "street" / "cloud.ply")
    truth = np.load(root / "truth" / "street_points.npy")
    return round(float(kabsch_error(street, truth).mean()), 4)


def prune(keep: list[Scene]) -> None:
    """Bound the cache: scene folders (and run outputs) not in the current matrix go. Hidden entries
    are left alone: they are scenes or runs being written (``.<name>.partial…``), maybe by another
    bench process, and the generator and the runner clear their own leftovers."""
    names = {s.name for s in keep}
    if not ROOT.is_dir():
        return
    for d in ROOT.iterdir():
        if d.name.startswith("."):
            continue
        if d.is_dir() and d.name != "out" and d.name not in names and (d / "scene.yaml").is_file():
            print(f"removing {d} (not in the matrix)")
            shutil.rmtree(d)
    if OUT.is_dir():
        for d in OUT.iterdir():
            if not d.name.startswith(".") and _scene_of_out(d.name) not in names:
                shutil.rmtree(d) if d.is_dir() else d.unlink()


def _scene_of_out(name: str) -> str:
    stem = name.removesuffix(".log").removesuffix("-gps")
    for r in RECIPES:
        if stem.endswith("-" + r):
            return stem[: -len(r) - 1]
    return stem


# --- running -------------------------------------------------------------------------------------
def gps_variant(s: Scene, sigma_m: float, every: int) -> Path:
    """scene-gps-s{sigma}-e{every}.yaml: the scene with bench-made fixes (see the module doc)."""
    from toolkit.synth.config import SynthConfig
    from toolkit.synth.street_writer import _write_gps

    from _common import truth_centres

    stem = f"gps-s{sigma_m:g}-e{every}"
    manifest = yaml.safe_load((s.dir / "scene.yaml").read_text())
    path = s.dir / "street" / f"{stem}.csv"
    # the generator's fixes (its error model and file), then every N-th kept
    _write_gps(path, truth_centres(s.dir / "truth" / "cameras.txt"),
               SynthConfig(crs=manifest["crs"], gps_sigma_m=sigma_m), np.random.default_rng([s.seed, 5005]))
    head, *rows = path.read_text().splitlines()
    path.write_text("\n".join([head] + rows[::every]) + "\n")
    manifest["street"] = {**manifest["street"], "gps": f"street/{stem}.csv"}
    out = s.dir / f"scene-{stem}.yaml"
    out.write_text(yaml.safe_dump(manifest, sort_keys=False))
    return out


def run_one(s: Scene, recipe: str, gps: bool, overrides: tuple[str, ...] = (), tag: str = "",
            manifest: Path | None = None) -> dict:
    out_root = ROOT / f"out-{tag}" if tag else OUT
    out = out_root / f"{s.name}-{recipe}{'-gps' if gps else ''}"
    manifest = manifest or s.dir / ("scene.yaml" if gps else "scene-nogps.yaml")
    cmd = [crossview(), "run", str(REPO / "recipes" / f"{recipe}.yaml"), "--scene", str(manifest),
           "--out", str(out), "--overwrite", "--no-rerun", "-q"] + [a for o in overrides for a in ("-s", o)]
    out_root.mkdir(parents=True, exist_ok=True)
    if out.exists():  # a failed run must not leave the previous run's metrics.json to be read
        shutil.rmtree(out)
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    seconds = time.perf_counter() - t0
    Path(f"{out}.log").write_text(" ".join(cmd) + "\n" + proc.stdout + proc.stderr)
    return {"out": out, "exit": proc.returncode, "seconds": round(seconds, 1), "registered_sha256": slim_run(out),
            "stderr_tail": (proc.stderr.strip().splitlines() or [""])[-1][:300]}


def row_of(s: Scene, stamp: dict, recipe: str, gps: bool, run: dict) -> dict:
    metrics = {}
    p = Path(run["out"]) / "metrics.json"
    if run["exit"] in (0, 4) or p.is_file():
        try:
            metrics = json.loads(p.read_text())
        except (OSError, ValueError):
            metrics = {}
    truth = metrics.get("truth") or {}
    horiz, e3 = truth.get("horizontal") or {}, truth.get("error_3d") or {}
    matching = metrics.get("matching") or {}
    warnings = metrics.get("warnings") or []
    assessment = metrics.get("assessment") or {}
    if isinstance(assessment.get("bp_converged"), bool):  # the run's self-assessment records it
        converged = assessment["bp_converged"]
    elif metrics.get("matching") is not None:  # else the match stage warned when it did not
        converged = not any("did not converge" in w for w in warnings)
    else:
        converged = None
    p95 = e3.get("p95_m") if recipe == "dsm" else horiz.get("p95_m")
    stats = stamp["stats"]
    row = {
        "scene": s.name,
        "city": CITIES[s.city].label,
        "crop": CITIES[s.city].crop,
        "route": s.route,
        "route_length_m": stats["route_length_m"],
        "route_closed": stats.get("route_closed"),
        "street_points": stats["street_points"],
        "cameras": stats["cameras"],
        "seed": s.seed,
        "drift": s.drift(),
        "source": recipe,
        "gps": gps,
        "horizontal_median_m": horiz.get("median_m"),
        "p95_m": p95,
        "p95_kind": "3d" if recipe == "dsm" else "horizontal",
        "error_3d_mean_m": e3.get("mean_m"),
        "rigid_mean_m": stamp["rigid_mean_m"],
        "precision": matching.get("precision"),
        "recall": matching.get("recall"),
        "n_street_segments": matching.get("n_street_segments"),
        "bp_converged": converged,
        "bp_iterations": assessment.get("bp_iterations"),
        "status": metrics.get("status"),
        "confidence": metrics.get("confidence"),
        "exit": run["exit"],
        "seconds": run["seconds"],
        "error": None if run["exit"] in (0, 4) else run["stderr_tail"],
        "warnings": warnings,
        "registered_sha256": run.get("registered_sha256"),
    }
    row["meets_bar"] = meets_bar(row)
    return row


def meets_bar(r: dict) -> bool:
    h, p, m = r["horizontal_median_m"], r["p95_m"], r["error_3d_mean_m"]
    return h is not None and p is not None and m is not None and h <= 0.5 and p <= 1.5 and m < r["rigid_mean_m"]


# --- reporting -----------------------------------------------------------------------------------
def _f(v, fmt="{:.2f}") -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)):
        return fmt.format(v)
    return str(v)


def print_table(rows: list[dict]) -> None:
    head = ["scene", "city", "route m", "source", "h med", "p95", "3D mean", "rigid", "prec", "rec",
            "BP conv", "status", "conf", "exit", "s"]
    body = [[r["scene"] + ("+gps" if r["gps"] else ""), r["city"],
             f"{r['route_length_m']:.0f}{'' if r['route_closed'] else ' open'}", r["source"],
             _f(r["horizontal_median_m"], "{:.3f}"), _f(r["p95_m"], "{:.3f}") + ("" if r["p95_kind"] == "3d" else "h"),
             _f(r["error_3d_mean_m"], "{:.3f}"), _f(r["rigid_mean_m"], "{:.3f}"), _f(r["precision"]),
             _f(r["recall"]), _f(r["bp_converged"]), _f(r["status"]), _f(r["confidence"]), str(r["exit"]),
             f"{r['seconds']:.0f}"] for r in rows]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *body)]
    for line in [head, ["-" * w for w in widths], *body]:
        print("  ".join(str(x).ljust(w) for x, w in zip(line, widths)).rstrip())
    n = sum(r["meets_bar"] for r in rows)
    print(f"\n{n} of {len(rows)} runs meet the bar (horizontal median <= 0.5 m AND p95 <= 1.5 m "
          f"(3D for dsm, 'h' horizontal for osm/label_map) AND 3D mean < rigid-fit mean)")
    ok = [r["status"] == "ok" for r in rows]
    fa, fn, oa, on = status_cells(ok, [bool(r["meets_bar"]) for r in rows])
    gross_ok = sum(1 for r, o in zip(rows, ok) if o and (r["horizontal_median_m"] or 0) > 2.0)
    print(f"status x accuracy: flagged & accurate {fa}, flagged & not {fn}, "
          f"ok & accurate {oa}, ok & not {on}; 'ok' runs > 2 m off: {gross_ok}")


def status_cells(ok: list[bool], accurate: list[bool]) -> tuple[int, int, int, int]:
    """Runs flagged & accurate, flagged & not, ok & accurate, ok & not."""
    pairs = list(zip(ok, accurate))
    return (sum(not o and a for o, a in pairs), sum(not o and not a for o, a in pairs),
            sum(o and a for o, a in pairs), sum(o and not a for o, a in pairs))


def code_state() -> tuple[str, str]:
    def git(*args) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=REPO).stdout

    sha = git("rev-parse", "--short", "HEAD").strip() or "unknown"
    digest = hashlib.sha1(git("diff", "HEAD").encode())
    # new files the runs may import (a module not yet added) are part of the state too
    untracked = sorted(f for f in git("ls-files", "--others", "--exclude-standard").splitlines()
                       if f.endswith((".py", ".yaml")))
    for f in untracked:
        digest.update(f.encode() + b"\0" + (REPO / f).read_bytes())
    dirty = bool(git("status", "--porcelain", "--untracked-files=no").strip()) or bool(untracked)
    return sha + ("-dirty" if dirty else ""), digest.hexdigest()[:12]


def save(rows: list[dict], state: tuple[str, str]) -> None:
    """Merge ``rows`` into results.json under ``state`` (code_state() when the runs started); a lock
    file keeps two bench processes from dropping each other's rows."""
    import fcntl

    key, diff_hash = state
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    with open(RESULTS.with_suffix(".lock"), "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            data = json.loads(RESULTS.read_text())
        except (OSError, ValueError):
            data = {}
        entry = data.setdefault(key, {"rows": []})
        stamp = time.strftime("%Y-%m-%dT%H:%M:%S")
        new = {(r["scene"], r["source"], r["gps"]) for r in rows}
        entry["rows"] = [r for r in entry["rows"] if (r["scene"], r["source"], r["gps"]) not in new]
        entry["rows"] += [{**r, "diff_sha": diff_hash, "time": stamp} for r in rows]
        entry["updated"] = stamp
        tmp = RESULTS.with_suffix(f".json.tmp{os.getpid()}")
        tmp.write_text(json.dumps(data, indent=1))
        tmp.replace(RESULTS)
    for r in rows:
        r["code_state"] = key


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", help="scenes whose name contains this")
    ap.add_argument("--recipes", default=",".join(RECIPES), help="comma-separated: dsm,osm,label_map")
    ap.add_argument("--gps", action="store_true", help="runs with street/gps.csv (default: without)")
    ap.add_argument("--build-only", action="store_true", help="build (or refresh) the scenes, run nothing")
    ap.add_argument("--jobs", type=int, default=1, help="runs side by side (default 1; the machine has 2 cores)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="recipe override passed to every run as -s (needs --tag)")
    ap.add_argument("--tag", default="", help="a variant's name: outputs go to data/cities/out-TAG/, rows under "
                                              "the code state + TAG")
    ap.add_argument("--gps-sigma-m", type=float, help="with --gps: bench-made fixes of this error (m; needs --tag)")
    ap.add_argument("--gps-every", type=int, default=1, help="with --gps-sigma-m: a fix every N images")
    ap.add_argument("--holdout", type=int, nargs="?", const=1, default=0, choices=(1, 2),
                    help="a held-out matrix: other seeds and drifts, under data/cities-holdout/ (2: a second one, "
                         "under data/cities-holdout2/)")
    ap.add_argument("--replicas", type=int, default=1, choices=(1, 2, 3),
                    help="also run the matrix with the street frame's units × 1.001 (2) and × 0.999 (3), as "
                         "tags TAG-s1001, TAG-s0999 (base-… without --tag)")
    args = ap.parse_args()
    if args.gps_sigma_m is not None and not (args.gps and args.tag):
        sys.exit("--gps-sigma-m needs --gps and --tag")
    if args.set and not args.tag:
        sys.exit("--set needs --tag (a variant must not overwrite the default runs)")
    if args.replicas > 1 and any(o.split("=", 1)[0].strip() == "street_scale" for o in args.set):
        sys.exit("--replicas sets street_scale itself: drop --set street_scale=…")
    if not RAW.is_dir():
        sys.exit(f"{RAW}: real city data not present (the 'shared' folder beside the repo); nothing to run")
    missing = sorted({str(c.path) for c in CITIES.values() if not c.path.is_file()})
    if missing:
        sys.exit(f"real city files missing: {', '.join(missing)}")
    recipes = [r.strip().removesuffix(".yaml") for r in args.recipes.split(",") if r.strip()]
    bad = [r for r in recipes if not (REPO / "recipes" / f"{r}.yaml").is_file()]
    if bad:
        sys.exit(f"unknown recipe(s): {', '.join(bad)}")
    if args.holdout:
        use_root(REPO / "data" / ("cities-holdout" if args.holdout == 1 else f"cities-holdout{args.holdout}"))
    every = scenes(holdout_matrix(args.holdout) if args.holdout else None)
    chosen = [s for s in every if not args.only or args.only in s.name]
    if not chosen:
        sys.exit(f"--only {args.only!r}: no scene matches ({', '.join(s.name for s in every)})")
    prune(every)
    code = generator_stamp()
    stamps = {s.name: build(s, code) for s in chosen}

    print(f"\n{'scene':16s} {'city':22s} {'crop':27s} {'route':>11s} {'points':>10s} {'cams':>5s} "
          f"{'seed':>4s}  {'drift':40s} {'gen s':>6s}")
    for s in chosen:
        st = stamps[s.name]
        stats = st["stats"]
        route = f"{stats['route_length_m']:.0f} m {'loop' if stats.get('route_closed') else 'open'}"
        print(f"{s.name:16s} {CITIES[s.city].label:22s} {CITIES[s.city].crop:27s} {route:>11s} "
              f"{stats['street_points']:>10,} {stats['cameras']:>5d} {s.seed:>4d}  {s.drift():40s} "
              f"{st['seconds']:>6.0f}")
        for w in st.get("warnings", []):
            print(f"{'':16s} warning: {w}")
    if args.build_only:
        return 0
    manifests = {s.name: gps_variant(s, args.gps_sigma_m, args.gps_every) for s in chosen} \
        if args.gps_sigma_m is not None else {}

    replicas = [(args.tag, list(args.set))] + [
        (f"{args.tag or 'base'}-{name}", list(args.set) + [f"street_scale={value}"])
        for name, value in REPLICA_SCALES[:args.replicas - 1]]
    keys = [run_matrix(chosen, recipes, stamps, manifests, args.gps, args.jobs, tag, overrides)
            for tag, overrides in replicas]
    if args.replicas > 1:
        print(f"replicas: {' '.join(keys)} (bench/matrix_floor.py --base {' '.join(keys)}, or --variant … "
              "against a base's replicas)")
    return 0


def run_matrix(chosen: list[Scene], recipes: list[str], stamps: dict, manifests: dict, gps: bool, jobs: int,
               tag: str, overrides: list[str]) -> str:
    """Every recipe on every chosen scene (``jobs`` side by side), rows saved as they finish and
    printed; the results.json key they were saved under."""
    # short loops first: a run cut short still has every city once
    runs = [(s, r) for route in ("short", "long") for s in chosen if s.route == route for r in recipes]
    print(f"\n{len(runs)} runs ({'with' if gps else 'without'} GPS, {jobs} at a time"
          f"{', ' + ' '.join(overrides) if overrides else ''})", flush=True)

    def work(job):
        s, r = job
        with lock:
            state = code_state()  # what the run's process loads (others may commit meanwhile)
            if tag:
                state = (f"{state[0]}+{tag}", state[1])
        run = run_one(s, r, gps, tuple(overrides), tag, manifests.get(s.name))
        row = row_of(s, stamps[s.name], r, gps, run)
        with lock:
            save([row], state)  # as it goes: an interrupted matrix keeps the runs it finished
            print(f"  {s.name} {r}: exit {run['exit']}, {run['seconds']:.0f} s, h med "
                  f"{_f(row['horizontal_median_m'], '{:.3f}')}, 3D mean {_f(row['error_3d_mean_m'], '{:.3f}')}"
                  + (f" ({row['error']})" if row["error"] else ""), flush=True)
        return row

    if tag and not (ROOT / f"out-{tag}").exists():  # room for this variant's outputs
        bound_folders(list(ROOT.glob("out-*")), KEEP_VARIANTS - 1, KEEP_SLIM)
    require_free_disk(ROOT, FREE_GIB + FREE_GIB_PER_RUN * len(runs))
    lock = threading.Lock()
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        done = {(row["scene"], row["source"]): row for row in pool.map(work, runs)}
    rows = [done[(s.name, r)] for s in chosen for r in recipes]
    print()
    print_table(rows)
    keys = sorted({r["code_state"] for r in rows})
    print(f"rows written to {RESULTS.relative_to(REPO)} under {', '.join(map(repr, keys))}")
    return keys[-1]


if __name__ == "__main__":
    sys.exit(main())
