"""warp.inverse_log (paper Eq. 6) and warp.nearest: weights, rotation averaging, points and cameras."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from plugins.warp_inverse_log import InverseLog
from plugins.warp_nearest import Nearest
from tests.refine_warp_world import world, write_scene
from toolkit.capture import StreetCapture
from toolkit.errors import StageError
from toolkit.io.cloud import write_ply
from toolkit.io.colmap import write_model
from toolkit.observe import NullObserver
from toolkit.refine.transforms import apply
from toolkit.scene import load_scene, write_manifest
from toolkit.types import Camera, SegmentTransforms, SparseModel, StreetSegments
from toolkit.warp.blend import average_rotations, inverse_log_weights


def test_inverse_log_weights_handle_distances_at_and_below_one_metre():
    d = np.array([0.0, 0.3, 1.0, 1.2, 1.5, 3.0, 30.0, 300.0])
    w = inverse_log_weights(d, 1.5)
    assert np.all(np.isfinite(w)) and np.all(w > 0)
    assert np.all(np.diff(w) <= 0)                         # never more weight farther away
    assert np.allclose(w[:5], 1 / np.log(1.5))             # clamped
    assert np.isclose(w[6], 1 / np.log(30.0))
    with pytest.raises(ValueError):
        inverse_log_weights(d, 1.0)
    with pytest.raises(ValidationError):
        InverseLog.from_config({"min_distance_m": 1.0})


def test_rotation_average_is_a_rotation_between_the_inputs():
    a, b = np.radians(10.0), np.radians(30.0)
    R = np.stack([Rotation.from_euler("z", a).as_matrix(), Rotation.from_euler("z", b).as_matrix()])[None]
    mean = average_rotations(R, np.array([[1.0, 1.0]]))[0]
    assert np.isclose(Rotation.from_matrix(mean).as_euler("zyx")[0], np.radians(20.0))
    assert np.isclose(np.linalg.det(mean), 1.0) and np.allclose(mean @ mean.T, np.eye(3))
    biased = average_rotations(R, np.array([[3.0, 1.0]]))[0]
    assert np.radians(10) < Rotation.from_matrix(biased).as_euler("zyx")[0] < np.radians(20)
    # a matrix average of distant rotations is not a rotation; the quaternion mean is
    far = np.stack([np.eye(3), Rotation.from_euler("x", 170, degrees=True).as_matrix()])[None]
    m = average_rotations(far, np.array([[1.0, 1.0]]))[0]
    assert np.allclose(m @ m.T, np.eye(3)) and np.isclose(np.linalg.det(m), 1.0)


def _cameras(street: StreetSegments, n=12):
    """A few cameras along the road (levelled y = 50 - 5 in local terms is street middle)."""
    lev_c = np.column_stack([np.linspace(10, 170, n), np.full(n, 48.0), np.full(n, 101.5)])
    # the world() levelled frame is the scene rotated by each segment's B^-1; any frame will do for cameras
    C = lev_c @ street.up_rotation + street.origin
    rng = np.random.default_rng(3)
    R = Rotation.from_rotvec(rng.normal(0, 0.3, (n, 3))).as_matrix()
    t = -np.einsum("cab,cb->ca", R, C)
    cam = Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500, 320, 240]))
    return SparseModel(cameras={1: cam}, image_names=tuple(f"c{i}.jpg" for i in range(n)),
                       image_ids=np.arange(1, n + 1), camera_ids=np.ones(n, int), R=R, t=t,
                       points3d_ids=np.zeros(0, int), points3d=np.zeros((0, 3)),
                       points3d_rgb=np.zeros((0, 3), np.uint8), observations=np.zeros((0, 4)))


@pytest.fixture(scope="module")
def scene_with_cameras(tmp_path_factory):
    w = world()
    model = _cameras(w["street"])
    scene = write_scene(w, tmp_path_factory.mktemp("warp") / "scene", with_sparse=model)
    return w, scene, model


def _transforms(T, valid=None):
    S = len(T)
    return SegmentTransforms(T=T, valid=np.ones(S, bool) if valid is None else valid, cost=np.zeros(S),
                             confidence=np.ones(S))


@pytest.mark.parametrize("stage", [InverseLog(), Nearest()], ids=["inverse_log", "nearest"])
def test_identical_segment_transforms_give_that_transform(scene_with_cameras, stage):
    w, scene, model = scene_with_cameras
    T = w["T_true"][1]
    reg = stage(_transforms(np.repeat(T[None], 4, axis=0)), w["street"], scene, StreetCapture(scene), NullObserver())
    assert reg.points.shape == w["inp"].shape and reg.points.dtype == np.float64
    assert np.abs(reg.points - apply(T, w["inp"])).max() < 1e-6
    assert reg.image_names == model.image_names
    centres = -np.einsum("cba,cb->ca", reg.R, reg.t)
    assert np.abs(centres - apply(T, model.centres)).max() < 1e-6
    assert np.allclose(reg.R, np.einsum("cab,db->cad", model.R, T[:3, :3]), atol=1e-9)


def test_nearest_uses_each_points_own_segment(scene_with_cameras):
    w, scene, _ = scene_with_cameras
    reg = Nearest()(_transforms(w["T_true"]), w["street"], scene, StreetCapture(scene), NullObserver())
    carried = w["carrier"] >= 0
    assert np.abs(reg.points[carried] - w["truth"][carried]).max() < 1e-6
    assert np.array_equal(reg.point_segment[carried], w["carrier"][carried])


def test_points_of_invalid_or_missing_segments_are_still_carried(scene_with_cameras):
    w, scene, _ = scene_with_cameras
    valid = np.array([True, True, False, True])
    for stage in (InverseLog(), Nearest()):
        reg = stage(_transforms(w["T_true"], valid), w["street"], scene, StreetCapture(scene), NullObserver())
        assert np.isfinite(reg.points).all() and len(reg.points) == len(w["inp"])
        assert set(np.unique(reg.point_segment)) <= {0, 1, 3}
        orphan = (w["carrier"] == 2) | (w["carrier"] < 0)
        err = np.linalg.norm(reg.points[orphan] - w["truth"][orphan], axis=1)
        assert err.max() < 10.0                       # moved by the neighbours, into the scene CRS
        far_from_input = np.linalg.norm(reg.points[orphan] - w["inp"][orphan], axis=1)
        assert far_from_input.min() > 1000.0


def test_cameras_blend_over_their_own_neighbour_count(scene_with_cameras):
    w, scene, _ = scene_with_cameras
    T = _transforms(w["T_true"])
    both = InverseLog.from_config({"neighbours_k": 3})(T, w["street"], scene, StreetCapture(scene), NullObserver())
    own = InverseLog.from_config({"neighbours_k": 3, "camera_neighbours_k": 0})(T, w["street"], scene, StreetCapture(scene), NullObserver())
    near = Nearest()(T, w["street"], scene, StreetCapture(scene), NullObserver())
    assert np.array_equal(own.points, both.points)          # the points' blend is untouched
    assert np.allclose(own.R, near.R, atol=1e-12) and np.allclose(own.t, near.t, atol=1e-9)
    assert np.abs(both.t - near.t).max() > 1e-3               # the cameras did blend with K = 3
    same = InverseLog.from_config({"neighbours_k": 3, "camera_neighbours_k": 3})(T, w["street"], scene, StreetCapture(scene), NullObserver())
    assert np.array_equal(same.t, both.t) and np.array_equal(same.R, both.R)


def test_no_valid_segment_is_a_one_line_stage_error(scene_with_cameras):
    w, scene, _ = scene_with_cameras
    with pytest.raises(StageError, match="no valid segment"):
        InverseLog()(_transforms(w["T_true"], np.zeros(4, bool)), w["street"], scene, StreetCapture(scene), NullObserver())


# --- blending matters at segment borders under a smooth drift ---------------------------------------
def _drifting_street(tmp_path, n_seg=7, seg_len=24.0, gap=10.0, heading_deg_per_100m=0.5, seed=0):
    """Façade segments along a straight road whose street-frame copy drifts smoothly (heading).

    Per-segment transforms are the rigid fits of each segment's points (façade and the ground it
    carries), so they are exact but for the drift's curvature.
    """
    rng = np.random.default_rng(seed)
    pitch = seg_len + gap
    L = n_seg * pitch
    fac_x = np.concatenate([rng.uniform(i * pitch, i * pitch + seg_len, 1500) for i in range(n_seg)])
    fac = np.column_stack([fac_x, np.full(len(fac_x), 8.0), rng.uniform(0, 10, len(fac_x))])
    gnd = np.column_stack([rng.uniform(0, L, 20000), rng.uniform(-6, 7, 20000), np.zeros(20000)])
    truth = np.vstack([fac, gnd])
    labels = np.concatenate([np.floor(fac_x / pitch).astype(np.int32), np.full(len(gnd), -1, np.int32)])

    def drift(p):     # heading error grows linearly along x: the street frame bends smoothly
        k = np.radians(heading_deg_per_100m) / 100.0
        th = k * p[:, 0]
        x = np.where(np.abs(th) > 1e-12, np.sin(th) / k, p[:, 0])
        y0 = np.where(np.abs(th) > 1e-12, (1 - np.cos(th)) / k, 0.0)
        return np.column_stack([x - p[:, 1] * np.sin(th), y0 + p[:, 1] * np.cos(th), p[:, 2]])

    street_pts = drift(truth)
    seg_centre = np.array([(i * pitch + seg_len / 2) for i in range(n_seg)])
    carrier = np.where(labels >= 0, labels, np.argmin(np.abs(truth[:, :1] - seg_centre[None]), axis=1)).astype(np.int32)
    T = np.zeros((n_seg, 4, 4))
    for i in range(n_seg):
        sel = carrier == i
        T[i] = _kabsch(street_pts[sel], truth[sel])
    street = StreetSegments(
        origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=carrier, ids=np.arange(n_seg),
        boundary_xy=tuple(street_pts[labels == i, :2] for i in range(n_seg)),
        centroids=np.array([street_pts[labels == i, :2].mean(0) for i in range(n_seg)]),
        extent_m=np.full(n_seg, seg_len), ground_z=np.zeros(n_seg), ground_normal=np.tile([0, 0, 1.0], (n_seg, 1)))
    root = tmp_path / "drift"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", street_pts)
    write_manifest(root, "drift", "EPSG:32617", {"street": {"cloud": "street/cloud.ply"}})
    border = np.abs(((truth[:, 0] - seg_len / 2) % pitch) - pitch / 2) < gap   # the stretch between segments
    return street, load_scene(root), T, truth, border & (labels < 0)


def _kabsch(src, dst):
    a, b = src.mean(0), dst.mean(0)
    U, _, Vt = np.linalg.svd((src - a).T @ (dst - b))
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, b - R @ a
    return T


def _with_refine_noise(T, street, truth, sigma_m, seed):
    """Each segment transform disturbed like a real refinement: ~sigma_m at the segment."""
    rng = np.random.default_rng(seed)
    out = T.copy()
    for i in range(len(T)):
        d = np.eye(4)
        d[:3, :3] = Rotation.from_rotvec(rng.normal(0, np.radians(0.3), 3) * [0.2, 0.2, 1]).as_matrix()
        c = truth[street.point_labels == i].mean(0)
        d[:3, 3] = c - d[:3, :3] @ c + rng.normal(0, sigma_m, 3) * [1, 1, 0.3]
        out[i] = d @ T[i]
    return out


# one-sided street, segments 34 m apart: the paper's K = 4 neighbours span ±70 m (the default
# K = 16 is tuned for campus-like density, both sides of every street)
SPARSE_STREET = {"neighbours_k": 4}


def test_blending_beats_nearest_at_segment_borders(tmp_path):
    """With realistically noisy segment transforms, Eq. 6 smooths the jumps between segments."""
    p95 = {"inverse_log": [], "nearest": []}
    for seed in range(3):
        street, scene, T, truth, border = _drifting_street(tmp_path / str(seed), seed=seed)
        Tn = _with_refine_noise(T, street, truth, 0.3, seed)
        for stage in (InverseLog.from_config(SPARSE_STREET), Nearest()):
            reg = stage(_transforms(Tn), street, scene, StreetCapture(scene), NullObserver())
            p95[stage.name].append(np.percentile(np.linalg.norm(reg.points - truth, axis=1)[border], 95))
    assert np.mean(p95["inverse_log"]) < 0.8 * np.mean(p95["nearest"]), p95


def test_with_exact_segment_transforms_blending_only_adds_the_drift_curvature(tmp_path):
    street, scene, T, truth, _ = _drifting_street(tmp_path)
    near = Nearest()(_transforms(T), street, scene, StreetCapture(scene), NullObserver())
    blend = InverseLog.from_config(SPARSE_STREET)(_transforms(T), street, scene, StreetCapture(scene), NullObserver())
    assert np.percentile(np.linalg.norm(near.points - truth, axis=1), 95) < 0.05
    assert np.percentile(np.linalg.norm(blend.points - truth, axis=1), 95) < 0.5


def test_a_camera_follows_the_segment_it_observes_not_the_nearest_one(tmp_path):
    """After a loop, drift can put another pass's segment nearest to a camera in the street frame."""
    rng = np.random.default_rng(4)
    a = np.column_stack([rng.uniform(0, 20, 400), np.full(400, 8.0), rng.uniform(0, 8, 400)])
    b = np.column_stack([rng.uniform(0, 20, 400), np.full(400, 6.0), rng.uniform(0, 8, 400)])
    pts = np.vstack([a, b])
    labels = np.repeat(np.arange(2, dtype=np.int32), 400)
    street = StreetSegments(
        origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=labels.copy(), ids=np.arange(2),
        boundary_xy=(a[:, :2], b[:, :2]), centroids=np.array([[10.0, 8.0], [10.0, 6.0]]), extent_m=np.full(2, 20.0),
        ground_z=np.zeros(2), ground_normal=np.tile([0, 0, 1.0], (2, 1)))
    T = np.repeat(np.eye(4)[None], 2, axis=0)
    T[1, :3, 3] = [0.0, 12.0, 0.0]                       # the other pass: 12 m away once registered
    C = np.array([[10.0, 9.5, 1.5]])                      # 1.5 m from segment a, 3.5 m from b
    seen = np.arange(400, 420)                            # it observes points of segment b
    model = SparseModel(
        cameras={1: Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500, 320, 240]))}, image_names=("c.jpg",),
        image_ids=np.array([1]), camera_ids=np.array([1]), R=np.eye(3)[None], t=-C,
        points3d_ids=np.arange(1, 21), points3d=pts[seen], points3d_rgb=np.zeros((20, 3), np.uint8),
        observations=np.column_stack([np.zeros(20), np.arange(20), rng.uniform(0, 400, (20, 2))]))
    root = tmp_path / "loop"
    (root / "street").mkdir(parents=True)
    write_ply(root / "street/cloud.ply", pts)
    write_model(model, root / "street/sparse")
    write_manifest(root, "loop", "EPSG:32617", {"street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"}})
    for stage in (InverseLog(), Nearest()):
        scene = load_scene(root)
        reg = stage(_transforms(T), street, scene, StreetCapture(scene), NullObserver())
        centre = -reg.R[0].T @ reg.t[0]
        assert np.allclose(centre, C[0] + [0.0, 12.0, 0.0], atol=1e-6), stage.key()
        assert np.abs(reg.points[:400] - a).max() < 1e-6      # the passes are not blended together


