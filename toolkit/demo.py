"""``crossview demo`` / ``make demo``: synthesise the built-in scene once, run recipes/demo.yaml on it.

The summary shows the run's self-assessment (``toolkit.status``); an unreliable demo exits 4 as
``crossview run`` does.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

from rich.console import Console

from toolkit.errors import CrossviewError

ROOT = Path(__file__).resolve().parents[1]


def _available_prefix(recipe):
    """The recipe truncated before its first step whose stage cannot be loaded (and those steps)."""
    from toolkit.registry import default_registry

    reg = default_registry()
    for i, spec in enumerate(recipe.steps):
        try:
            reg.get(spec.use)
        except Exception:
            return dataclasses.replace(recipe, steps=recipe.steps[:i]), [s.use for s in recipe.steps[i:]]
    return recipe, []


def run_demo(preset: str = "campus", seed: int = 0, quiet: bool = False) -> int:
    from toolkit.observe import ProgressObserver
    from toolkit.recipe import load_recipe
    from toolkit.runner import run_recipe
    from toolkit.status import EXIT_UNRELIABLE, verdict_line
    from toolkit.summary import print_summary

    console = Console(stderr=True)
    scene_dir = Path("data/demo")
    t0 = time.perf_counter()
    if not (scene_dir / "scene.yaml").is_file():
        from toolkit.synth.generate import generate

        if not quiet:
            console.print(f"[bold]synthesising[/] the built-in '{preset}' scene (seed {seed}) into {scene_dir}")
        generate(preset, seed, scene_dir)
        if not quiet:
            console.print(f"  done in {time.perf_counter() - t0:.1f} s")
    recipe_path = Path("recipes/demo.yaml")
    if not recipe_path.is_file():
        recipe_path = ROOT / "recipes" / "demo.yaml"
    recipe, missing = _available_prefix(load_recipe(recipe_path, scene=str(scene_dir)))
    if missing:
        console.print(f"[yellow]demo:[/] these stages are not available yet, running the first "
                      f"{len(recipe.steps)} steps only: missing {', '.join(missing)}")
    if not recipe.steps:
        raise CrossviewError("demo: no stage of recipes/demo.yaml is available")
    res = run_recipe(recipe_path, scene=scene_dir, out=Path("out/demo"), overwrite=True,
                     observer=ProgressObserver(quiet=quiet), recipe=recipe)
    if not quiet:  # -q: as crossview run, only errors and the verdict below
        print_summary(res)
        console.print(f"demo finished in {time.perf_counter() - t0:.1f} s")
    line = verdict_line(res.assessment)
    if line is None:
        return 0
    sys.stdout.flush()  # as crossview run: the verdict is the last line
    console.print(line, markup=False, highlight=False)
    return EXIT_UNRELIABLE
