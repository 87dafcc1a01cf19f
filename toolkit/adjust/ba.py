"""Eq. 7: min Σ ρ(‖u_ij − f(X_j | R_i, t_i)‖²) + λ Σ ‖C_i − C_i^warped‖², intrinsics fixed.

Two solvers of the same problem:
- ``ceres``: pycolmap's Ceres bundle adjuster with pose priors (``create_pose_prior_bundle_adjuster``):
  a prior position with covariance I/λ adds exactly λ‖ΔC‖² (Ceres halves both terms alike).
  That adjuster first aligns the model to the priors with a RANSAC Sim3; the priors are the
  current centres, so the alignment is the identity, but it FAILS (and silently drops every prior)
  when the centres are exactly coplanar or collinear, so such input goes to ``scipy`` instead.
- ``scipy``: ``scipy.optimize.least_squares`` (trf, sparse finite-difference Jacobian), per-residual
  robust loss on the reprojections only and a plain quadratic prior.
Both work about a local origin (the mean warped centre): scene coordinates are large UTM numbers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.adjust.model import project
from toolkit.threads import single_threaded_blas
from toolkit.types import SparseModel


@dataclass(frozen=True)
class BAParams:
    lambda_: float = 20.0
    loss: str = "huber"
    loss_scale_px: float = 1.0
    max_iterations: int = 100
    function_tolerance: float = 1e-6
    threads: int = 1
    trust_region: str = "dogleg"


@dataclass(frozen=True)
class BAResult:
    R: np.ndarray
    t: np.ndarray
    X: np.ndarray
    iterations: int
    backend: str


def _spread(C: np.ndarray) -> np.ndarray:
    """Singular values of the centred camera centres, largest first (their spread along each axis)."""
    return np.linalg.svd(C - C.mean(axis=0), compute_uv=False)


def degenerate_centres(C: np.ndarray, rel: float = 1e-9) -> bool:
    """True when the centres are (numerically exactly) collinear or coplanar."""
    if len(C) < 3:
        return True
    s = _spread(C)
    return bool(s[-1] <= rel * max(s[0], 1e-12))


def straight_track(C: np.ndarray, ratio: float) -> bool:
    """True when the centres lie nearly on a line: second over first singular value below ``ratio``.
    Position priors then leave the rotation of the whole model about that line unobserved."""
    if len(C) < 2:
        return True
    s = _spread(C)
    return bool(s[1] < ratio * s[0])


def _tracks(model: SparseModel):
    """Observation order by image, index of each observation within its image, track lengths."""
    ob = model.observations
    img, pt = ob[:, 0].astype(np.int64), ob[:, 1].astype(np.int64)
    order = np.argsort(img, kind="stable")
    counts = np.bincount(img, minlength=len(model.image_names))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    pos = np.empty(len(ob), np.int64)
    pos[order] = np.arange(len(ob)) - starts[img[order]]
    track_len = np.bincount(pt, minlength=len(model.points3d))
    return img, pt, order, counts, starts, pos, track_len


def prior_variances(C: int, p: BAParams, extra_var_m2: np.ndarray | None) -> np.ndarray:
    """(C,3) variance (m², per axis) of each camera's prior position: 1/λ (the paper's λ‖ΔC‖²), plus
    ``extra_var_m2`` where given ((C,) or (C,3): e.g. the warp's uncertainty of that camera's position)."""
    var = np.full((C, 3), 1.0 / p.lambda_)
    if extra_var_m2 is not None:
        var += np.asarray(extra_var_m2, np.float64).reshape(C, -1)
    return var


def adjust_ceres(model: SparseModel, R0: np.ndarray, t0: np.ndarray, X0: np.ndarray, C_prior: np.ndarray,
                 p: BAParams, extra_var_m2: np.ndarray | None = None) -> BAResult:
    import pycolmap

    origin = C_prior.mean(axis=0)
    img, pt, order, counts, starts, pos, track_len = _tracks(model)
    rec = pycolmap.Reconstruction()
    for cid, cam in model.cameras.items():
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model=cam.model, width=int(cam.width), height=int(cam.height),
            params=np.asarray(cam.params, np.float64), camera_id=int(cid)))
    ob = model.observations
    for k, name in enumerate(model.image_names):
        kp = ob[order[starts[k]:starts[k] + counts[k]], 2:4]
        im = pycolmap.Image(name=name, keypoints=np.ascontiguousarray(kp), camera_id=int(model.camera_ids[k]),
                            image_id=int(model.image_ids[k]))
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R0[k]), t0[k] + R0[k] @ origin)
        rec.add_image_with_trivial_frame(im, pose)
    use = np.flatnonzero(track_len >= 2)
    by_pt = np.argsort(pt, kind="stable")
    bounds = np.searchsorted(pt[by_pt], np.arange(len(X0) + 1))
    iid = model.image_ids
    # plain Python ints, built once: pycolmap takes elements one by one
    elem_image, elem_idx = iid[img[by_pt]].tolist(), pos[by_pt].tolist()
    starts, ends, xyz = bounds[use].tolist(), bounds[use + 1].tolist(), X0[use] - origin
    element = pycolmap.TrackElement
    new_ids = np.array([
        rec.add_point3D(xyz[n], pycolmap.Track([element(a, b) for a, b in zip(elem_image[s:e], elem_idx[s:e])]))
        for n, (s, e) in enumerate(zip(starts, ends))], np.int64).reshape(-1)

    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    opts.refine_sensor_from_rig = False
    opts.print_summary = False
    # pycolmap switches to iterative Schur above 1000 images; sparse Schur stays 2× faster here
    # (campus, 1456 images: 22 s vs 48 s for the same 40 iterations)
    opts.ceres.max_num_images_direct_sparse_cpu_solver = 20000
    opts.ceres.loss_function_type = getattr(pycolmap.LossFunctionType, p.loss.upper())
    opts.ceres.loss_function_scale = p.loss_scale_px
    so = opts.ceres.solver_options
    so.function_tolerance = p.function_tolerance
    so.max_num_iterations = p.max_iterations
    so.num_threads = p.threads
    strategy = type(so.trust_region_strategy_type)  # pyceres' enum; pycolmap does not re-export it
    so.trust_region_strategy_type = getattr(strategy, p.trust_region.upper())
    cfg = pycolmap.BundleAdjustmentConfig()
    observed = np.flatnonzero(np.bincount(img[np.isin(pt, use)], minlength=len(model.image_names)) > 0)
    for k in observed:
        cfg.add_image(int(iid[k]))
    for cid in model.cameras:
        cfg.set_constant_cam_intrinsics(int(cid))
    priors = []
    var = prior_variances(len(C_prior), p, extra_var_m2)
    for k in observed:
        prior = pycolmap.PosePrior()
        prior.position = C_prior[k] - origin
        prior.position_covariance = np.diag(var[k])
        prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
        prior.corr_data_id = rec.images[int(iid[k])].data_id
        priors.append(prior)
    popts = pycolmap.PosePriorBundleAdjustmentOptions()
    popts.alignment_ransac.random_seed = 0
    summary = pycolmap.create_pose_prior_bundle_adjuster(opts, popts, cfg, priors, rec).solve()
    cs = summary.ceres_summary
    R, t, X = R0.copy(), t0.copy(), X0.copy()
    for k in observed:
        pose = rec.images[int(iid[k])].cam_from_world()
        R[k] = pose.rotation.matrix()
        t[k] = np.asarray(pose.translation) - R[k] @ origin
    X[use] = np.array([rec.points3D[int(i)].xyz for i in new_ids]).reshape(-1, 3) + origin
    return BAResult(R, t, X, int(cs.num_successful_steps + cs.num_unsuccessful_steps), "ceres")


def adjust_scipy(model: SparseModel, R0: np.ndarray, t0: np.ndarray, X0: np.ndarray, C_prior: np.ndarray,
                 p: BAParams, extra_var_m2: np.ndarray | None = None) -> BAResult:
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix
    from scipy.spatial.transform import Rotation

    origin = C_prior.mean(axis=0)
    img_all, pt_all, *_, track_len = _tracks(model)
    use_pts = np.flatnonzero(track_len >= 2)
    keep = np.isin(pt_all, use_pts)
    img = img_all[keep]
    col_of_pt = np.full(len(X0), -1)
    col_of_pt[use_pts] = np.arange(len(use_pts))
    pti = col_of_pt[pt_all[keep]]
    uv_obs = model.observations[keep, 2:4]
    C, P, K = len(R0), len(use_pts), len(img)
    C0 = -np.einsum("cba,cb->ca", R0, t0) - origin
    prior = C_prior - origin
    sq = 1.0 / np.sqrt(prior_variances(len(C_prior), p, extra_var_m2))
    cams = model.camera_ids[img]
    groups = [(model.cameras[int(c)], cams == c) for c in np.unique(cams)]

    def unpack(x):
        return (x[:3 * C].reshape(C, 3), x[3 * C:6 * C].reshape(C, 3), x[6 * C:].reshape(P, 3))

    def fun(x):
        rv, Cc, Xp = unpack(x)
        R = Rotation.from_rotvec(rv).as_matrix() @ R0
        xc = np.einsum("kab,kb->ka", R[img], Xp[pti] - Cc[img])
        uv = np.empty((K, 2))
        for cam, sel in groups:
            uv[sel] = project(cam, xc[sel])
        return np.concatenate([(uv - uv_obs).ravel(), (sq * (Cc - prior)).ravel()])

    rows_r = np.repeat(np.arange(2 * K), 9)
    cols_one = np.concatenate([3 * img[:, None] + np.arange(3), 3 * C + 3 * img[:, None] + np.arange(3),
                               6 * C + 3 * pti[:, None] + np.arange(3)], axis=1)        # (K, 9)
    cols_r = np.repeat(cols_one, 2, axis=0).ravel()
    rows_p = 2 * K + np.arange(3 * C)
    cols_p = 3 * C + np.arange(3 * C)
    sparsity = coo_matrix((np.ones(len(rows_r) + len(rows_p)),
                           (np.concatenate([rows_r, rows_p]), np.concatenate([cols_r, cols_p]))),
                          shape=(2 * K + 3 * C, 6 * C + 3 * P)).tocsr()
    n_rep = 2 * K

    def loss(z):
        # rho'' is reported as 0: scipy's full second-order correction zeroes the Jacobian rows of
        # every residual in the linear part of Huber (rho' + 2 rho'' z = 0), so a start with most
        # residuals above the loss scale never moves; with 0 the rows are scaled by sqrt(rho')
        # (iteratively reweighted least squares, what Ceres falls back to in that case).
        out = np.empty((3, len(z)))
        out[0], out[1], out[2] = z, 1.0, 0.0
        r = z[:n_rep]
        if p.loss == "huber":
            big = r > 1
            s = np.sqrt(np.where(big, r, 1))
            out[0, :n_rep] = np.where(big, 2 * s - 1, r)
            out[1, :n_rep] = np.where(big, 1 / s, 1)
        elif p.loss == "cauchy":
            out[0, :n_rep], out[1, :n_rep] = np.log1p(r), 1 / (1 + r)
        elif p.loss == "soft_l1":
            t = 1 + r
            out[0, :n_rep], out[1, :n_rep] = 2 * (t ** 0.5 - 1), t ** -0.5
        return out

    x0 = np.concatenate([np.zeros(3 * C), C0.ravel(), (X0[use_pts] - origin).ravel()])
    with single_threaded_blas():
        res = least_squares(fun, x0, jac_sparsity=sparsity, method="trf", tr_solver="lsmr", x_scale="jac",
                            loss="linear" if p.loss == "trivial" else loss, f_scale=p.loss_scale_px,
                            ftol=p.function_tolerance, xtol=1e-10, gtol=1e-10, max_nfev=p.max_iterations)
    rv, Cc, Xp = unpack(res.x)
    R = Rotation.from_rotvec(rv).as_matrix() @ R0
    Cw = Cc + origin
    t = -np.einsum("cab,cb->ca", R, Cw)
    X = X0.copy()
    X[use_pts] = Xp + origin
    return BAResult(R, t, X, int(res.nfev), "scipy")