def test_neighbours_beyond_the_gap_limit_are_not_blended(tmp_path):
    street, scene, T, truth, _ = _drifting_street(tmp_path)
    far = InverseLog.from_config({"neighbours_k": 16})(_transforms(T), street, scene, StreetCapture(scene), NullObserver())
    near = InverseLog.from_config({"neighbours_k": 16, "max_neighbour_gap_m": 15.0})(
        _transforms(T), street, scene, StreetCapture(scene), NullObserver())
    err = {k: np.percentile(np.linalg.norm(r.points - truth, axis=1), 95) for k, r in (("all", far), ("15m", near))}
    assert err["15m"] < err["all"], err


def _exact_blend(points, xy, anchors, T, index, k, d_min):
    """Eq. 6 with per-point weights (the reference the cell approximation is checked against)."""
    out = np.empty_like(points)
    for n in range(len(points)):
        cand = index.candidates(int(anchors[n]), k)
        w = inverse_log_weights(index.distances(cand, xy[n:n + 1])[0], d_min)
        out[n] = sum(wj * apply(T[j], points[n:n + 1])[0] for wj, j in zip(w, cand)) / w.sum()
    return out


def test_cell_weights_approximate_per_point_weights_and_chunks_do_not_matter(tmp_path):
    from toolkit.scene import load_points
    from toolkit.warp.blend import SegmentIndex, blend_points

    street, scene, T, truth, _ = _drifting_street(tmp_path)
    Tn = _with_refine_noise(T, street, truth, 0.3, 0)
    tr = _transforms(Tn)
    pts = load_points(scene, "street_cloud")
    rng = np.random.default_rng(0)
    pick = rng.choice(len(pts), 400, replace=False)
    p, xy = pts[pick], street.level(pts[pick])[:, :2]
    index = SegmentIndex.build(street, tr, 4)
    anchors = index.anchors(xy, np.asarray(street.carrier)[pick], tr.valid)
    exact = _exact_blend(p, xy, anchors, Tn, index, 4, 1.5)
    fine = blend_points(p, xy, anchors, Tn, index, 4, 1.5, cell_m=0.05)
    coarse = blend_points(p, xy, anchors, Tn, index, 4, 1.5, cell_m=0.5)
    assert np.abs(fine - exact).max() < 0.005
    gap = np.linalg.norm(coarse - exact, axis=1)
    assert 0 < gap.max() < 0.1 and np.percentile(gap, 90) < 0.01, (gap.max(), np.percentile(gap, 90))
    assert np.array_equal(blend_points(p, xy, anchors, Tn, index, 4, 1.5, cell_m=0.5, chunk=37), coarse)
    nearest = blend_points(p, xy, anchors, Tn, index, 0, 1.5)
    own = np.einsum("nab,nb->na", Tn[anchors, :3, :3], p) + Tn[anchors, :3, 3]
    assert np.abs(nearest - own).max() < 1e-6


