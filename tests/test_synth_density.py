"""``street_density_factor``: K rows per MVS point in street/cloud.laz, truth for rows i*K only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from toolkit.errors import CrossviewError

K = 3


@pytest.fixture(scope="module")
def tiny_k1_k3(tmp_path_factory) -> tuple[Path, Path]:
    """The tiny preset, seed 0, at K = 1 and at K = 3."""
    from toolkit.synth.generate import generate

    base = tmp_path_factory.mktemp("density")
    one = generate("tiny", 0, base / "k1", preview=False)
    three = generate("tiny", 0, base / "k3", preview=False, street_density_factor=K)
    return one, three


def _laz(root: Path):
    import laspy

    las = laspy.read(root / "street/cloud.laz")
    return las, np.column_stack([las.x, las.y, las.z])


def test_rows_i_times_k_are_the_k1_cloud(tiny_k1_k3):
    from toolkit.io.cloud import read_points

    one, three = tiny_k1_k3
    assert not (three / "street/cloud.ply").exists()
    las, xyz = _laz(three)
    p1, c1 = read_points(one / "street/cloud.ply", with_colors=True)
    assert len(xyz) == K * len(p1) and las.header.point_format.id in (2, 3)
    scale = las.header.scales
    assert np.all(scale <= 0.0005) and np.all(las.header.offsets % 100 == 0)
    assert np.abs(xyz[::K] - p1).max() <= scale.max() / 2 + 1e-9
    rgb1 = c1.astype(np.uint16) * 257
    rgb = np.column_stack([las.red, las.green, las.blue])
    assert np.array_equal(rgb[::K], rgb1) and np.array_equal(rgb[1::K], rgb1) and np.array_equal(rgb[2::K], rgb1)


def test_truth_is_the_k1_truth_for_rows_i_times_k(tiny_k1_k3):
    from toolkit.scene import load_array, load_scene

    one, three = tiny_k1_k3
    scene = load_scene(three)
    assert scene.files.street_cloud.name == "cloud.laz" and scene.has("truth_street_rows")
    rows = load_array(scene, "truth_street_rows")
    n = len(np.load(one / "truth/street_points.npy"))
    assert rows.dtype == np.int64 and np.array_equal(rows, np.arange(0, K * n, K))
    for name in ("street_points", "street_labels"):
        a, b = np.load(one / f"truth/{name}.npy"), np.load(three / f"truth/{name}.npy")
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    # drift.npz (camera_index, sparse_point_index: per truth row), lidar and GPS are the K = 1 scene's
    for name in ("truth/drift.npz", "truth/lidar.ply", "street/gps.csv", "street/sparse/cameras.txt"):
        assert (one / name).read_bytes() == (three / name).read_bytes(), name


def test_extra_samples_stay_near_their_first_row(tiny_k1_k3):
    from toolkit.synth.drift import Drift

    _, three = tiny_k1_k3
    _, xyz = _laz(three)
    d = np.load(three / "truth/drift.npz")
    drift = Drift(**{k: d[k] for k in d.files if k not in ("camera_index", "sparse_point_index", "global_scale")},
                  global_scale=d["global_scale"].item())
    truth = np.load(three / "truth/street_points.npy")
    cam = d["camera_index"]
    # the first rows map back onto the truth through the K = 1 drift (up to the LAS quantisation)
    assert np.abs(drift.undo(xyz[::K], cam) - truth).max() < 1e-3
    extra = drift.undo(xyz.reshape(-1, K, 3)[:, 1:].reshape(-1, 3), np.repeat(cam, K - 1))
    dist = np.linalg.norm(extra.reshape(-1, K - 1, 3) - truth[:, None], axis=2)
    # tiny: point_spacing_m 0.22 (offsets ≤ 0.156 m), noise sigma ≤ 0.09 m per axis at 30 m for both rows
    assert np.median(dist) < 0.2
    assert dist.max() < 0.22 / np.sqrt(2) + 6 * np.sqrt(2) * 0.09
    assert np.percentile(dist, 99) < 0.5


def test_colmap_ids_name_the_dense_rows(tiny_k1_k3):
    from toolkit.io.colmap import read_model

    one, three = tiny_k1_k3
    m1, m3 = read_model(one / "street/sparse"), read_model(three / "street/sparse")
    assert len(m3.points3d_ids) > 1000 and np.all(m3.points3d_ids % K == 1)
    assert np.array_equal(m3.points3d_ids, (m1.points3d_ids - 1) * K + 1)
    assert np.array_equal(m3.points3d, m1.points3d)
    rows = np.load(three / "truth/street_rows.npy")
    spi = np.load(three / "truth/drift.npz")["sparse_point_index"]
    assert np.array_equal(m3.points3d_ids, rows[spi] + 1)


def test_k1_writes_the_ply_and_no_street_rows(tiny_k1_k3):
    import yaml

    from toolkit.scene import load_scene

    one, _ = tiny_k1_k3
    assert (one / "street/cloud.ply").is_file() and not (one / "street/cloud.laz").exists()
    assert not (one / "truth/street_rows.npy").exists()
    manifest = yaml.safe_load((one / "scene.yaml").read_text())
    assert "street_rows" not in manifest["truth"] and manifest["street"]["cloud"] == "street/cloud.ply"
    assert load_scene(one).files.truth_street_rows is None


def test_density_factor_must_be_a_positive_integer():
    from toolkit.synth.config import config_for

    with pytest.raises(CrossviewError, match="street_density_factor"):
        config_for("tiny", street_density_factor=0)
    assert config_for("tiny").street_density_factor == 1


def _flat_chunk(normal, n=500, sigma=0.0, outlier=False):
    from toolkit.synth.street import StreetChunk

    rng = np.random.default_rng(1)
    hits = rng.uniform(0, 50, (n, 3))
    return StreetChunk(
        points=hits.copy(), labels=np.zeros(n, np.int32), colors=rng.integers(0, 255, (n, 3)).astype(np.uint8),
        camera=np.zeros(n, np.int32), surface=np.zeros((0, 3)), surface_labels=np.zeros(0, np.int32),
        hits=hits, normals=np.tile(np.asarray(normal, np.float32), (n, 1)), sigma=np.full(n, sigma),
        outlier=np.full(n, outlier),
    )


@pytest.mark.parametrize("normal", [(0, 0, 1), (1, 0, 0), (0.6, 0.8, 0)])
def test_extra_samples_lie_in_the_hit_plane(tmp_path, normal):
    """Without noise or drift, the extra samples are the hit moved within its plane by ≤ spacing/2 per axis."""
    import laspy

    from toolkit.synth.config import config_for
    from toolkit.synth.density import DenseCloudWriter, tangent_axes
    from toolkit.synth.drift import Drift

    cfg = config_for("tiny", street_density_factor=5)
    eye = np.eye(3)
    drift = Drift(np.zeros((1, 3)), np.zeros((1, 3)), eye[None], np.ones(1), eye, np.zeros(3))
    ch = _flat_chunk(normal)
    outs = []
    for name in ("a.laz", "b.laz"):
        w = DenseCloudWriter(tmp_path / name, drift, cfg, np.zeros(3), np.random.default_rng(5))
        w.write(ch, ch.points)
        w.close()
        outs.append((tmp_path / name).read_bytes())
    assert outs[0] == outs[1]  # deterministic bytes
    las = laspy.read(tmp_path / "a.laz")
    xyz = np.column_stack([las.x, las.y, las.z]).reshape(-1, 5, 3)
    q = las.header.scales.max()
    assert np.abs(xyz[:, 0] - ch.hits).max() <= q
    t1, t2 = tangent_axes(ch.normals)
    d = xyz[:, 1:] - ch.hits[:, None]
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    assert np.abs(d @ n).max() <= 2 * q
    half = cfg.point_spacing_m / 2
    for t in (t1, t2):
        along = np.einsum("nkj,nj->nk", d, t)
        assert np.abs(along).max() <= half + 2 * q and np.abs(along).max() > 0.9 * half
    assert np.allclose(np.einsum("ij,ij->i", t1, t2), 0) and np.allclose(np.einsum("ij,ij->i", t1, ch.normals), 0)
