"""Scores of street segments against ``truth/street_labels.npy`` (building id per point; -1 ground,
-2 clutter/outlier), used by tests and ``bench/street_accuracy.py``.

- Façade points: precision and recall of "in a segment" (point_labels ≥ 0) vs "on a building".
- Buildings: a building is eligible when its points span at least ``min_facade_m`` horizontally
  (levelled frame); it is covered when some segment holds ≥ ``purity`` of its points from it.
- Vertical error: angle between the found up and the true one in the input frame, the latter from
  a rigid fit of the input points onto ``truth/street_points.npy`` (scene CRS, z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.street.outline import diameters
from toolkit.threads import thread_budget
from toolkit.types import StreetSegments


@dataclass(frozen=True)
class StreetScore:
    facade_precision: float
    facade_recall: float  # over every building point (roofs seen from the street included)
    buildings_eligible: int
    buildings_covered: int
    segments: int
    segments_pure: int  # segments with ≥ purity of their points from one building
    wall_recall: float = float("nan")  # over building points on steep true surfaces (when known)

    @property
    def coverage(self) -> float:
        return self.buildings_covered / self.buildings_eligible if self.buildings_eligible else float("nan")

    def line(self) -> str:
        return (f"façade precision {self.facade_precision:.3f} recall {self.facade_recall:.3f} "
                f"(walls only {self.wall_recall:.3f}); "
                f"buildings covered {self.buildings_covered}/{self.buildings_eligible} ({self.coverage:.3f}); "
                f"segments {self.segments} ({self.segments_pure} pure)")


def score_segments(seg: StreetSegments, truth_labels: np.ndarray, points: np.ndarray,
                   min_facade_m: float = 5.0, purity: float = 0.95,
                   walls: np.ndarray | None = None) -> StreetScore:
    """``points``: the input street cloud (N,3), to measure building extents in the levelled frame;
    ``walls``: optional (N,) bool, True where the true surface is steep (see ``steep_truth``)."""
    truth = np.asarray(truth_labels).astype(np.int64)
    pred = np.asarray(seg.point_labels).astype(np.int64)
    if truth.shape != pred.shape:
        raise ValueError(f"truth labels {truth.shape} and point labels {pred.shape} differ")
    on_building, in_segment = truth >= 0, pred >= 0
    precision = float(on_building[in_segment].mean()) if in_segment.any() else float("nan")
    recall = float(in_segment[on_building].mean()) if on_building.any() else float("nan")

    b_ids, b_inv = np.unique(truth[on_building], return_inverse=True)
    xy = seg.level(np.asarray(points)[on_building])[:, :2]
    extent = diameters(xy, b_inv.astype(np.int64), len(b_ids))
    eligible = extent >= min_facade_m

    covered = np.zeros(len(b_ids), dtype=bool)
    n_pure = 0
    if in_segment.any():
        s = pred[in_segment]
        t = truth[in_segment]
        size = np.bincount(s, minlength=len(seg))
        pairs, counts = np.unique(np.stack([s, t], axis=1), axis=0, return_counts=True)
        best = np.zeros(len(seg), dtype=np.int64)
        best_t = np.full(len(seg), -9, dtype=np.int64)
        order = np.lexsort((-counts, pairs[:, 0]))
        first = order[np.unique(pairs[order, 0], return_index=True)[1]]
        best[pairs[first, 0]] = counts[first]
        best_t[pairs[first, 0]] = pairs[first, 1]
        pure = (size > 0) & (best >= purity * np.maximum(size, 1)) & (best_t >= 0)
        n_pure = int(pure.sum())
        pos = np.searchsorted(b_ids, best_t[pure])
        covered[pos[(pos < len(b_ids))]] = True
    wall_recall = float("nan")
    if walls is not None and (on_building & walls).any():
        wall_recall = float(in_segment[on_building & walls].mean())
    return StreetScore(precision, recall, int(eligible.sum()), int((covered & eligible).sum()),
                       len(seg), n_pure, wall_recall)


def steep_truth(truth_points: np.ndarray, lidar_points: np.ndarray, angle_deg: float = 60.0,
                knn: int = 12) -> np.ndarray:
    """(N,) bool: the noise-free reference surface (truth/lidar.ply) nearest to each true street
    point has a normal more than ``angle_deg`` from vertical (walls, not roofs or ground)."""
    from toolkit.open3d_import import open3d
    o3d = open3d()
    from scipy.spatial import cKDTree

    origin = np.median(lidar_points, axis=0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(lidar_points) - origin))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn))
    steep = np.abs(np.asarray(pcd.normals)[:, 2]) < np.cos(np.radians(angle_deg))
    _, idx = cKDTree(np.asarray(pcd.points)).query(np.asarray(truth_points) - origin, k=1, workers=thread_budget())
    return steep[idx]


def true_up(points: np.ndarray, truth_points: np.ndarray, sample: int = 200_000, seed: int = 0) -> np.ndarray:
    """(3,) the scene's +z expressed in the input street frame (rigid least-squares fit, trimmed)."""
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(points), min(sample, len(points)), replace=False)
    a = np.asarray(points)[pick]
    b = np.asarray(truth_points)[pick]
    keep = np.ones(len(a), dtype=bool)
    for _ in range(3):
        r, t = _kabsch(a[keep], b[keep])
        res = np.linalg.norm(a @ r.T + t - b, axis=1)
        keep = res <= np.quantile(res, 0.9)
    return r.T @ np.array([0.0, 0.0, 1.0])


def _kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return r, cb - r @ ca


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle between two directions (signed: a flipped up is 180°)."""
    c = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v)))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def found_up(seg: StreetSegments) -> np.ndarray:
    """(3,) the up direction the stage found, in the input frame."""
    return seg.up_rotation.T @ np.array([0.0, 0.0, 1.0])
