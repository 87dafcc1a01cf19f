"""FPFH + RANSAC global registration, then ICP (Open3D), of one whole cloud onto another: refine.global_fpfh.

Both clouds are centred locally, voxel-averaged, given normals and FPFH features; mutual nearest
neighbours in feature space are the correspondences of several seeded RANSAC runs, each refined by
point-to-plane ICP; the run with the best fitness (then the lower inlier RMSE) is kept.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from toolkit.errors import StageError


def voxel_down(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Centroid of the points in each occupied voxel (numpy: faster than Open3D, order stable)."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(counts), 3))
    for d in range(3):
        sums[:, d] = np.bincount(inverse, weights=points[:, d], minlength=len(counts))
    return sums / counts[:, None]


def mutual_feature_matches(a: np.ndarray, b: np.ndarray, chunk: int = 256) -> np.ndarray:
    """(K,2) index pairs (i, j) where a[i] and b[j] are each other's nearest neighbour (Euclidean).

    Blocked float32 distance matrices: BLAS-fast in 33-D, where KD-trees degrade to brute force.
    """
    # Zero-padding the 33 FPFH bins to 64 changes no distance and runs OpenBLAS's sgemm faster.
    width = max(64, a.shape[1])
    a32 = np.zeros((len(a), width), np.float32)
    b32 = np.zeros((len(b), width), np.float32)
    a32[:, :a.shape[1]] = a
    b32[:, :b.shape[1]] = b
    bb = (b32 * b32).sum(axis=1)
    ab = np.empty(len(a32), np.int64)
    best_b = np.full(len(b32), np.inf, np.float32)
    arg_b = np.zeros(len(b32), np.int64)
    for i0 in range(0, len(a32), chunk):
        blk = a32[i0:i0 + chunk]
        d = bb[None, :] - 2.0 * (blk @ b32.T)  # + |a|², constant per row: irrelevant to both argmins
        d += (blk * blk).sum(axis=1)[:, None]
        ab[i0:i0 + len(blk)] = d.argmin(axis=1)
        col = d.argmin(axis=0)
        cmin = d[col, np.arange(len(b32))]
        better = cmin < best_b
        best_b[better] = cmin[better]
        arg_b[better] = col[better] + i0
    i = np.nonzero(arg_b[ab] == np.arange(len(a32)))[0]
    return np.column_stack([i, ab[i]])


def register_fpfh(src: np.ndarray, dst: np.ndarray, p: Any) -> tuple[np.ndarray, float, float]:
    """(4,4) src → dst, RANSAC+ICP fitness, inlier RMSE. Both clouds are centred locally first.

    ``p``: the refine.global_fpfh Params (voxel, radii, key points, RANSAC, ICP and seed settings)."""
    src_origin, dst_origin = src.mean(axis=0), dst.mean(axis=0)
    s_pcd, s_feat = fpfh_cloud(src, src_origin, p)
    d_pcd, d_feat = fpfh_cloud(dst, dst_origin, p)
    pairs = feature_pairs(s_feat, d_feat, p.max_keypoints)
    T_local, fitness, rmse = best_registration(s_pcd, d_pcd, pairs, p)
    # x_dst = T_local (x_src − src_origin) + dst_origin
    T = np.eye(4)
    T[:3, :3] = T_local[:3, :3]
    T[:3, 3] = T_local[:3, 3] + dst_origin - T_local[:3, :3] @ src_origin
    return T, fitness, rmse


def fpfh_cloud(pts: np.ndarray, origin: np.ndarray, p: Any):
    """Open3D cloud of the voxel-averaged points about ``origin``, with normals, and its FPFH features."""
    from toolkit.open3d_import import open3d
    o3d = open3d()

    down = voxel_down(np.asarray(pts, np.float64) - origin, p.voxel_m)
    if len(down) < 10:
        raise StageError(f"refine.global_fpfh: only {len(down)} voxels of {p.voxel_m} m; lower voxel_m")
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(down))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=p.normal_radius_m, max_nn=30))
    feat = o3d.pipelines.registration.compute_fpfh_feature(pcd, o3d.geometry.KDTreeSearchParamHybrid(
        radius=p.feature_radius_m, max_nn=100))
    return pcd, feat


def feature_pairs(s_feat, d_feat, max_keypoints: int) -> np.ndarray:
    """(K,2) source/target point indices of mutual nearest neighbours in feature space, from at most
    ``max_keypoints`` evenly spread source points."""
    # Computed once for all restarts (Open3D's own mutual filter redoes a 33-D KD-tree search per
    # call and is ~50× slower here).
    s_data = np.asarray(s_feat.data).T
    keys = np.linspace(0, len(s_data) - 1, min(max_keypoints, len(s_data))).astype(np.int64)
    pairs = mutual_feature_matches(s_data[keys], np.asarray(d_feat.data).T)
    pairs[:, 0] = keys[pairs[:, 0]]
    if len(pairs) < 3:
        raise StageError(f"refine.global_fpfh: only {len(pairs)} mutual FPFH correspondences")
    return pairs


def best_registration(s_pcd, d_pcd, pairs: np.ndarray, p: Any) -> tuple[np.ndarray, float, float]:
    """RANSAC on the correspondences (seeds seed, seed+1, …), each refined by point-to-plane ICP; the
    local transform, fitness and inlier RMSE of the best fitness (then lowest RMSE)."""
    from toolkit.open3d_import import open3d
    o3d = open3d()

    reg = o3d.pipelines.registration
    corr = o3d.utility.Vector2iVector(pairs.astype(np.int32))
    best = (np.eye(4), -1.0, np.inf)
    for k in range(p.ransac_restarts):
        o3d.utility.random.seed(p.seed + k)
        result = reg.registration_ransac_based_on_correspondence(
            s_pcd, d_pcd, corr, p.ransac_distance_m, reg.TransformationEstimationPointToPoint(False), 3,
            [reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
             reg.CorrespondenceCheckerBasedOnDistance(p.ransac_distance_m)],
            reg.RANSACConvergenceCriteria(p.ransac_iterations, p.ransac_confidence))
        T_k = np.asarray(result.transformation)
        fit_k, rmse_k = float(result.fitness), float(result.inlier_rmse)
        if p.icp_iterations > 0:
            icp = reg.registration_icp(s_pcd, d_pcd, p.icp_distance_m, T_k,
                                       reg.TransformationEstimationPointToPlane(),
                                       reg.ICPConvergenceCriteria(max_iteration=p.icp_iterations))
            T_k, fit_k, rmse_k = np.asarray(icp.transformation), float(icp.fitness), float(icp.inlier_rmse)
        if fit_k > best[1] or (fit_k == best[1] and rmse_k < best[2]):
            best = (T_k, fit_k, rmse_k)
    return best
