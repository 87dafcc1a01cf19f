"""adjust.constrained_ba (paper Eq. 7) and adjust.none on a small COLMAP model with known truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from plugins.adjust_constrained_ba import ConstrainedBA
from plugins.adjust_none import NoAdjust
from tests.refine_warp_world import ba_problem
from toolkit.capture import StreetCapture
from toolkit.adjust.ba import degenerate_centres, straight_track
from toolkit.adjust.model import project, residuals, rms_px, warp_points3d
from toolkit.io.colmap import read_model, write_model
from toolkit.observe import NullObserver
from toolkit.scene import load_scene, write_manifest
from toolkit.types import Camera

NOISE_PX = 0.5


def _scene(tmp_path, model):
    root = tmp_path / "scene"
    (root / "street").mkdir(parents=True)
    write_model(model, root / "street/sparse", binary=True)
    write_manifest(root, "ba", "EPSG:32617", {"street": {"sparse": "street/sparse"}})
    return load_scene(root)


@pytest.fixture(scope="module")
def problem(tmp_path_factory):
    model, reg, truth = ba_problem(noise_px=NOISE_PX)
    return model, reg, truth, _scene(tmp_path_factory.mktemp("ba"), model)


@pytest.fixture(scope="module")
def small_problem(tmp_path_factory):
    model, reg, truth = ba_problem(seed=1, n_cam=14, n_pts=700, noise_px=NOISE_PX)
    return model, reg, truth, _scene(tmp_path_factory.mktemp("ba_small"), model)


def _centre_error(R, t, truth):
    return np.linalg.norm(-np.einsum("cba,cb->ca", R, t) - truth["Cs"], axis=1).mean()


def test_constrained_ba_reaches_the_pixel_noise_and_improves_the_cameras(problem):
    model, reg, truth, scene = problem
    out = ConstrainedBA()(reg, scene, StreetCapture(scene), NullObserver())
    assert out.model.image_names == model.image_names
    assert out.model.points3d.shape == model.points3d.shape
    assert out.rms_before_px > 5 * NOISE_PX
    assert out.rms_after_px <= 1.2 * NOISE_PX
    assert 0 < out.iterations <= 100
    assert _centre_error(out.model.R, out.model.t, truth) < _centre_error(reg.R, reg.t, truth)
    assert np.allclose(np.einsum("cab,cdb->cad", out.model.R, out.model.R), np.eye(3), atol=1e-9)
    # the adjusted 3D points are in the scene CRS, near the truth
    assert np.median(np.linalg.norm(out.model.points3d - truth["Xs"], axis=1)) < 0.3


def test_both_trust_region_strategies_place_the_cameras_alike(problem):
    model, reg, truth, scene = problem
    lm = ConstrainedBA.from_config({"trust_region": "levenberg_marquardt"})(reg, scene, StreetCapture(scene), NullObserver())
    dogleg = ConstrainedBA.from_config({"trust_region": "dogleg"})(reg, scene, StreetCapture(scene), NullObserver())
    assert dogleg.rms_after_px <= 1.2 * NOISE_PX
    # the same minimum up to the solver tolerance: flat along the track, so a few cm apart, equally good
    assert np.abs(dogleg.model.centres - lm.model.centres).max() < 0.05
    assert _centre_error(dogleg.model.R, dogleg.model.t, truth) < 1.1 * _centre_error(lm.model.R, lm.model.t, truth)


def test_a_straight_track_is_solved_with_damped_steps(problem):
    # the test track is a straight street: position priors leave the roll about it unobserved, and
    # dogleg's long steps roll the whole model (points end farther from the truth than warped)
    model, reg, truth, scene = problem
    C = -np.einsum("cba,cb->ca", reg.R, reg.t)
    assert straight_track(C, 0.05) and not straight_track(C, 0.0)
    warped = np.median(np.linalg.norm(warp_points3d(model, reg.R, reg.t) - truth["Xs"], axis=1))
    point_error = lambda out: np.median(np.linalg.norm(out.model.points3d - truth["Xs"], axis=1))
    dogleg = ConstrainedBA.from_config({"trust_region": "dogleg"})(reg, scene, StreetCapture(scene), NullObserver())
    auto = ConstrainedBA()(reg, scene, StreetCapture(scene), NullObserver())
    assert point_error(dogleg) > warped
    assert point_error(auto) < 0.6 * warped


def test_scipy_backend_solves_the_same_problem(small_problem):
    _, reg, truth, scene = small_problem
    ceres = ConstrainedBA()(reg, scene, StreetCapture(scene), NullObserver())
    scipy = ConstrainedBA.from_config({"backend": "scipy"})(reg, scene, StreetCapture(scene), NullObserver())
    assert scipy.rms_after_px <= 1.2 * NOISE_PX
    assert abs(scipy.rms_after_px - ceres.rms_after_px) < 0.02
    # 14 cameras leave a flat valley: equal costs (within 0.5 %) 10 cm apart, both near the truth
    assert np.abs(scipy.model.centres - ceres.model.centres).max() < 0.15
    assert _centre_error(scipy.model.R, scipy.model.t, truth) < _centre_error(reg.R, reg.t, truth)


@pytest.mark.parametrize("backend", ["ceres", "scipy"])
def test_infinite_lambda_keeps_the_warped_positions(small_problem, backend):
    _, reg, _, scene = small_problem
    out = ConstrainedBA.from_config({"lambda_": 1e9, "backend": backend})(reg, scene, StreetCapture(scene), NullObserver())
    warped = -np.einsum("cba,cb->ca", reg.R, reg.t)
    assert np.abs(out.model.centres - warped).max() < 1e-3
    assert out.rms_after_px < out.rms_before_px       # rotations and points still adjust


def test_lambda_trades_positions_against_reprojection(small_problem):
    _, reg, _, scene = small_problem
    warped = -np.einsum("cba,cb->ca", reg.R, reg.t)
    moves = []
    for lam in (1.0, 20.0, 1e4):
        out = ConstrainedBA.from_config({"lambda_": lam})(reg, scene, StreetCapture(scene), NullObserver())
        moves.append(np.linalg.norm(out.model.centres - warped, axis=1).mean())
    assert moves[0] > moves[1] > moves[2]


def test_no_adjust_returns_the_warped_poses(problem):
    _, reg, _, scene = problem
    out = NoAdjust()(reg, scene, StreetCapture(scene), NullObserver())
    assert np.allclose(out.model.R, reg.R) and np.allclose(out.model.t, reg.t)
    assert out.iterations == 0 and out.rms_before_px == out.rms_after_px > 5 * NOISE_PX


def test_adjusted_model_writes_as_text_and_binary(problem, tmp_path):
    _, reg, _, scene = problem
    out = ConstrainedBA()(reg, scene, StreetCapture(scene), NullObserver())
    for binary in (False, True):
        path = tmp_path / ("bin" if binary else "txt")
        write_model(out.model, path, binary=binary)
        back = read_model(path)
        assert back.image_names == out.model.image_names
        assert np.allclose(back.centres, out.model.centres, atol=1e-6)
        assert np.allclose(back.points3d, out.model.points3d)


def test_degenerate_centres_go_to_scipy_with_a_warning(small_problem, tmp_path):
    model, reg, _, _ = small_problem
    C = -np.einsum("cba,cb->ca", reg.R, reg.t)
    C[:, 2] = C[0, 2]                                    # exactly coplanar (all at one height)
    flat = dataclasses.replace(reg, t=-np.einsum("cab,cb->ca", reg.R, C))
    assert degenerate_centres(C) and not degenerate_centres(-np.einsum("cba,cb->ca", reg.R, reg.t))
    obs = NullObserver()
    scene = _scene(tmp_path, model)
    out = ConstrainedBA()(flat, scene, StreetCapture(scene), obs)
    assert any("scipy" in w for w in obs.warnings)
    assert out.rms_after_px < out.rms_before_px


def test_points_follow_the_pose_change_of_their_cameras(problem):
    model, *_ = problem
    rng = np.random.default_rng(0)
    from scipy.spatial.transform import Rotation

    G = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    g = np.array([5e5, 4.4e6, 100.0])
    R_new = np.einsum("cab,db->cad", model.R, G)           # every camera moved by X ↦ G X + g
    t_new = model.t - np.einsum("cab,b->ca", R_new, g)
    X = warp_points3d(model, R_new, t_new)
    assert np.allclose(X, model.points3d @ G.T + g, atol=1e-6)
    assert np.allclose(residuals(model, R_new, t_new, X), residuals(model, model.R, model.t, model.points3d),
                       atol=1e-6)


@pytest.mark.parametrize("name,params", [
    ("SIMPLE_PINHOLE", [700.0, 320, 240]), ("PINHOLE", [700.0, 710, 320, 240]),
    ("SIMPLE_RADIAL", [700.0, 320, 240, -0.08]), ("RADIAL", [700.0, 320, 240, -0.08, 0.01]),
    ("OPENCV", [700.0, 710, 320, 240, -0.08, 0.01, 0.001, -0.002]), ("FULL_OPENCV", [700.0, 710, 320, 240] + [0.01] * 8)])
def test_projection_matches_pycolmap(name, params):
    import pycolmap

    rng = np.random.default_rng(1)
    xc = np.column_stack([rng.uniform(-2, 2, (50, 2)), rng.uniform(3, 10, 50)])
    cam = Camera(1, name, 640, 480, np.array(params))
    ref = pycolmap.Camera(model=name, width=640, height=480, params=params).img_from_cam(xc)
    assert np.allclose(project(cam, xc), ref, atol=1e-8)
    assert rms_px(np.array([[3.0, 4.0]])) == pytest.approx(np.sqrt(12.5))


def test_gross_outlier_observations_are_removed_and_adjusted_again(tmp_path):
    model, reg, truth = ba_problem(seed=2, n_cam=20, n_pts=1200, noise_px=NOISE_PX)
    rng = np.random.default_rng(0)
    ob = model.observations.copy()
    hit = rng.choice(len(ob), 30, replace=False)
    ob[hit, 2:4] += rng.choice([-1, 1], (30, 2)) * rng.uniform(30, 80, (30, 2))     # mismatched features
    model = dataclasses.replace(model, observations=ob)
    obs = NullObserver()
    scene = _scene(tmp_path, model)
    out = ConstrainedBA()(reg, scene, StreetCapture(scene), obs)
    assert any("removed" in w for w in obs.warnings)
    assert len(model.observations) - 60 <= len(out.model.observations) <= len(model.observations) - 30
    assert out.rms_after_px <= 1.2 * NOISE_PX
    other = _scene(tmp_path / "b", model)
    kept = ConstrainedBA.from_config({"max_reproj_error_px": None})(reg, other, StreetCapture(other), NullObserver())
    assert len(kept.model.observations) == len(model.observations) and kept.rms_after_px > 2 * NOISE_PX


def test_ceres_in_a_child_process_gives_the_same_bytes(small_problem, monkeypatch):
    from toolkit.forked import forks

    model, reg, truth, scene = small_problem
    here_or_child = ConstrainedBA()(reg, scene, StreetCapture(scene), NullObserver())
    monkeypatch.setenv("OMP_NUM_THREADS", "1")  # one thread: the solve runs in this process
    assert not forks() and ConstrainedBA().holds_gil()  # so nothing is prefetched beside it
    here = ConstrainedBA()(reg, scene, StreetCapture(scene), NullObserver())
    for a, b in ((here.model.R, here_or_child.model.R), (here.model.t, here_or_child.model.t),
                 (here.model.points3d, here_or_child.model.points3d)):
        assert a.tobytes() == b.tobytes()


def test_prior_variances_add_the_warp_spread_to_one_over_lambda():
    from toolkit.adjust.ba import BAParams, prior_variances

    p = BAParams(lambda_=20.0)
    assert np.allclose(prior_variances(3, p, None), 0.05)
    assert np.allclose(prior_variances(3, p, np.array([0.0, 0.01, 1.0])), np.array([[0.05], [0.06], [1.05]]))
    assert prior_variances(3, p, np.ones((3, 3))).shape == (3, 3)


def test_camera_spread_loosens_only_the_cameras_the_warp_places_uncertainly(small_problem):
    model, reg, truth, scene = small_problem
    plain = ConstrainedBA.from_config({"prior_spread": False})(reg, scene, StreetCapture(scene), NullObserver())
    zero = ConstrainedBA()(dataclasses.replace(reg, camera_spread_m=np.zeros(len(reg.image_names))), scene,
                           StreetCapture(scene), NullObserver())
    assert np.allclose(zero.model.t, plain.model.t, atol=1e-9)        # no spread: the paper's λ
    # one camera's warped centre pushed 3 m off, with a matching spread: the images bring it back
    # closer than with the paper's uniform λ
    k = 3
    C = -np.einsum("cba,cb->ca", reg.R, reg.t)
    C[k] += [3.0, 0.0, 0.0]
    off = dataclasses.replace(reg, t=-np.einsum("cab,cb->ca", reg.R, C))
    spread = np.zeros(len(reg.image_names))
    spread[k] = 3.0
    held = ConstrainedBA.from_config({"prior_spread": False})(off, scene, StreetCapture(scene), NullObserver())
    loose = ConstrainedBA()(dataclasses.replace(off, camera_spread_m=spread), scene, StreetCapture(scene), NullObserver())
    err = lambda m: np.linalg.norm(m.centres[k] - truth["Cs"][k])
    assert err(loose.model) < err(held.model)


def test_a_fix_moves_a_loose_prior_and_not_a_tight_one():
    from toolkit.adjust.fixes import CameraFixes, fuse_fixes

    C = np.array([[0.0, 0.0, 2.0], [100.0, 0.0, 2.0], [200.0, 0.0, 2.0]])
    var = np.array([0.05, 25.0, 25.0])
    fixes = CameraFixes(np.array([0, 1]), np.array([[10.0, 0.0], [110.0, 0.0]]), np.array([5.0, 5.0]))
    fused, fvar = fuse_fixes(C, var, fixes)
    assert abs(fused[0, 0] - 10.0 * 0.05 / 25.05) < 1e-9      # 0.2 % of the way to a 5 m fix
    assert np.allclose(fused[1], [105.0, 0.0, 2.0]) and np.allclose(fvar[1], [12.5, 12.5, 25.0])
    assert np.array_equal(fused[2], C[2]) and np.allclose(fvar[2], 25.0)   # no fix: unchanged
    assert np.array_equal(fused[:, 2], C[:, 2])                # heights keep the warp's


def test_gps_fixes_hold_cameras_the_warp_placed_loosely(small_problem, tmp_path):
    """Cameras pushed 3 m off with a matching spread (what a wrong blend or a bridge gives over a
    stretch): the images cannot tell where the stretch lies, fixes of σ 1 m at the true centres can."""
    from pyproj import Transformer

    model, reg, truth, _ = small_problem
    root = tmp_path / "gps-scene"
    (root / "street").mkdir(parents=True)
    write_model(model, root / "street/sparse", binary=True)
    lon, lat = Transformer.from_crs("EPSG:32617", "EPSG:4326", always_xy=True).transform(
        truth["Cs"][:, 0], truth["Cs"][:, 1])
    (root / "street/gps.csv").write_text("image_name,lon,lat,sigma_m\n" + "".join(
        f"{n},{a:.9f},{b:.9f},1\n" for n, a, b in zip(model.image_names, lon, lat)))
    write_manifest(root, "ba", "EPSG:32617", {"street": {"sparse": "street/sparse", "gps": "street/gps.csv"}})
    scene = load_scene(root)
    loose = slice(None)
    C = -np.einsum("cba,cb->ca", reg.R, reg.t)
    C[loose] += [0.0, 3.0, 0.0]
    spread = np.zeros(len(reg.image_names))
    spread[loose] = 3.0
    off = dataclasses.replace(reg, t=-np.einsum("cab,cb->ca", reg.R, C), camera_spread_m=spread)
    images = ConstrainedBA.from_config({"gps_prior": False})(off, scene, StreetCapture(scene), NullObserver())
    fixed = ConstrainedBA.from_config({"gps_prior": True})(off, scene, StreetCapture(scene), NullObserver())
    err = lambda m: np.linalg.norm(m.centres[loose] - truth["Cs"][loose], axis=1).mean()
    assert err(fixed.model) < 0.5 * err(images.model)