def test_cell_keys_group_points_by_anchor_then_cell_like_a_sort():
    from toolkit.warp.cells import cell_keys

    rng = np.random.default_rng(21)
    xy = rng.uniform(-40, 60, (20000, 2))
    anchors = rng.integers(0, 7, len(xy))
    rows, table = cell_keys(xy, anchors, 0.5)
    cell = np.floor(xy / 0.5).astype(np.int64)
    keys = np.column_stack([anchors, cell])
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    assert np.array_equal(rows, inv.ravel())
    assert np.array_equal(table[:, 0], uniq[:, 0]) and np.allclose(table[:, 1:], (uniq[:, 1:] + 0.5) * 0.5)


def test_relative_inverse_log_weights_measure_from_the_nearest_segment():
    d = np.array([[0.2, 5.0, 30.0], [40.0, 41.0, 120.0]])
    w = inverse_log_weights(d, 1.5, relative=True)
    assert np.allclose(w[0], inverse_log_weights(d[0] - 0.2, 1.5))      # on a footprint: (nearly) as before
    assert np.isclose(w[1, 0], 1 / np.log(1.5)) and np.isclose(w[1, 1], 1 / np.log(1.5))
    assert np.isclose(w[1, 2], 1 / np.log(80.0))
    # far from every footprint the nearest segments dominate; absolute distances weigh all alike
    wa = inverse_log_weights(d, 1.5)
    assert w[1, 2] / w[1].sum() < wa[1, 2] / wa[1].sum()

