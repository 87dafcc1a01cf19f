"""Nested parameter groups of the stages and the old flat spelling of their keys.

A helper module owns a small pydantic group (``toolkit.street.split``: ``SplitConfig``, ...) that a
stage's Params nests (``steps.street.params.split.window_m``). Stage Params used to be flat; a
group's old flat key is ``flat_names[field]``, else ``flat_prefix + field`` (``flat_prefix`` None:
``<group>_``). ``GroupedParams`` reads the old keys as the nested ones, so recipes and ``-s``
overrides written before the grouping keep working. A field given both ways takes the spelling
given later (``toolkit.recipe`` puts an override's and a child recipe's keys last), so
``-s steps.refine.params.joint.window_m=200`` beats a recipe's ``joint_window_m: 160``.
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from toolkit.stage import StageParams


class ParamGroup(BaseModel):
    """Base of the helpers' parameter groups: unknown fields rejected, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    flat_prefix: ClassVar[str | None] = None
    flat_names: ClassVar[dict[str, str]] = {}

    @classmethod
    def flat_keys(cls, group: str) -> dict[str, str]:
        """Old flat key → field name, for the group nested as ``group``."""
        prefix = f"{group}_" if cls.flat_prefix is None else cls.flat_prefix
        return {cls.flat_names.get(f, prefix + f): f for f in cls.model_fields}


def nested_groups(model: type[BaseModel]) -> dict[str, type[ParamGroup]]:
    """The fields of ``model`` that are parameter groups, by name, with their group class."""
    return {name: f.annotation for name, f in model.model_fields.items()
            if isinstance(f.annotation, type) and issubclass(f.annotation, ParamGroup)}


def nest_flat_keys(data: Any, groups: dict[str, type[ParamGroup]]) -> Any:
    """``data`` with every old flat key moved to ``data[<group>][<field>]`` (a ``mode="before"``
    validator). Only fields the group has are moved (an unknown key stays, to be rejected under
    its own name); given both ways, the key later in ``data`` wins."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for group, cls in groups.items():
        flat = {key: field for key, field in cls.flat_keys(group).items() if key in data}
        if not flat:
            continue
        nested = out.get(group) or {}
        if isinstance(nested, BaseModel):
            nested = nested.model_dump(exclude_unset=True)
        if not isinstance(nested, dict):
            continue  # rejected by the group's own validation
        nested = dict(nested)
        order = list(data)
        for key, field in flat.items():
            value = out.pop(key)
            if field not in nested or group not in data or order.index(key) > order.index(group):
                nested[field] = value
        out[group] = nested
    return out


class GroupedParams(StageParams):
    """Stage Params nesting parameter groups; the groups' old flat keys are read as nested."""

    @model_validator(mode="before")
    @classmethod
    def _flat_keys(cls, data: Any) -> Any:
        return nest_flat_keys(data, nested_groups(cls))


def group(cls: type[ParamGroup], description: str) -> Any:
    """A Params field holding the group ``cls``, its defaults by default."""
    return Field(default_factory=cls, description=description)
