"""Façade points: steep normals whose neighbourhood is steep too (Ling & Qin 2022, street-view building segments).

A point is a façade point when the angle between its normal and the vertical exceeds
``angle_deg`` AND more than ``neighbour_fraction`` of its k nearest neighbours (itself excluded)
pass the same angle test (the released code computes this test and then overwrites it; here it
is real). With several scales, a point is a façade point when at least ``min_votes`` scales say so.

Neighbour lists are queried once, in chunks, for the points passing the angle test only; each
chunk also yields the curvature of its points and the first ``graph_k`` neighbours that region
growing links, so no (points × k) table is ever held whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import Field, model_validator
from scipy.spatial import cKDTree

from toolkit.street.normals import build_tree, coordinate_columns, neighbourhood_covariance, symmetric_eigenvalues
from toolkit.street.params import StreetConfig
from toolkit.threads import map_in_order

CHUNK = 1 << 16


class FacadeConfig(StreetConfig):
    """The façade rule (see ``facade_points``)."""

    angle_deg: float = Field(75.0, gt=0, lt=90, description="façade: normal more than this from vertical (degrees)")
    neighbour_fraction: float = Field(
        0.75, ge=0, lt=1, description="façade: more than this share of the k neighbours pass the angle test")


class MultiscaleConfig(StreetConfig):
    """The façade rule voted over several neighbourhood sizes."""

    knn: list[int] | None = Field(
        None, description="optional several k (e.g. [10, 20, 30]): façade when ≥ multiscale.min_votes scales agree")
    min_votes: int = Field(2, ge=1, description="scales that must call a point façade")

    @model_validator(mode="after")
    def _scales(self) -> MultiscaleConfig:
        if self.knn is not None:
            if len(self.knn) == 0 or min(self.knn) < 3:
                raise ValueError("multiscale.knn must list k values ≥ 3")
            if self.min_votes > len(self.knn):
                raise ValueError("multiscale.min_votes exceeds the number of scales")
        return self

    def scales(self, knn: int) -> list[int]:
        """The neighbourhood sizes voting (ascending; ``[knn]`` without multiscale)."""
        return sorted(set(self.knn)) if self.knn else [knn]

    def votes(self) -> int:
        """Scales that must agree (1 without multiscale)."""
        return self.min_votes if self.knn else 1


@dataclass(frozen=True)
class Facade:
    """index: (F,) analysis indices of façade points (ascending); graph: (F,graph_k) int32 analysis
    indices of their nearest neighbours (itself excluded), nearest first; curvature: (F,) float32
    surface variation λ0/Σλ over their ``knn`` nearest points (itself included)."""

    index: np.ndarray
    graph: np.ndarray
    curvature: np.ndarray


def steep(normals: np.ndarray, up: np.ndarray, angle_deg: float) -> np.ndarray:
    """(M,) bool: angle between the normal line and ``up`` above ``angle_deg``."""
    return np.abs(normals @ up.astype(normals.dtype)) < np.cos(np.radians(angle_deg))


def facade_points(points: np.ndarray, tree: cKDTree, columns: tuple[np.ndarray, np.ndarray, np.ndarray],
                  normals_per_scale: list[np.ndarray], scales: list[int], knn: int, up: np.ndarray,
                  angle_deg: float, neighbour_fraction: float, min_votes: int, graph_k: int) -> Facade:
    passes = [steep(n, up, angle_deg) for n in normals_per_scale]
    candidates = np.flatnonzero(np.logical_or.reduce(passes)).astype(np.int32)
    kq = min(max(max(scales), knn, graph_k) + 1, len(points))

    def chunk(start: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        cand = candidates[start:start + CHUNK]
        _, nbrs = tree.query(points[cand], k=kq)
        nbrs = nbrs.astype(np.int32)
        votes = np.zeros(len(cand), dtype=np.int32)
        for k, ok in zip(scales, passes):
            share = ok[nbrs[:, 1:k + 1]].mean(axis=1)
            votes += ok[cand] & (share > neighbour_fraction)
        keep = votes >= min_votes
        if not keep.any():
            return None
        lam = symmetric_eigenvalues(neighbourhood_covariance(columns, nbrs[keep, :knn]))
        total = lam.sum(axis=1)
        curv = np.where(total > 0, lam[:, 0] / np.where(total > 0, total, 1.0), 0.0).astype(np.float32)
        return cand[keep].astype(np.int32), np.ascontiguousarray(nbrs[keep, 1:graph_k + 1]), curv

    # whole chunks (query and the numpy after it) run in threads, joined in chunk order
    parts = [r for r in map_in_order(chunk, range(0, len(candidates), CHUNK)) if r is not None]
    keep_idx, keep_graph, keep_curv = (list(x) for x in zip(*parts)) if parts else ([], [], [])
    if not keep_idx:
        return Facade(np.zeros(0, np.int32), np.zeros((0, graph_k), np.int32), np.zeros(0, np.float32))
    return Facade(np.concatenate(keep_idx), np.concatenate(keep_graph), np.concatenate(keep_curv))


def find_facade(points: np.ndarray, normals_per_scale: list[np.ndarray], knn: int, up: np.ndarray,
                facade: FacadeConfig, multiscale: MultiscaleConfig, graph_k: int) -> Facade:
    """``facade_points`` of the analysis cloud ``points`` (M,3), its KD-tree built here."""
    return facade_points(points, build_tree(points), coordinate_columns(points), normals_per_scale,
                         multiscale.scales(knn), knn, up, facade.angle_deg, facade.neighbour_fraction,
                         multiscale.votes(), graph_k)
