"""The ``crossview`` command: run, validate, stages, demo, synth, compare, batch.

User errors print one line and exit 2; ``--debug`` shows the traceback instead.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from pathlib import Path
from typing import Sequence

from toolkit.errors import CrossviewError

# Sub-commands that live in their own modules, each exposing ``register(subparsers)``.
PLUGGED_COMMANDS = ("toolkit.synth.command", "toolkit.compare", "toolkit.batch", "toolkit.apply_warp",
                    "toolkit.scene_init")


def _add_run_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("recipe", type=Path, help="YAML recipe (see recipes/)")
    p.add_argument("--scene", help="scene folder (overrides the recipe's 'scene:')")
    p.add_argument("-s", "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a recipe value, e.g. -s steps.match.params.c1=0.2 (repeatable)")


def cmd_run(args: argparse.Namespace) -> int:
    from toolkit.observe import ProgressObserver
    from toolkit.runner import run_recipe
    from toolkit.status import EXIT_UNRELIABLE, verdict_line
    from toolkit.summary import print_summary

    obs = ProgressObserver(quiet=args.quiet)
    res = run_recipe(args.recipe, scene=args.scene, out=args.out, overrides=args.overrides,
                     observer=obs, overwrite=args.overwrite, rerun=False if args.no_rerun else None,
                     scheduler=args.scheduler)
    if not args.quiet:  # -q: only errors, and the verdict below (an error-like outcome)
        print_summary(res)
    line = verdict_line(res.assessment)
    if line is None:
        return 0
    sys.stdout.flush()  # the verdict must be the last line, after the summary on stdout
    print(line, file=sys.stderr)
    return EXIT_UNRELIABLE


def cmd_validate(args: argparse.Namespace) -> int:
    from toolkit.recipe import load_recipe
    from toolkit.runner import build
    from toolkit.validate import gps_match, uses_gps

    plan = build(load_recipe(args.recipe, args.overrides), scene=args.scene)
    print(f"{args.recipe}: ok — scene {plan.scene.root} ({plan.scene.crs}), "
          f"{len(plan.stages)} steps: {', '.join(s.use for s, _ in plan.stages)}")
    stages = [stage for _, stage in plan.stages]
    if uses_gps(plan.scene, stages):
        found = gps_match(plan.capture)
        print(f"gps: {found.matched} of {found.fixes} fixes match images")
    return 0


def cmd_stages(args: argparse.Namespace) -> int:
    from toolkit.registry import default_registry
    from toolkit.stage import KINDS

    reg = default_registry()
    classes, broken = [], []
    for key in reg.keys():
        try:
            classes.append(reg.get(key))
        except Exception as exc:  # a plugin that fails to import must not hide the others
            broken.append(f"{key:26s} cannot be loaded: {type(exc).__name__}: {exc}")
    classes.sort(key=lambda c: (KINDS.index(c.kind), c.name))
    for line in broken:
        print(line, file=sys.stderr)
    for cls in classes:
        doc = (cls.__doc__ or "").strip().splitlines()
        print(f"{cls.key():26s} {doc[0] if doc else ''}")
        if args.verbose:
            rows = _param_rows(cls.Params)
            width = max([28] + [len(key) for key, _, _ in rows])
            for key, default, description in rows:
                value = "" if default is None else f"= {default:12}"
                print(f"    {key:{width}s} {value:14s}  {description}")
    return 0


def _param_rows(model: type, prefix: str = "") -> list[tuple[str, str | None, str]]:
    """(dotted key, default repr, description) per parameter; a nested group (refine's ``scale``,
    unary's ``route_prior``) is a row without default, followed by its fields as ``group.field``."""
    from pydantic import BaseModel

    rows: list[tuple[str, str | None, str]] = []
    for fname, f in model.model_fields.items():
        default = f.default if f.default_factory is None else f.default_factory()
        if isinstance(default, BaseModel):
            rows.append((prefix + fname, None, f.description or ""))
            rows += _param_rows(type(default), f"{prefix}{fname}.")
        else:
            rows.append((prefix + fname, repr(default), f.description or ""))
    return rows


def cmd_demo(args: argparse.Namespace) -> int:
    from toolkit.demo import run_demo

    return run_demo(preset=args.preset, seed=args.seed, quiet=args.quiet)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("crossview-toolkit")
    except PackageNotFoundError:
        return "unknown (not installed)"


class OneLineHandler(logging.Handler):
    """Notes and warnings of the ``crossview.*`` loggers (readers: a raster reprojected, a float32
    cloud) as one stderr line each, each line once per command (a file read by several steps)."""

    def __init__(self, level: int = logging.NOTSET) -> None:
        super().__init__(level)
        self.shown: set[str] = set()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            level = "note" if record.levelno < logging.WARNING else record.levelname.lower()
            line = f"crossview: {level}: {' '.join(record.getMessage().split())}"
            if line not in self.shown:
                self.shown.add(line)
                print(line, file=sys.stderr)
        except Exception:
            self.handleError(record)


def reader_messages(quiet: bool):
    """Show the readers' notes (INFO) and warnings for the duration of a command; ``-q`` hides both."""
    from toolkit.logcache import listening

    return listening(OneLineHandler(logging.ERROR if quiet else logging.INFO))


class OneLineParser(argparse.ArgumentParser):
    """argparse, but a usage error is one line (and exit code 2, as argparse does)."""

    def error(self, message: str):  # type: ignore[override]
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="crossview", description=(
        "Register street-view point clouds onto over-view data (DSM, OSM, label maps) "
        "by graph matching of building segments."))
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    parser.add_argument("--version", action="version", version=f"crossview {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=OneLineParser)
    sub.required = True

    p = sub.add_parser("run", help="run a recipe on a scene", description="Run a recipe; outputs go to "
                       "out/<name>/ (written to a temporary folder, renamed when complete).")
    _add_run_args(p)
    p.add_argument("--out", type=Path, help="output folder (default out/<recipe name>)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--no-rerun", action="store_true", help="do not write recording.rrd")
    p.add_argument("--scheduler", help="Dask scheduler for the chunked passes over a street cloud of more than "
                   "stream.max_points points, e.g. tcp://host:8786")
    p.add_argument("-q", "--quiet", action="store_true",
                   help="print nothing but errors (and the final 'registration unreliable' line)")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("validate", help="check a recipe and its scene without running",
                       description="Validate stage names, parameters, step order and scene files.")
    _add_run_args(p)
    p.add_argument("-q", "--quiet", action="store_true", help="no notes or warnings")
    p.set_defaults(func=cmd_validate)

    p = sub.add_parser("stages", help="list registered stages", description="List every stage.")
    p.add_argument("-v", "--verbose", action="store_true", help="show parameters, defaults, descriptions")
    p.set_defaults(func=cmd_stages)

    p = sub.add_parser("demo", help="synthesise the built-in scene (once) and run the demo recipe",
                       description="Generate data/demo if missing, then run recipes/demo.yaml on it.")
    p.add_argument("--preset", default="campus", help="synthetic preset for data/demo (default campus)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=cmd_demo)

    for module in PLUGGED_COMMANDS:
        try:
            mod = importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name and module.startswith(exc.name):
                continue  # that command is not built yet
            raise
        mod.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        with reader_messages(getattr(args, "quiet", False)):
            return int(args.func(args) or 0)
    except CrossviewError as exc:
        if debug:
            raise
        print(f"crossview: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("crossview: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # a bug, not a user error: say so, keep it to one line
        if debug:
            raise
        print(f"crossview: internal error: {type(exc).__name__}: {' '.join(str(exc).split())} "
              "(run with --debug for the traceback)", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
