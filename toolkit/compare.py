"""``crossview compare``: run variants of a recipe on the same scene(s) and tabulate metrics and times.

    crossview compare recipes/dsm.yaml --swap overview=overview.osm,overview.label_map \\
        --swap match=match.icm,match.greedy --with recipes/baseline-open3d.yaml --seeds 3

Variants: the recipe itself, one per swapped stage (one factor at a time, the way the paper's §4.2
compares DSM vs OSM vs label maps; ``--grid`` runs every combination instead) and one per
``--with`` recipe. Each run writes its full output (report.html, metrics.json, …) under
``OUT/runs/<scene>/<variant>/``; the comparison writes ``OUT/table.md`` and ``OUT/table.csv`` (one
row per variant, mean over scenes, ± std in the markdown when there are several), ``OUT/runs.csv``
(one row per run) and ``OUT/recording.rrd`` (the first scene's runs, each under ``/<variant>/``, with
a side-by-side blueprint). Each run's self-assessment (``toolkit.status``) gives the ``status`` and
``confidence`` columns: per variant, ``ok``/``unreliable`` when all its runs agree, else ``k/n
unreliable``, and the mean confidence. An unreliable run is not a failed one.
"""

from __future__ import annotations

import argparse
import csv
import itertools
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.errors import CrossviewError, RecipeError, SceneError
from toolkit.metrics_model import RunMetrics

# The metrics columns, each a toolkit.metrics_model.KeyFigures attribute (as the run summary shows them)
METRIC_COLUMNS: tuple[str, ...] = (
    "chamfer_3d_mean_m", "chamfer_3d_std_m", "chamfer_2d_mean_m", "chamfer_2d_std_m", "paired_fraction",
    "error_h_median_m", "error_3d_mean_m", "error_3d_p95_m", "within_1m_h", "match_precision", "match_recall",
    "camera_median_m",
)
MD_HEADERS = {
    "chamfer_3d_mean_m": "Chamfer 3D (m)", "chamfer_3d_std_m": "3D std", "chamfer_2d_mean_m": "Chamfer 2D (m)",
    "chamfer_2d_std_m": "2D std", "paired_fraction": "paired", "error_h_median_m": "err h median (m)",
    "error_3d_mean_m": "err 3D mean (m)", "error_3d_p95_m": "err 3D p95 (m)", "within_1m_h": "≤1 m (h)",
    "match_precision": "precision", "match_recall": "recall", "camera_median_m": "camera (m)",
    "time_total_s": "time (s)", "confidence": "confidence",
}


@dataclass(frozen=True)
class Variant:
    """One configuration to run: a recipe file plus ``-s`` overrides."""

    name: str
    recipe: Path
    overrides: tuple[str, ...] = ()
    description: str = ""


@dataclass
class RunRow:
    variant: str
    scene: str
    metrics: RunMetrics = field(default_factory=RunMetrics)  # the evaluation's (empty: none or failed)
    timings: dict[str, float] = field(default_factory=dict)
    error: str | None = None
    out_dir: Path | None = None
    seconds: float | None = None  # the run's wall time: steps may overlap, so not their sum
    status: str | None = None  # the self-assessment: "ok" | "unreliable" (None: failed or not assessed)
    confidence: float | None = None


# --- planning ---------------------------------------------------------------------------------
def parse_swap(text: str) -> tuple[str, list[str]]:
    """``match=match.icm,match.greedy`` → ('match', ['match.icm', 'match.greedy'])."""
    if "=" not in text:
        raise RecipeError(f"--swap {text}: expected STEP=STAGE[,STAGE...] (e.g. match=match.icm,match.greedy)")
    step, rhs = (p.strip() for p in text.split("=", 1))
    keys = [k.strip() for k in rhs.split(",") if k.strip()]
    if not step or not keys:
        raise RecipeError(f"--swap {text}: expected STEP=STAGE[,STAGE...]")
    for k in keys:
        if k.split(".", 1)[0] != step or "." not in k:
            raise RecipeError(f"--swap {text}: {k!r} is not a stage of kind {step!r} (use {step}.<name>)")
    return step, keys


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_") or "variant"


