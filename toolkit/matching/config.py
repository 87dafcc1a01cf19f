"""Parameter groups of the matching helpers (``toolkit.params``): old flat keys are the field names.

Each helper module owns a small group (``pose_search.py``: ``PoseSearchConfig``, ...) that the unary
stage nests (``steps.unary.params.pose.refine_top_k``); ``refine_top_k`` is read as that key, and
``flat_prefix`` / ``flat_names`` say otherwise (``gps_radius_m``, ``anchor_spacing_m``).
"""

from __future__ import annotations

from typing import ClassVar

from toolkit.params import GroupedParams, ParamGroup, nest_flat_keys

__all__ = ["GroupedParams", "MatchingConfig", "nest_flat_keys"]


class MatchingConfig(ParamGroup):
    """Base of the matching helpers' parameter groups (old flat key: the field name unless set)."""

    flat_prefix: ClassVar[str | None] = ""

    @classmethod
    def flat_keys(cls, group: str = "") -> dict[str, str]:
        return super().flat_keys(group)
