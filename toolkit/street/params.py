"""Parameter groups of the street helpers (``toolkit.params``): old flat keys are ``<group>_<field>``.

Each helper module owns a small group (``split.py``: ``SplitConfig``, ...) that the street stage
nests (``steps.street.params.split.window_m``); ``split_window_m`` is read as that key.
"""

from __future__ import annotations

from toolkit.params import GroupedParams, ParamGroup, group, nest_flat_keys, nested_groups

__all__ = ["GroupedParams", "StreetConfig", "group", "nest_flat_keys", "nested_groups"]


class StreetConfig(ParamGroup):
    """Base of the street helpers' parameter groups (old flat key: ``<group>_<field>`` unless set)."""
