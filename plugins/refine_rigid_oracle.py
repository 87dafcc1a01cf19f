"""refine.rigid_oracle — the best single rigid transform given the truth: the ceiling of any rigid method.

A baseline, not a method: it reads ``truth/street_points.npy`` (the one documented exception to
"truth is read only by evaluate.*") and fits one rotation + translation (no scale, Kabsch) taking
the whole street cloud onto its true positions. Comparing it with the piecewise-rigid pipeline
shows what non-rigid (drift) handling buys. It ignores the matches.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pydantic import Field

from toolkit.capture import StreetCapture
from toolkit.errors import SceneError, StageError
from toolkit.evaluation.metrics import apply_transform, rigid_fit, subsample
from toolkit.scene import load_array
from toolkit.stage import Stage, StageParams
from toolkit.types import ConjugateGraphs, Matches, OverviewSegments, Scene, SegmentTransforms, StreetSegments


class RigidOracle(Stage):
    """Best single rigid transform street → truth (baseline; reads truth/street_points.npy)."""

    kind = "refine"
    name = "rigid_oracle"

    class Params(StageParams):
        max_points: int = Field(2_000_000, ge=0, description="fit on at most this many points "
                                "(deterministic subsample; 0 = all)")
        seed: int = Field(0, description="seed of the subsample")

    @classmethod
    def scene_needs(cls, params: StageParams) -> tuple[str, ...]:
        return ("street_cloud", "truth_street_points")

    def __call__(self, matches: Matches, street: StreetSegments, overview: OverviewSegments, scene: Scene,
                 capture: StreetCapture, obs: Any, graphs: ConjugateGraphs | None = None) -> SegmentTransforms:
        pts = capture.points
        true = load_array(scene, "truth_street_points")
        if true.shape != pts.shape:
            raise SceneError(f"{scene.files.truth_street_points}: shape {true.shape} does not match the "
                             f"street cloud's {pts.shape}")
        if len(pts) < 3:
            raise StageError("refine.rigid_oracle: the street cloud has fewer than 3 points")
        idx = subsample(pts, self.params.max_points, self.params.seed)
        T = rigid_fit(pts[idx], true[idx])
        residual = np.linalg.norm(apply_transform(T, pts) - true, axis=1)
        obs.debug("residual_m", float(residual.mean()))
        return uniform_transforms(T, street, residual)


def uniform_transforms(T: np.ndarray, street: StreetSegments, point_cost: np.ndarray | None = None,
                       confidence: float = 1.0) -> SegmentTransforms:
    """The same transform for every street segment; cost = mean ``point_cost`` over its points."""
    S = len(street)
    cost = np.zeros(S)
    if point_cost is not None and S:
        labels = np.asarray(street.point_labels)
        sel = labels >= 0
        sums = np.bincount(labels[sel], weights=point_cost[sel], minlength=S)[:S]
        counts = np.bincount(labels[sel], minlength=S)[:S]
        cost = np.divide(sums, counts, out=np.full(S, float(np.mean(point_cost))), where=counts > 0)
    return SegmentTransforms(T=np.repeat(np.asarray(T, np.float64)[None], S, axis=0), valid=np.ones(S, bool),
                             cost=cost, confidence=np.full(S, float(confidence)))
