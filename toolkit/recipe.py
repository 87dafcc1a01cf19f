"""YAML recipes: schema, one-level ``base:`` inheritance, ``-s dotted.key=value`` overrides.

Only ``yaml.safe_load``; stages are named by registry key, never by import path. Every error names
the recipe file and the path inside it (``steps.match.params.c1``).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable

import yaml

from toolkit.errors import RecipeError
from toolkit.stage import KINDS

TOP_KEYS = ("recipe", "name", "base", "scene", "street_scale", "steps", "log", "outputs", "stream")
STEP_KEYS = ("use", "params")
LOG_KEYS = ("rerun", "max_points", "progress", "report")
OUTPUT_KEYS = ("ply",)  # outputs: {ply: false} skips registered.ply (registered.laz is always written)


@dataclass(frozen=True)
class StepSpec:
    name: str
    use: str
    params: dict[str, Any]


@dataclass(frozen=True)
class Recipe:
    """A resolved recipe: base merged, overrides applied, schema checked."""

    path: Path
    name: str
    scene: str | None
    steps: tuple[StepSpec, ...]
    log: dict[str, Any] = field(default_factory=dict)
    outputs: dict[str, Any] = field(default_factory=dict)
    street_scale: Any = None  # 'auto', a number, or None (the scene's setting)
    stream: Any = None  # toolkit.stream.StreamSettings (large street clouds, chunked passes)

    def to_dict(self) -> dict[str, Any]:
        out = {
            "recipe": 1, "name": self.name, "scene": self.scene,
            "steps": {s.name: {"use": s.use, "params": dict(s.params)} for s in self.steps},
            "log": dict(self.log),
        }
        if self.outputs:
            out["outputs"] = dict(self.outputs)
        if self.street_scale is not None:
            out["street_scale"] = self.street_scale
        if self.stream is not None and self.stream.model_fields_set:
            out["stream"] = self.stream.model_dump(exclude_unset=True)
        return out

    def to_yaml(self) -> str:
        return yaml.safe_dump(self.to_dict(), sort_keys=False)

    def step(self, name: str) -> StepSpec | None:
        return next((s for s in self.steps if s.name == name), None)


def _read_yaml(path: Path) -> dict[str, Any]:
    if not path.is_file():
        raise RecipeError(f"{path}: recipe not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"line {mark.line + 1}: " if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise RecipeError(f"{path}: invalid YAML, {where}{problem}") from exc
    if not isinstance(data, dict):
        raise RecipeError(f"{path}: a recipe is a mapping with 'recipe: 1', got {type(data).__name__}")
    return data


def _merge(base: dict[str, Any], child: dict[str, Any]) -> dict[str, Any]:
    out = copy.deepcopy(base)
    for key, value in child.items():
        if key == "base":
            continue
        if key == "steps" and isinstance(value, dict) and isinstance(out.get("steps"), dict):
            steps = out["steps"]
            for name, spec in value.items():
                old = steps.get(name)
                if isinstance(spec, dict) and isinstance(old, dict):
                    same_stage = spec.get("use", old.get("use")) == old.get("use")
                    merged = {"use": spec.get("use", old.get("use"))}
                    # changing `use` resets the step's params: the old ones belong to another stage
                    params = dict(old.get("params") or {}) if same_stage else {}
                    for key, value in (spec.get("params") or {}).items():
                        params.pop(key, None)  # last: given both ways, the child's spelling wins
                        params[key] = value
                    merged["params"] = params
                    steps[name] = merged
                else:
                    steps[name] = copy.deepcopy(spec)
        elif key in ("log", "outputs") and isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key].update(value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def parse_override(text: str) -> tuple[list[str], Any]:
    """``steps.match.params.c1=0.2`` → (['steps','match','params','c1'], 0.2)."""
    if "=" not in text:
        raise RecipeError(f"-s {text}: expected key=value (e.g. steps.match.params.c1=0.2)")
    key, raw = text.split("=", 1)
    parts = [p for p in key.strip().split(".") if p]
    if not parts:
        raise RecipeError(f"-s {text}: empty key")
    try:
        value = yaml.safe_load(raw) if raw.strip() else ""
    except yaml.YAMLError:
        value = raw
    return parts, value


def apply_overrides(data: dict[str, Any], overrides: Iterable[str]) -> dict[str, Any]:
    data = copy.deepcopy(data)
    for text in overrides:
        parts, value = parse_override(text)
        node = data
        for i, part in enumerate(parts[:-1]):
            nxt = node.get(part) if isinstance(node, dict) else None
            if nxt is None:
                if parts[0] == "steps" and i == 1:
                    raise RecipeError(f"-s {text}: the recipe has no step {part!r}")
                nxt = node[part] = {}
            if not isinstance(nxt, dict):
                raise RecipeError(f"-s {text}: {'.'.join(parts[:i + 1])} is not a mapping")
            node = nxt
        if parts[0] == "steps" and len(parts) == 3 and parts[2] == "use":
            node["params"] = {}  # a new stage starts from its own defaults
        node[parts[-1]] = value
        if parts[0] == "steps" and len(parts) >= 4 and parts[2] == "params":
            params = data["steps"][parts[1]]["params"]
            params[parts[3]] = params.pop(parts[3])  # last: given both ways, the override's spelling wins
    return data


def load_recipe(path: str | Path, overrides: Iterable[str] = (), scene: str | None = None) -> Recipe:
    path = Path(path)
    data = _read_yaml(path)
    if "base" in data:
        base_ref = data["base"]
        if not isinstance(base_ref, str):
            raise RecipeError(f"{path}: base: must be a recipe file name, got {base_ref!r}")
        base_path = (path.parent / base_ref).resolve()
        if base_path == path.resolve():
            raise RecipeError(f"{path}: base: loop (the recipe names itself)")
        base = _read_yaml(base_path)
        if "base" in base:
            loop = (base_path.parent / str(base["base"])).resolve() == path.resolve()
            what = "loop" if loop else "chain"
            raise RecipeError(f"{path}: base: {what} through {base_path.name} "
                              "(inheritance is one level: a base recipe may not have a base)")
        data = _merge(base, data)
    data = apply_overrides(data, overrides)
    if scene is not None:
        data["scene"] = scene
    return _validate(path, data)


def _validate(path: Path, data: dict[str, Any]) -> Recipe:
    unknown = [k for k in data if k not in TOP_KEYS]
    if unknown:
        raise RecipeError(f"{path}: unknown key {unknown[0]!r} (allowed: {', '.join(TOP_KEYS)})")
    if data.get("recipe") != 1:
        raise RecipeError(f"{path}: recipe: must be 1 (format version), got {data.get('recipe')!r}")
    name = data.get("name") or path.stem
    if not isinstance(name, str):
        raise RecipeError(f"{path}: name: must be a string, got {name!r}")
    scene = data.get("scene")
    if scene is not None and not isinstance(scene, str):
        raise RecipeError(f"{path}: scene: must be a folder path, got {scene!r}")
    steps_raw = data.get("steps")
    if not isinstance(steps_raw, dict) or not steps_raw:
        raise RecipeError(f"{path}: steps: must be a non-empty mapping of step name → {{use, params}}")
    steps: list[StepSpec] = []
    last = -1
    for step_name, spec in steps_raw.items():
        where = f"{path}: steps.{step_name}"
        if step_name not in KINDS:
            raise RecipeError(f"{where}: unknown step (steps are named by kind: {', '.join(KINDS)})")
        if not isinstance(spec, dict):
            raise RecipeError(f"{where}: must be a mapping with 'use' (e.g. use: {step_name}.<name>)")
        bad = [k for k in spec if k not in STEP_KEYS]
        if bad:
            raise RecipeError(f"{where}: unknown key {bad[0]!r} (allowed: use, params)")
        use = spec.get("use")
        if not isinstance(use, str) or "." not in use:
            raise RecipeError(f"{where}.use: must be a stage key like '{step_name}.<name>', got {use!r}")
        if use.split(".", 1)[0] != step_name:
            raise RecipeError(f"{where}.use: stage {use!r} is not of kind {step_name!r}")
        params = spec.get("params") or {}
        if not isinstance(params, dict):
            raise RecipeError(f"{where}.params: must be a mapping, got {type(params).__name__}")
        order = KINDS.index(step_name)
        if order < last:
            raise RecipeError(f"{where}: wrong step order ({step_name} must come before {KINDS[last]}; "
                              f"order: {' → '.join(KINDS)})")
        last = order
        steps.append(StepSpec(step_name, use, dict(params)))
    log = data.get("log") or {}
    if not isinstance(log, dict):
        raise RecipeError(f"{path}: log: must be a mapping")
    bad = [k for k in log if k not in LOG_KEYS]
    if bad:
        raise RecipeError(f"{path}: log: unknown key {bad[0]!r} (allowed: {', '.join(LOG_KEYS)})")
    return Recipe(path=path, name=name, scene=scene, steps=tuple(steps), log=dict(log),
                  outputs=_outputs(path, data.get("outputs")), street_scale=data.get("street_scale"),
                  stream=_stream(path, data.get("stream")))


def _stream(path: Path, stream: Any):
    from pydantic import ValidationError

    from toolkit.stream import StreamSettings

    if stream is not None and not isinstance(stream, dict):
        raise RecipeError(f"{path}: stream: must be a mapping (e.g. stream: {{max_points: 8000000}})")
    try:
        return StreamSettings(**(stream or {}))
    except ValidationError as exc:
        err = exc.errors()[0]
        loc = ".".join(str(p) for p in err.get("loc", ()))
        raise RecipeError(f"{path}: stream.{loc}: {err.get('msg', 'invalid')}") from exc


def _outputs(path: Path, outputs: Any) -> dict[str, Any]:
    outputs = outputs or {}
    if not isinstance(outputs, dict):
        raise RecipeError(f"{path}: outputs: must be a mapping (e.g. outputs: {{ply: false}})")
    bad = [k for k in outputs if k not in OUTPUT_KEYS]
    if bad:
        raise RecipeError(f"{path}: outputs: unknown key {bad[0]!r} (allowed: {', '.join(OUTPUT_KEYS)})")
    if not isinstance(outputs.get("ply", True), bool):
        raise RecipeError(f"{path}: outputs.ply: must be true or false, got {outputs['ply']!r}")
    return dict(outputs)
