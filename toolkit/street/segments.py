"""Façade segments from façade points: grow, cut terraces, merge, drop the small, absorb leftovers.

Region growing (Rabbani) as connected components of the façade kNN graph, bends split
(``growing.py``); rows of terraced houses cut where the façade top steps (``split.py``); walls
meeting at a corner and pieces of one occluded wall merged when they reach the same height
(``merge.py``); segments under ``min_diameter_m`` wide, ``min_height_m`` high or ``min_points``
dropped; leftover façade points absorbed by an adjacent segment whose normal agrees
(``absorb.py``). Segment indices are ordered by decreasing size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.street.absorb import AbsorbConfig, absorb_leftovers
from toolkit.street.facade import Facade
from toolkit.street.growing import GrowingConfig, group_min_max, grow_regions
from toolkit.street.merge import MergeConfig, merge_segments
from toolkit.street.outline import diameters, relabel_by_size
from toolkit.street.split import SplitConfig, split_terraces


@dataclass(frozen=True)
class FacadeSegments:
    """The façade points in a segment: index (P,) their analysis indices, labels (P,) int32 their
    segment 0..count-1 (by decreasing size), xy (P,2) levelled horizontal coordinates."""

    index: np.ndarray
    labels: np.ndarray
    xy: np.ndarray
    count: int


def facade_segments(points: np.ndarray, normals: np.ndarray, facade: Facade, rotation: np.ndarray, *,
                    growing: GrowingConfig, split: SplitConfig, merge: MergeConfig, absorb: AbsorbConfig,
                    min_diameter_m: float, min_height_m: float, min_points: int) -> FacadeSegments:
    """The segments of the façade points of the analysis cloud ``points`` (M,3) with ``normals``
    (M,3) float32; ``rotation`` levels the analysis frame."""
    xyz = points[facade.index] @ rotation.T
    labels = np.zeros(0, dtype=np.int32)
    if len(facade.index):
        fac_normals = normals[facade.index] @ rotation.T.astype(np.float32)
        azimuth = np.arctan2(fac_normals[:, 1], fac_normals[:, 0])
        labels = grow_regions(fac_normals, facade.graph, facade.index, len(points), facade.curvature,
                              growing.smooth_angle_deg, growing.seed_curvature_max, azimuth,
                              growing.bend_split_angle_deg)
        labels = split_terraces(xyz, azimuth, labels, **split.model_dump())
        labels = merge_segments(xyz[:, :2], xyz[:, 2], azimuth, labels, **merge.model_dump(), min_points=min_points)
        labels = drop_small(relabel_by_size(labels), xyz, min_diameter_m, min_height_m, min_points)
        if absorb.hops > 0:
            labels = relabel_by_size(absorb_leftovers(labels, facade.graph, facade.index, len(points), xyz,
                                                      fac_normals, absorb.angle_deg, absorb.link_m, absorb.hops))
    count = int(labels.max()) + 1 if len(labels) and labels.max() >= 0 else 0
    in_seg = labels >= 0
    return FacadeSegments(facade.index[in_seg], labels[in_seg], xyz[in_seg, :2], count)


def drop_small(labels: np.ndarray, xyz: np.ndarray, min_diameter_m: float, min_height_m: float,
               min_points: int) -> np.ndarray:
    """Labels with the segments under ``min_diameter_m`` wide, ``min_height_m`` high or ``min_points``
    points set to -1, the others renumbered in order."""
    ok = labels >= 0
    if not ok.any():
        return labels
    n = int(labels.max()) + 1
    lo, hi = group_min_max(xyz[ok, 2], labels[ok], n)
    big = ((diameters(xyz[ok, :2], labels[ok], n) >= min_diameter_m) & (hi - lo >= min_height_m)
           & (np.bincount(labels[ok], minlength=n) >= min_points))
    remap = np.full(n, -1, dtype=np.int32)
    remap[big] = np.arange(int(big.sum()), dtype=np.int32)
    out = labels.copy()
    out[ok] = remap[labels[ok]]
    return out