def plan_variants(recipe_path: Path, swaps: Sequence[str] = (), with_recipes: Sequence[Path] = (),
                  grid: bool = False, overrides: Sequence[str] = ()) -> list[Variant]:
    """The variants to run; names are unique and safe as folder names and rerun entity paths."""
    from toolkit.recipe import load_recipe

    base = load_recipe(recipe_path, overrides)
    parsed = [parse_swap(s) for s in swaps]
    for step, _ in parsed:
        if base.step(step) is None:
            raise RecipeError(f"--swap {step}=...: {recipe_path} has no step {step!r}")
    variants = [Variant(_safe(base.name), Path(recipe_path), tuple(overrides), f"{base.name} (as written)")]
    if grid and parsed:
        options = [[(step, k) for k in [base.step(step).use, *keys]] for step, keys in parsed]
        for combo in itertools.product(*options):
            changed = [(s, k) for s, k in combo if k != base.step(s).use]
            if changed:
                variants.append(_swap_variant(recipe_path, overrides, changed))
    else:
        for step, keys in parsed:
            for k in keys:
                if k != base.step(step).use:
                    variants.append(_swap_variant(recipe_path, overrides, [(step, k)]))
    for path in with_recipes:
        other = load_recipe(path, overrides)
        variants.append(Variant(_safe(other.name), Path(path), tuple(overrides), f"{other.name} ({Path(path).name})"))
    seen: dict[str, int] = {}
    unique = []
    for v in variants:
        n = seen.get(v.name, 0)
        seen[v.name] = n + 1
        unique.append(v if n == 0 else Variant(f"{v.name}_{n + 1}", v.recipe, v.overrides, v.description))
    return unique


def _swap_variant(recipe_path: Path, overrides: Sequence[str], changed: list[tuple[str, str]]) -> Variant:
    name = "+".join(k.split(".", 1)[1] for _, k in changed)
    extra = tuple(f"steps.{s}.use={k}" for s, k in changed)
    return Variant(_safe(name), Path(recipe_path), tuple(overrides) + extra, ", ".join(f"{s}: {k}" for s, k in changed))


def seed_scenes(scene_dir: Path, n: int, cache_root: Path | None = None) -> list[Path]:
    """The synthetic scene and n−1 siblings with the next seeds and the same generator config
    (generated once into ``<scene>-seed<k>`` beside it, then reused)."""
    from toolkit.scene import load_scene

    scene = load_scene(scene_dir)
    synth = scene.manifest.get("synth")
    if not isinstance(synth, dict) or not ({"preset", "city"} & set(synth)):
        raise SceneError(f"{scene.root / 'scene.yaml'}: --seeds needs a synthetic scene "
                         "(its manifest has no 'synth:' entry naming a preset or city)")
    seed0 = int(synth.get("seed", 0))
    config = dict(synth.get("config") or {})
    out = [scene.root]
    root = cache_root or scene.root.parent
    for k in range(1, n):
        target = root / f"{scene.root.name}-seed{seed0 + k}"
        if not (target / "scene.yaml").is_file():
            from toolkit.synth import generate as gen

            if "preset" in synth:
                gen.generate(str(synth["preset"]), seed0 + k, target, **config)
            else:
                gen.generate_from_city(Path(synth["city"]), seed0 + k, target, **config)
        out.append(target)
    return out


# --- running ----------------------------------------------------------------------------------
def validate_variants(variants: Sequence[Variant], scenes: Sequence[Path | None], registry: Any = None) -> None:
    """Stage names, parameters and scene files of every variant, before any computation."""
    from toolkit.recipe import load_recipe
    from toolkit.runner import build

    for v in variants:
        recipe = load_recipe(v.recipe, v.overrides)
        for scene in scenes:
            try:
                build(recipe, scene=scene, registry=registry)
            except CrossviewError as exc:
                raise type(exc)(f"variant {v.name}: {exc}") from exc


def run_variants(variants: Sequence[Variant], scenes: Sequence[Path | None], out: Path, rerun: bool = True,
                 quiet: bool = False, registry: Any = None) -> list[RunRow]:
    """Run every variant on every scene; a failing run becomes a row with its error."""
    from rich.console import Console

    from toolkit.observe import MultiObserver, ProgressObserver
    from toolkit.runner import run_recipe

    console = Console(stderr=True)
    validate_variants(variants, scenes, registry)
    out.mkdir(parents=True, exist_ok=True)
    rec = None
    if rerun:
        from toolkit.viz_rerun import open_shared_recording

        rec = open_shared_recording(out / "recording.rrd", [v.name for v in variants])
    rows: list[RunRow] = []
    try:
        for si, scene in enumerate(scenes):
            scene_name = _safe(Path(scene).name) if scene is not None else "scene"
            for v in variants:
                if not quiet:
                    console.print(f"[bold magenta]■ {v.name}[/] on {scene_name}: {v.description}")
                obs: Any = ProgressObserver(quiet=quiet)
                rerun_obs = None
                if rec is not None and si == 0:
                    from toolkit.recipe import load_recipe
                    from toolkit.viz_rerun import RerunObserver

                    rerun_obs = RerunObserver(recording=rec, prefix=f"/{v.name}")
                    rerun_obs.log_text("recipe", f"```yaml\n{load_recipe(v.recipe, v.overrides).to_yaml()}\n```")
                    obs = MultiObserver(obs, rerun_obs)
                row = RunRow(v.name, scene_name)
                t0 = time.perf_counter()
                try:
                    res = run_recipe(v.recipe, scene=scene, out=out / "runs" / scene_name / v.name,
                                     overrides=list(v.overrides), observer=obs, overwrite=True, rerun=False,
                                     registry=registry)
                    metrics = res.results.metrics
                    row.metrics = RunMetrics.of(metrics)
                    row.timings = dict(res.timings)
                    row.out_dir = res.out_dir
                    row.seconds = time.perf_counter() - t0
                    if res.assessment is not None:
                        row.status, row.confidence = res.assessment.status, res.assessment.confidence
                except Exception as exc:  # noqa: BLE001 — one failing variant must not lose the others
                    if isinstance(exc, CrossviewError):
                        row.error = str(exc)
                    else:
                        row.error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
                    row.timings = {"total": time.perf_counter() - t0}
                    console.print(f"  [red]failed[/] {v.name} on {scene_name}: {row.error}")
                rows.append(row)
    finally:
        if rec is not None:
            rec.flush()
            rec.disconnect()
    return rows


