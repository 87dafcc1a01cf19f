"""``crossview batch``: one recipe over many scenes on dask.distributed.

A ``LocalCluster`` by default (``--workers N``, one thread each, separate processes) or any running
scheduler (``--scheduler tcp://host:8786``). Each scene writes its own output folder as ``run`` does;
a failing scene becomes a row with its error, the others go on. The summary is written as
``summary.csv`` and ``summary.md`` in the batch folder and printed.

A row's ``status`` is the run's self-assessment (``ok`` | ``unreliable``, with its ``confidence``
and main ``reason``; ``toolkit.status``) or, when the scene did not finish, ``failed`` (a user error)
| ``error`` (a bug). An unreliable scene is a finished scene: only failed ones set the exit code.
"""

from __future__ import annotations

import argparse
import csv
import glob
import os
import time
from pathlib import Path
from typing import Any

from toolkit.errors import CrossviewError

# Metrics columns of the summary table: (column, toolkit.metrics_model.KeyFigures attribute)
COLUMNS: tuple[tuple[str, str], ...] = (
    ("h_median_m", "error_h_median_m"),
    ("h_mean_m", "error_h_mean_m"),
    ("e3d_p95_m", "error_3d_p95_m"),
    ("chamfer2d_m", "chamfer_2d_mean_m"),
    ("chamfer3d_m", "chamfer_3d_mean_m"),
    ("paired", "paired_fraction"),
    ("match_precision", "match_precision"),
    ("match_recall", "match_recall"),
)


def scene_label(scene_dir: Path) -> str:
    return scene_dir.name or str(scene_dir)


def run_one(recipe_path: str, scene_dir: str, out_dir: str, overrides: list[str], overwrite: bool) -> dict[str, Any]:
    """Run one scene; never raises for user errors (they become the row's ``error``)."""
    from toolkit.metrics_model import RunMetrics
    from toolkit.runner import run_recipe

    row: dict[str, Any] = {"scene": scene_label(Path(scene_dir)), "status": "ok", "confidence": None,
                           "reason": "", "error": ""}
    t0 = time.perf_counter()
    try:
        res = run_recipe(recipe_path, scene=scene_dir, out=out_dir, overrides=overrides,
                         overwrite=overwrite, rerun=False)
        if res.assessment is not None:
            row.update(status=res.assessment.status, confidence=res.assessment.confidence,
                       reason=res.assessment.main_reason if not res.assessment.reliable else "")
        metrics = res.results.metrics
        figures = RunMetrics.of(metrics).key_figures()
        for col, name in COLUMNS:
            row[col] = getattr(figures, name)
        row.update({f"t_{k}_s": round(v, 3) for k, v in res.timings.items()})
        row["warnings"] = len(res.warnings)
    except CrossviewError as exc:
        row.update(status="failed", error=str(exc))
    except Exception as exc:  # a bug in one scene must not stop the batch; report it as such
        row.update(status="error", error=f"internal error: {type(exc).__name__}: {' '.join(str(exc).split())}")
    row["seconds"] = round(time.perf_counter() - t0, 3)
    return row


def scene_bytes(scene_dir: Path) -> int:
    """Size of the scene's files (a proxy for its run time); 0 when unreadable."""
    try:
        return sum(f.stat().st_size for f in Path(scene_dir).rglob("*") if f.is_file())
    except OSError:
        return 0


def find_scenes(pattern: str) -> list[Path]:
    paths = sorted({Path(p).parent if Path(p).name == "scene.yaml" else Path(p) for p in glob.glob(pattern)})
    if not paths:
        raise CrossviewError(f"--scenes {pattern!r}: no scene matched")
    labels = [scene_label(p) for p in paths]
    dupes = sorted({x for x in labels if labels.count(x) > 1})
    if dupes:
        raise CrossviewError(f"--scenes {pattern!r}: several scenes are named {dupes[0]!r}; "
                             "outputs would collide")
    return paths


def worker_config() -> dict[str, Any]:
    """Dask settings for LocalCluster workers that keep a scene as fast as in ``crossview run``.

    Dask's default worker environment sets ``MALLOC_TRIM_THRESHOLD_``; any fixed trim threshold
    turns off glibc's adaptive mmap threshold, so every large numpy temporary is mmapped, faulted
    in and unmapped again. Two campus scenes side by side spent ~11 s each in the kernel instead of
    ~4 s (stage times 1.4-1.8x those of ``run``). A task also runs in a worker thread, where glibc
    would give it its own arena with the same churn: one arena (``MALLOC_ARENA_MAX=1``). The
    profiler samples the task thread every 10 ms under the GIL; a scene is one call, so it is off.
    """
    import dask

    environ = {k: v for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
               if k != "MALLOC_TRIM_THRESHOLD_"}
    environ["MALLOC_ARENA_MAX"] = 1
    return {"distributed.nanny.pre-spawn-environ": environ, "distributed.worker.profile.enabled": False}


