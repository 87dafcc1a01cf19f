"""Parameter groups of the street helpers and the old flat spelling of their keys.

Each helper module owns a small pydantic group (``split.py``: ``SplitConfig``, ...) that the street
stage nests (``steps.street.params.split.window_m``). The stage's Params used to be flat, most
groups' keys prefixed by the group's name (``split_window_m``; ``flat_prefix`` says otherwise);
``nest_flat_keys`` reads those as the nested key, so recipes and ``-s`` overrides written before
the grouping keep working.
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, Field, model_validator

from toolkit.stage import StageParams


class StreetConfig(BaseModel):
    """Base of the street helpers' parameter groups: unknown fields rejected, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    # the old flat key of a field is flat_prefix + field; None: "<group>_"
    flat_prefix: ClassVar[str | None] = None


def nested_groups(model: type[BaseModel]) -> dict[str, type[StreetConfig]]:
    """The fields of ``model`` that are street parameter groups, by name, with their group class."""
    return {name: f.annotation for name, f in model.model_fields.items()
            if isinstance(f.annotation, type) and issubclass(f.annotation, StreetConfig)}


def nest_flat_keys(data: Any, groups: dict[str, type[StreetConfig]]) -> Any:
    """``data`` with every old flat key (``<group>_<field>``) moved to ``data[<group>][<field>]``.

    For a ``mode="before"`` model validator. Only fields the group has are moved (an unknown
    ``split_x`` stays, to be rejected under its own name); a field given both ways is an error.
    """
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for group, cls in groups.items():
        prefix = f"{group}_" if cls.flat_prefix is None else cls.flat_prefix
        flat = {prefix + field: field for field in cls.model_fields if prefix + field in data}
        if not flat:
            continue
        nested = out.get(group) or {}
        if isinstance(nested, BaseModel):
            nested = nested.model_dump(exclude_unset=True)
        if not isinstance(nested, dict):
            continue  # rejected by the group's own validation
        nested = dict(nested)
        for key, field in flat.items():
            if field in nested:
                raise ValueError(f"{key} and {group}.{field} both given: keep {group}.{field}")
            nested[field] = out.pop(key)
        out[group] = nested
    return out


class GroupedParams(StageParams):
    """Stage Params nesting street parameter groups; the groups' old flat keys are read as nested."""

    @model_validator(mode="before")
    @classmethod
    def _flat_keys(cls, data: Any) -> Any:
        return nest_flat_keys(data, nested_groups(cls))


def group(cls: type[StreetConfig], description: str) -> Any:
    """A Params field holding the group ``cls``, its defaults by default."""
    return Field(default_factory=cls, description=description)
