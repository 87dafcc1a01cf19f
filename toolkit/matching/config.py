"""Parameter groups of the matching helpers and the old flat spelling of their keys.

Each helper module owns a small pydantic group (``pose_search.py``: ``PoseSearchConfig``, ...) that
a stage nests (``steps.unary.params.pose.refine_top_k``). The unary stage's Params used to be flat;
``GroupedParams`` reads those flat keys (``refine_top_k``, ``gps_radius_m``) as the nested key, so
recipes and ``-s`` overrides written before the grouping keep working.
"""

from __future__ import annotations

from typing import Any, ClassVar

from pydantic import BaseModel, ConfigDict, model_validator

from toolkit.stage import StageParams


class MatchingConfig(BaseModel):
    """Base of the matching helpers' parameter groups: unknown fields rejected, immutable."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    # the old flat key of a field: flat_names[field], else flat_prefix + field
    flat_prefix: ClassVar[str] = ""
    flat_names: ClassVar[dict[str, str]] = {}

    @classmethod
    def flat_keys(cls) -> dict[str, str]:
        """Old flat key → field name."""
        return {cls.flat_names.get(f, cls.flat_prefix + f): f for f in cls.model_fields}


def nest_flat_keys(data: Any, groups: dict[str, type[MatchingConfig]]) -> Any:
    """``data`` with every old flat key moved to ``data[<group>][<field>]`` (a ``mode="before"``
    validator); a field given both ways is an error naming the nested key."""
    if not isinstance(data, dict):
        return data
    out = dict(data)
    for group, cls in groups.items():
        flat = {key: field for key, field in cls.flat_keys().items() if key in data}
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
    """Stage Params nesting matching parameter groups; the groups' old flat keys are read as nested."""

    @model_validator(mode="before")
    @classmethod
    def _flat_keys(cls, data: Any) -> Any:
        groups = {name: f.annotation for name, f in cls.model_fields.items()
                  if isinstance(f.annotation, type) and issubclass(f.annotation, MatchingConfig)}
        return nest_flat_keys(data, groups)