def run_batch(recipe_path: Path, scenes: list[Path], out_root: Path, workers: int = 2,
              scheduler: str | None = None, overrides: list[str] | None = None, overwrite: bool = False,
              progress: bool = True) -> list[dict[str, Any]]:
    from dask.distributed import Client, LocalCluster, as_completed

    from toolkit.batch_client import finished_line
    from toolkit.recipe import load_recipe
    from toolkit.registry import default_registry

    recipe = load_recipe(recipe_path, overrides or [])
    for spec in recipe.steps:  # fail fast on recipe errors, before starting any worker
        default_registry().get(spec.use).from_config(spec.params)
    cluster = None
    # dask's nanny writes the workers' environment (OMP_NUM_THREADS=1, …) into this process's
    # os.environ before it spawns them: without the restore, this process (and so everything it
    # runs after the batch) is held to one thread
    environ = dict(os.environ)
    if scheduler:
        from toolkit.batch_client import connect_scheduler

        client = connect_scheduler(scheduler)
    else:
        import dask

        with dask.config.set(worker_config()):
            cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                   dashboard_address=None, silence_logs=40)
        _restore_environ(environ)
        client = Client(cluster)
    rows: list[dict[str, Any]] = []
    try:
        out_root.mkdir(parents=True, exist_ok=True)  # only once a scheduler is there: nothing half-written
        # largest scenes first (by bytes on disk): the last scene running alone on one worker is
        # then a small one, which keeps the other workers' idle tail short
        futures = [client.submit(run_one, str(recipe_path.resolve()), str(s.resolve()),
                                 str((out_root / scene_label(s)).resolve()), list(overrides or []), overwrite,
                                 pure=False, key=f"scene-{scene_label(s)}", priority=i)
                   for i, s in enumerate(sorted(scenes, key=scene_bytes))]
        if progress:
            from rich.progress import Progress

            with Progress(transient=True) as bar:
                task = bar.add_task(f"{len(scenes)} scenes", total=len(scenes))
                for fut in as_completed(futures):
                    rows.append(fut.result())
                    bar.console.print(finished_line(rows[-1]), markup=False, highlight=False)
                    bar.advance(task)
        else:
            rows = [f.result() for f in as_completed(futures)]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
        _restore_environ(environ)  # a worker the nanny restarted wrote it again
    rows.sort(key=lambda r: r["scene"])
    write_summary(out_root, rows)
    return rows


def _restore_environ(saved: dict[str, str]) -> None:
    """Put back the variables of ``saved`` (a copy of ``os.environ``) that were changed or added since."""
    for key in [k for k in os.environ if k not in saved]:
        del os.environ[key]
    for key, value in saved.items():
        if os.environ.get(key) != value:
            os.environ[key] = value


def write_summary(out_root: Path, rows: list[dict[str, Any]]) -> None:
    cols: list[str] = []
    for r in rows:
        cols += [c for c in r if c not in cols]
    with open(out_root / "summary.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        w.writerows(rows)
    (out_root / "summary.md").write_text(markdown_table(rows, cols))


def _fmt(v: Any) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.3f}"
    return str(v).replace("|", "\\|")


def markdown_table(rows: list[dict[str, Any]], cols: list[str]) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(_fmt(r.get(c)) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def run(args: argparse.Namespace) -> int:
    scenes = find_scenes(args.scenes)
    from toolkit.recipe import load_recipe

    name = load_recipe(args.recipe, args.overrides).name
    out_root = args.out or Path("out") / f"{name}-batch"
    rows = run_batch(args.recipe, scenes, out_root, workers=args.workers, scheduler=args.scheduler,
                     overrides=args.overrides, overwrite=args.overwrite, progress=not args.quiet)
    cols = ["scene", "status", "confidence", *[c for c, _ in COLUMNS], "seconds", "error"]
    print(markdown_table(rows, cols), end="")
    print(f"summary: {out_root / 'summary.csv'}  {out_root / 'summary.md'}")
    return exit_code(rows)


FAILED = ("failed", "error")  # row statuses of scenes that did not finish (ok / unreliable did)


def exit_code(rows: list[dict[str, Any]]) -> int:
    """0 when every scene finished (ok or unreliable), 3 when some failed, 2 when all failed."""
    bad = [r for r in rows if r["status"] in FAILED]
    return 0 if not bad else 3 if len(bad) < len(rows) else 2


def register(subparsers: Any) -> None:
    p = subparsers.add_parser("batch", help="run one recipe over many scenes on Dask",
                              description="Run a recipe over many scene folders on dask.distributed. "
                              "Exit code 0 when every scene finished (its status ok or unreliable), 3 when "
                              "some failed, 2 when all failed.")
    p.add_argument("recipe", type=Path)
    p.add_argument("--scenes", required=True, help="glob of scene folders or scene.yaml files (quote it)")
    grp = p.add_mutually_exclusive_group()
    grp.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes (default 2)")
    grp.add_argument("--scheduler", help="address of a running dask scheduler, e.g. tcp://host:8786")
    p.add_argument("--out", type=Path, help="batch folder (default out/<recipe name>-batch)")
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    p.add_argument("--overwrite", action="store_true", help="replace existing per-scene outputs")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=run)