# --- tables -----------------------------------------------------------------------------------
def run_record(row: RunRow) -> dict[str, Any]:
    rec: dict[str, Any] = {"variant": row.variant, "scene": row.scene, "status": row.status,
                           "confidence": row.confidence}
    figures = row.metrics.key_figures()
    rec.update({col: getattr(figures, col) for col in METRIC_COLUMNS})
    total = row.seconds if row.seconds is not None else sum(row.timings.values()) if row.timings else None
    rec["time_total_s"] = None if total is None else float(total)
    for step, sec in row.timings.items():
        rec[f"time_{step}_s"] = float(sec)
    rec["error"] = row.error or ""
    return rec


def aggregate(rows: Sequence[RunRow], variants: Sequence[Variant]) -> list[dict[str, Any]]:
    """One record per variant: mean over its successful runs (and std, n_runs, n_failed)."""
    records = [run_record(r) for r in rows]
    time_cols = sorted({k for r in records for k in r if k.startswith("time_") and k != "time_total_s"},
                       key=lambda k: _step_order(k))
    out = []
    for v in variants:
        mine = [r for r in records if r["variant"] == v.name]
        ok = [r for r in mine if not r["error"]]
        agg: dict[str, Any] = {"variant": v.name, "description": v.description, "n_runs": len(ok),
                               "n_failed": len(mine) - len(ok), "status": variant_status(ok)}
        for col in ["confidence"] + list(METRIC_COLUMNS) + ["time_total_s"] + time_cols:
            vals = np.array([r[col] for r in ok if r.get(col) is not None], float)
            agg[col] = float(vals.mean()) if len(vals) else None
            agg[f"{col}__std"] = float(vals.std()) if len(vals) > 1 else None
        agg["error"] = "; ".join(sorted({r["error"] for r in mine if r["error"]}))
        out.append(agg)
    return out


def variant_status(records: Sequence[dict[str, Any]]) -> str | None:
    """"ok" / "unreliable" when every assessed run says so, else "k/n unreliable" (None: none assessed)."""
    statuses = [r["status"] for r in records if r.get("status")]
    if not statuses:
        return None
    if len(set(statuses)) == 1:
        return statuses[0]
    return f"{statuses.count('unreliable')}/{len(statuses)} unreliable"


def _step_order(col: str) -> int:
    from toolkit.stage import KINDS

    step = col[len("time_"):-len("_s")]
    return KINDS.index(step) if step in KINDS else len(KINDS)


def _md_cell(value: float | None, std: float | None, col: str) -> str:
    if value is None:
        return "—"
    pct = col in ("paired_fraction", "within_1m_h", "match_precision", "match_recall")
    if isinstance(value, str):
        return value
    text = f"{100 * value:.0f} %" if pct else (f"{value:.1f}" if col.startswith("time") else f"{value:.2f}")
    if std is not None:
        text += f" ± {100 * std:.0f}" if pct else f" ± {std:.2f}"
    return text


