"""adjust.constrained_ba — paper Eq. 7 on the street COLMAP model, in the scene CRS.

The model's 3D points are first moved with the warp (each by the pose change of the cameras
that observe it), then poses and points are re-adjusted: robust reprojection error plus
λ‖C_i − C_i^warped‖² holding every camera centre near its warped position; intrinsics fixed.
Solvers (``toolkit.adjust.ba``): pycolmap's Ceres adjuster with pose priors (default) or scipy
least_squares (the same result, ~8x slower).
As COLMAP does after a bundle adjustment, observations still reprojecting farther than
``max_reproj_error_px`` (or behind their camera: a point the robust loss let drift through a
camera) are then removed from the model and the adjustment is run again.
Then every street point is moved with the pose change of the camera that captured it
(``remake_points``, ``toolkit.adjust.remake``): the evaluation and the outputs see those points.
Reprojection RMS is over all image coordinates (u, v pooled), like a per-axis pixel noise σ; before
over every observation of the warped model, after over the observations the adjusted model keeps.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Literal

import numpy as np
from pydantic import Field

from toolkit.adjust.ba import (
    BAParams,
    adjust_ceres,
    adjust_scipy,
    degenerate_centres,
    prior_variances,
    straight_track,
)
from toolkit.adjust.fixes import camera_fixes, fuse_fixes
from toolkit.adjust.model import (
    bad_observations,
    place_unadjusted,
    point_errors_px,
    registered_poses,
    registered_spread,
    residuals,
    rms_px,
    warp_points3d,
)
from toolkit.adjust.remake import remake_registration
from toolkit.capture import StreetCapture
from toolkit.forked import forks, run_forked
from toolkit.io.colmap import replace_poses
from toolkit.stage import Stage, StageParams
from toolkit.threads import single_threaded_blas
from toolkit.types import AdjustedCameras, Registration, Scene


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
        trust_region: Literal["auto", "dogleg", "levenberg_marquardt"] = Field(
            "auto", description="Ceres trust-region strategy (auto: dogleg, levenberg_marquardt on a straight track).")
        straight_track_ratio: float = Field(
            0.05, ge=0, description="Below this ratio of the camera centres' second to first singular value the "
                                    "track counts as straight (trust_region auto)")
        threads: int = Field(
            1, ge=-1, description="Ceres threads (-1 = all cores; more than one is not bit-reproducible)")
        max_reproj_error_px: float | None = Field(
            4.0, gt=0, description="Drop observations reprojecting farther than this after a "
                                   "first solve, then re-solve (px; None: keep all)")

        prior_spread: bool = Field(
            True, description="Camera position prior variance 1/λ + (warp spread at the "
                              "camera)² (m²) instead of the paper's 1/λ alone")
        remake_points: bool = Field(
            True, description="Move every street point with the adjusted pose change of the camera that "
                              "captured it (off: the warp's points stand)")
        gps_prior: bool = Field(
            False, description="With street/gps.csv: each fix joins its camera's position prior (x, y, weighted by "
                              "the fix's σ and the prior's variance)")
        capture_sparse_gap_m: float = Field(
            10.0, gt=0, description="Only a sparse point within this distance names a street point's "
                                    "capture camera, else the nearest camera centre (m)")

    @classmethod
    def scene_needs(cls, params) -> tuple[str, ...]:
        return ("sparse",)

    def remakes(self) -> tuple[str, ...]:
        return ("registration",) if self.params.remake_points else ()

    def holds_gil(self) -> bool:
        return self.params.backend == "ceres" and not self._isolated()

    def _isolated(self) -> bool:
        # pycolmap keeps the GIL through the whole Ceres solve (a Python thread beside it got 351
        # loop iterations in 2.2 s instead of ~150 000): in a child process it leaves this one
        # free (toolkit.forked); with more Ceres threads it uses the cores itself
        return self.params.threads == 1 and forks()

    def _trust_region(self, C_prior: np.ndarray) -> str:
        # on a straight track position priors leave the roll about it unobserved: dogleg's long steps
        # drift along it (degrees), Levenberg-Marquardt's damped ones stay near the warp's roll
        if self.params.trust_region != "auto":
            return self.params.trust_region
        return "levenberg_marquardt" if straight_track(C_prior, self.params.straight_track_ratio) else "dogleg"

    def __call__(self, registration: Registration, scene: Scene, capture: StreetCapture, obs) -> AdjustedCameras:
        with single_threaded_blas():
            return self._run(registration, capture, obs)

    def _run(self, registration: Registration, capture: StreetCapture, obs) -> AdjustedCameras:
        p = self.params
        model = capture.require_sparse("adjust")
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
                      function_tolerance=p.function_tolerance, threads=p.threads,
                      trust_region=self._trust_region(C_prior))
        backend = p.backend
        if backend == "ceres" and degenerate_centres(C_prior):
            obs.warn("camera centres are exactly collinear/coplanar (pycolmap's prior alignment would "
                     "drop the priors): using the scipy solver")
            backend = "scipy"
        solve = adjust_scipy if backend == "scipy" else \
            partial(run_forked, adjust_ceres) if self._isolated() else adjust_ceres
        spread = registered_spread(model, registration) if p.prior_spread else None
        extra_var = None if spread is None else spread ** 2
        fixes = camera_fixes(capture, model) if p.gps_prior else None
        if fixes is not None:
            C_prior, var = fuse_fixes(C_prior, prior_variances(len(C_prior), bp, extra_var), fixes)
            extra_var = var - 1.0 / bp.lambda_
        res = solve(model, R_w, t_w, X_w, C_prior, bp, extra_var)
        iterations = res.iterations
        X = place_unadjusted(model, res)
        if p.max_reproj_error_px is not None:
            bad = bad_observations(model, res.R, res.t, X, p.max_reproj_error_px)
            removed = int(bad.sum())
            if bad.any():
                # again from the warped state: the pose-prior adjuster first snaps the model onto the
                # priors with a RANSAC Sim3, and from a shifted start it settles elsewhere in the
                # flat valleys of a forward-moving camera (measured: points 0.7 m off instead of 0.08)
                model = dataclasses.replace(model, observations=model.observations[~bad])
                X_w = warp_points3d(model, R_w, t_w)
                res = solve(model, R_w, t_w, X_w, C_prior, bp, extra_var)
                iterations += res.iterations
                X = place_unadjusted(model, res)
                # what the second adjustment still cannot fit is dropped, not adjusted a third time
                bad = bad_observations(model, res.R, res.t, X, p.max_reproj_error_px)
                if bad.any():
                    removed += int(bad.sum())
                    model = dataclasses.replace(model, observations=model.observations[~bad])
                    X = place_unadjusted(model, dataclasses.replace(res, X=X))
                obs.warn(f"removed {removed} of {len(model.observations) + removed} observations reprojecting "
                         f"farther than {p.max_reproj_error_px:g} px or behind their camera (adjusted again)")
        residual_px = residuals(model, res.R, res.t, X)
        adjusted = replace_poses(model, res.R, res.t, X, point_errors_px(model, residual_px))
        # every observation names capture cameras, also those the adjustment dropped
        remade = remake_registration(registration, capture.points, capture.require_sparse("adjust"), res.R, res.t,
                                     p.capture_sparse_gap_m) if self.remakes() and capture.cloud_path else None
        return AdjustedCameras(adjusted, before, rms_px(residual_px), iterations, remade)

