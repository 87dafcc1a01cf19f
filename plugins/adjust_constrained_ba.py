"""adjust.constrained_ba — paper Eq. 7 on the street COLMAP model, in the scene CRS.

The model's 3D points are first moved with the warp (each by the pose change of the cameras
that observe it), then poses and points are re-adjusted: robust reprojection error plus
λ‖C_i − C_i^warped‖² holding every camera centre near its warped position; intrinsics fixed.
Solvers (``toolkit.adjust.ba``): pycolmap's Ceres adjuster with pose priors (default) or scipy
least_squares. Measured on campus seed 0 (1456 images, 30 k points, 179 k observations): Ceres
5.8 s, scipy 44.5 s, same result (RMS 0.428 px, median camera-centre error 0.49 m).
As COLMAP does after a bundle adjustment, observations still reprojecting farther than
``max_reproj_error_px`` (or behind their camera: a point the robust loss let drift through a
camera) are then removed from the model and the adjustment is run again.
Reprojection RMS is over all image coordinates (u, v pooled), like a per-axis pixel noise σ; before
over every observation of the warped model, after over the observations the adjusted model keeps.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Literal

import numpy as np
from pydantic import Field

from toolkit.adjust.ba import BAParams, adjust_ceres, adjust_scipy, degenerate_centres
from toolkit.adjust.model import (
    point_errors_px,
    registered_poses,
    registered_spread,
    residuals,
    rms_px,
    warp_points3d,
)
from toolkit.capture import StreetCapture
from toolkit.forked import forks, run_forked
from toolkit.io.colmap import replace_poses
from toolkit.refine.blas import single_threaded_blas
from toolkit.stage import Stage, StageParams
from toolkit.types import AdjustedCameras, Registration, Scene, SparseModel


class ConstrainedBA(Stage):
    """Paper Eq. 7: bundle adjustment with λ‖Δt‖² holding camera centres near their warped positions."""

    kind = "adjust"
    name = "constrained_ba"

    class Params(StageParams):
        lambda_: float = Field(20.0, gt=0, description="Weight λ of the camera-position term (px² per m²; paper: 20).")
        loss: Literal["huber", "cauchy", "soft_l1", "trivial"] = Field(
            "huber", description="Robust loss on the reprojection residuals (trivial = plain least squares).")
        loss_scale_px: float = Field(1.0, gt=0, description="Scale of the robust loss (pixels).")
        backend: Literal["ceres", "scipy"] = Field(
            "ceres", description="ceres: pycolmap's Ceres bundle adjuster with pose priors; scipy: least_squares.")
        max_iterations: int = Field(100, ge=1, description="Solver iteration cap (scipy: function evaluations).")
        function_tolerance: float = Field(1e-6, gt=0, description="Relative cost decrease that stops the solver (pycolmap's default of 0 would run to the cap).")
        threads: int = Field(
            1, ge=-1, description="Ceres threads (-1 = all cores; more than one is not bit-reproducible)")
        max_reproj_error_px: float | None = Field(
            4.0, gt=0, description="Drop observations reprojecting farther than this after a "
                                   "first solve, then re-solve (px; None: keep all)")

        prior_spread: bool = Field(
            True, description="Camera position prior variance 1/λ + (warp spread at the "
                              "camera)² (m²) instead of the paper's 1/λ alone")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("sparse",)

    def holds_gil(self) -> bool:
        return self.params.backend == "ceres" and not self._isolated()

    def _isolated(self) -> bool:
        # pycolmap keeps the GIL through the whole Ceres solve (a Python thread beside it got 351
        # loop iterations in 2.2 s instead of ~150 000): in a child process it leaves this one
        # free (toolkit.forked); with more Ceres threads it uses the cores itself
        return self.params.threads == 1 and forks()

    def __call__(self, registration: Registration, scene: Scene, capture: StreetCapture, obs) -> AdjustedCameras:
        with single_threaded_blas():
            return self._run(registration, capture.require_sparse("adjust"), obs)

    def _run(self, registration: Registration, model: SparseModel, obs) -> AdjustedCameras:
        p = self.params
        R_w, t_w = registered_poses(model, registration)
        X_w = warp_points3d(model, R_w, t_w)
        warped_px = residuals(model, R_w, t_w, X_w)
        before = rms_px(warped_px)
        if len(model.observations) == 0 or len(model.image_names) == 0:
            obs.warn("the COLMAP model has no observations: poses left as warped")
            return AdjustedCameras(replace_poses(model, R_w, t_w, X_w, point_errors_px(model, warped_px)),
                                   before, before, 0)
        C_prior = -np.einsum("cba,cb->ca", R_w, t_w)
        bp = BAParams(lambda_=p.lambda_, loss=p.loss, loss_scale_px=p.loss_scale_px, max_iterations=p.max_iterations,
                      function_tolerance=p.function_tolerance, threads=p.threads)
        backend = p.backend
        if backend == "ceres" and degenerate_centres(C_prior):
            obs.warn("camera centres are exactly collinear/coplanar (pycolmap's prior alignment would "
                     "drop the priors): using the scipy solver")
            backend = "scipy"
        solve = adjust_scipy if backend == "scipy" else \
            partial(run_forked, adjust_ceres) if self._isolated() else adjust_ceres

        spread = registered_spread(model, registration) if p.prior_spread else None
        extra_var = None if spread is None else spread ** 2
        res = solve(model, R_w, t_w, X_w, C_prior, bp, extra_var)
        iterations = res.iterations
        X = _place_unadjusted(model, res)
        if p.max_reproj_error_px is not None:
            bad = _bad_observations(model, res.R, res.t, X, p.max_reproj_error_px)
            removed = int(bad.sum())
            if bad.any():
                # again from the warped state: the pose-prior adjuster first snaps the model onto the
                # priors with a RANSAC Sim3, and from a shifted start it settles elsewhere in the
                # flat valleys of a forward-moving camera (measured: points 0.7 m off instead of 0.08)
                model = dataclasses.replace(model, observations=model.observations[~bad])
                X_w = warp_points3d(model, R_w, t_w)
                res = solve(model, R_w, t_w, X_w, C_prior, bp, extra_var)
                iterations += res.iterations
                X = _place_unadjusted(model, res)
                # what the second adjustment still cannot fit is dropped, not adjusted a third time
                bad = _bad_observations(model, res.R, res.t, X, p.max_reproj_error_px)
                if bad.any():
                    removed += int(bad.sum())
                    model = dataclasses.replace(model, observations=model.observations[~bad])
                    X = _place_unadjusted(model, dataclasses.replace(res, X=X))
                obs.warn(f"removed {removed} of {len(model.observations) + removed} observations reprojecting "
                         f"farther than {p.max_reproj_error_px:g} px or behind their camera (adjusted again)")
        residual_px = residuals(model, res.R, res.t, X)
        adjusted = replace_poses(model, res.R, res.t, X, point_errors_px(model, residual_px))
        return AdjustedCameras(adjusted, before, rms_px(residual_px), iterations)


def _place_unadjusted(model, res) -> np.ndarray:
    """Points seen by fewer than two cameras are not adjusted: put them where their camera sees them."""
    X = res.X.copy()
    single = np.bincount(model.observations[:, 1].astype(np.int64), minlength=len(X)) < 2
    if single.any():
        X[single] = warp_points3d(model, res.R, res.t)[single]
    return X


def _bad_observations(model, R, t, X, max_px: float) -> np.ndarray:
    ob = model.observations
    img, pt = ob[:, 0].astype(np.int64), ob[:, 1].astype(np.int64)
    depth = np.einsum("kb,kb->k", R[img, 2], X[pt]) + t[img, 2]
    return (np.linalg.norm(residuals(model, R, t, X), axis=1) > max_px) | (depth <= 0)