def markdown_table(agg: Sequence[dict[str, Any]], n_scenes: int) -> str:
    cols = [c for c in ("status", "confidence") if any(a.get(c) is not None for a in agg)]
    cols += [c for c in METRIC_COLUMNS if any(a.get(c) is not None for a in agg)] + ["time_total_s"]
    lines = [f"Comparison over {n_scenes} scene(s); mean" + (" ± std over scenes" if n_scenes > 1 else "") + ".",
             "",
             "| variant | " + " | ".join(MD_HEADERS.get(c, c) for c in cols) + " |",
             "|---|" + "---:|" * len(cols)]
    for a in agg:
        cells = [_md_cell(a.get(c), a.get(f"{c}__std"), c) for c in cols]
        name = a["variant"] + (f" (failed: {a['error']})" if a["n_runs"] == 0 and a["error"] else "")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    time_cols = [c for c in agg[0] if c.startswith("time_") and c != "time_total_s" and not c.endswith("__std")] \
        if agg else []
    if time_cols:
        lines += ["", "Seconds per step:", "",
                  "| variant | " + " | ".join(c[len("time_"):-len("_s")] for c in time_cols) + " |",
                  "|---|" + "---:|" * len(time_cols)]
        for a in agg:
            lines.append(f"| {a['variant']} | " + " | ".join(_md_cell(a.get(c), None, c) for c in time_cols) + " |")
    lines += ["", "Variants:", ""] + [f"- **{a['variant']}**: {a['description']}" for a in agg]
    return "\n".join(lines) + "\n"


def write_csv(path: Path, records: Sequence[dict[str, Any]]) -> None:
    """Columns in first-seen order; ``__std`` columns only when some run set has a spread."""
    cols: list[str] = []
    for r in records:
        cols += [k for k in r if k not in cols]
    cols = [c for c in cols if not c.endswith("__std") or any(r.get(c) is not None for r in records)]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=[c.replace("__std", "_std") for c in cols])
        w.writeheader()
        for r in records:
            w.writerow({c.replace("__std", "_std"): _csv_value(r.get(c)) for c in cols})


def _csv_value(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return round(v, 6)
    return v


def write_tables(out: Path, rows: Sequence[RunRow], variants: Sequence[Variant], n_scenes: int) -> str:
    agg = aggregate(rows, variants)
    md = markdown_table(agg, n_scenes)
    (out / "table.md").write_text(md)
    write_csv(out / "table.csv", agg)
    write_csv(out / "runs.csv", [run_record(r) for r in rows])
    return md


# --- command line -----------------------------------------------------------------------------
def register(subparsers) -> None:
    p = subparsers.add_parser(
        "compare", help="run variants of a recipe on the same scene(s) and tabulate them",
        description="Run the recipe, one variant per swapped stage (or every combination with --grid) "
                    "and each --with recipe on the same scene(s); write table.md, table.csv, runs.csv and "
                    "one recording.rrd with each variant under /<variant>/.")
    p.add_argument("recipe", type=Path, help="the reference recipe")
    p.add_argument("--swap", action="append", default=[], metavar="STEP=STAGE[,STAGE...]",
                   help="stages to try in place of the recipe's, e.g. overview=overview.osm,overview.label_map")
    p.add_argument("--with", dest="with_recipes", action="append", default=[], type=Path, metavar="RECIPE",
                   help="another whole recipe to compare (e.g. recipes/baseline-open3d.yaml)")
    p.add_argument("--grid", action="store_true", help="every combination of the swaps, not one at a time")
    p.add_argument("--scene", action="append", default=[], help="scene folder (repeatable; default: the recipe's)")
    p.add_argument("--seeds", type=int, default=1, metavar="N",
                   help="also run on N−1 more synthetic scenes with the next seeds (generated once)")
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override applied to every variant, e.g. -s steps.match.params.c1=0.2")
    p.add_argument("--out", type=Path, help="output folder (default out/compare-<recipe name>)")
    p.add_argument("--no-rerun", action="store_true", help="do not write recording.rrd")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from toolkit.recipe import load_recipe
    from toolkit.runner import resolve_scene_path

    if args.seeds < 1:
        raise CrossviewError(f"--seeds {args.seeds}: must be at least 1")
    variants = plan_variants(args.recipe, args.swap, args.with_recipes, args.grid, args.overrides)
    base = load_recipe(args.recipe, args.overrides)
    scenes: list[Path] = [Path(s) for s in args.scene] or [resolve_scene_path(base, None)]
    if args.seeds > 1:
        scenes = [s for scene in scenes for s in seed_scenes(scene, args.seeds)]
    out = args.out or Path("out") / f"compare-{_safe(base.name)}"
    rows = run_variants(variants, scenes, out, rerun=not args.no_rerun, quiet=args.quiet)
    md = write_tables(out, rows, variants, len(scenes))
    print(md)
    print(f"tables: {out / 'table.md'}, {out / 'table.csv'}, {out / 'runs.csv'}")
    if not args.no_rerun:
        print(f"recording: rerun {out / 'recording.rrd'}")
    failed = [r for r in rows if r.error]
    return 1 if failed else 0
