"""File I/O: COLMAP text/binary round-trip (and pycolmap agreement), GeoTIFF CRS, PLY float64."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from toolkit.errors import SceneError
from toolkit.io.cloud import read_points, write_ply
from toolkit.io.colmap import qvec_to_rotmat, read_model, rotmat_to_qvec, write_model
from toolkit.io.raster import read_raster, write_geotiff
from toolkit.types import Camera, Grid, SparseModel


def _random_model(seed: int = 0, n_img: int = 5, n_pts: int = 40) -> SparseModel:
    rng = np.random.default_rng(seed)
    from scipy.spatial.transform import Rotation

    cams = {1: Camera(1, "PINHOLE", 800, 600, np.array([700.1, 701.2, 400.3, 300.4])),
            3: Camera(3, "SIMPLE_RADIAL", 640, 480, np.array([500.0, 320.0, 240.0, 0.01]))}
    R = Rotation.random(n_img, random_state=seed).as_matrix()
    obs = []
    for k in range(n_img):
        for p in rng.choice(n_pts, size=10, replace=False):
            obs.append([k, p, rng.uniform(0, 640), rng.uniform(0, 480)])
    return SparseModel(
        cameras=cams, image_names=tuple(f"frame_{k:04d}.jpg" for k in range(n_img)),
        image_ids=np.arange(1, n_img + 1) * 2, camera_ids=np.array([1, 3, 1, 3, 1])[:n_img],
        R=R, t=rng.normal(size=(n_img, 3)) * 100,
        points3d_ids=np.arange(n_pts) + 100, points3d=rng.normal(size=(n_pts, 3)) * 1e5,
        points3d_rgb=rng.integers(0, 255, size=(n_pts, 3)).astype(np.uint8),
        observations=np.array(obs, dtype=np.float64),
    )


def _assert_same(a: SparseModel, b: SparseModel) -> None:
    assert a.image_names == b.image_names
    np.testing.assert_array_equal(a.image_ids, b.image_ids)
    np.testing.assert_array_equal(a.camera_ids, b.camera_ids)
    np.testing.assert_allclose(a.R, b.R, atol=1e-15)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.points3d, b.points3d)
    np.testing.assert_array_equal(a.points3d_rgb, b.points3d_rgb)
    np.testing.assert_array_equal(a.observations, b.observations)
    for cid in a.cameras:
        assert a.cameras[cid].model == b.cameras[cid].model
        np.testing.assert_array_equal(a.cameras[cid].params, b.cameras[cid].params)


@pytest.mark.parametrize("binary", [False, True])
def test_colmap_roundtrip_exact(tmp_path: Path, binary: bool):
    m = _random_model()
    write_model(m, tmp_path / "m", binary=binary)
    back = read_model(tmp_path / "m")
    _assert_same(m, back)
    # a second write of what we read is byte-identical
    write_model(back, tmp_path / "m2", binary=binary)
    for f in (tmp_path / "m").iterdir():
        assert f.read_bytes() == (tmp_path / "m2" / f.name).read_bytes()


def _reference_txt(model: SparseModel, path: Path) -> None:
    """The text writer as it was: one f-string (repr per float) per observation and per point."""
    from toolkit.io.colmap import _qvecs, _Tracks

    tr = _Tracks(model)
    path.mkdir(parents=True)
    qs = _qvecs(model)
    uv = [f"{u!r} {v!r} {p}" for (u, v), p in zip(tr.uv.tolist(), tr.pid.tolist())]
    with open(path / "images.txt", "w") as fh:
        fh.write("# IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n# POINTS2D[] as (X, Y, POINT3D_ID)\n")
        for k, name in enumerate(model.image_names):
            vals = [*map(float, qs[k]), *map(float, model.t[k])]
            fh.write(" ".join([str(int(model.image_ids[k])), *map(repr, vals), str(int(model.camera_ids[k])), name]) + "\n")
            fh.write(" ".join(uv[tr.img_start[k]:tr.img_start[k + 1]]) + "\n")
    pairs = [f"{a} {j}" for a, j in tr.track.tolist()]
    xyz, rgb = np.asarray(model.points3d, np.float64).tolist(), np.asarray(model.points3d_rgb).tolist()
    starts = tr.pt_start.tolist()
    with open(path / "points3D.txt", "w") as fh:
        fh.write("# POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n")
        fh.writelines(
            f"{pid} {x!r} {y!r} {z!r} {r} {g} {b} 0.0 {' '.join(pairs[starts[i]:starts[i + 1]])}\n"
            for i, (pid, (x, y, z), (r, g, b)) in enumerate(zip(np.asarray(model.points3d_ids).tolist(), xyz, rgb)))


def test_text_writer_matches_per_value_repr(tmp_path: Path):
    """The column-wise text writer gives the very bytes of per-value repr formatting, edge cases included."""
    from dataclasses import replace

    m = _random_model(3, n_img=5, n_pts=40)
    obs = m.observations.copy()
    special = [0.0, -0.0, 1.0, 1e-5, 1e16, 123456789.125, 5e-324, -2.5e-7, 0.1 + 0.2, 1e22]
    obs[:len(special), 2] = special
    obs[:len(special), 3] = special[::-1]
    obs = obs[obs[:, 0] != 2]  # an image without observations
    pts = m.points3d.copy()
    pts[:len(special), 0] = special
    m = replace(m, observations=obs, points3d=pts)  # some points now have no track
    write_model(m, tmp_path / "new", binary=False)
    _reference_txt(m, tmp_path / "ref")
    for name in ("images.txt", "points3D.txt"):
        assert (tmp_path / "new" / name).read_bytes() == (tmp_path / "ref" / name).read_bytes(), name
    _assert_same(m, read_model(tmp_path / "new"))


def test_text_and_binary_agree(tmp_path: Path):
    m = _random_model(1)
    write_model(m, tmp_path / "t", binary=False)
    write_model(m, tmp_path / "b", binary=True)
    _assert_same(read_model(tmp_path / "t"), read_model(tmp_path / "b"))


@pytest.mark.parametrize("binary", [False, True])
def test_pycolmap_reads_our_models(tmp_path: Path, binary: bool):
    pycolmap = pytest.importorskip("pycolmap")
    m = _random_model(2)
    write_model(m, tmp_path / "m", binary=binary)
    rec = pycolmap.Reconstruction(str(tmp_path / "m"))
    assert rec.num_images() == len(m.image_names) and rec.num_points3D() == len(m.points3d)
    for k, iid in enumerate(m.image_ids):
        img = rec.images[int(iid)]
        assert img.name == m.image_names[k]
        pose = img.cam_from_world() if callable(img.cam_from_world) else img.cam_from_world
        np.testing.assert_allclose(pose.rotation.matrix(), m.R[k], atol=1e-12)
        np.testing.assert_allclose(pose.translation, m.t[k], atol=1e-9)


def test_quaternion_helpers_invert():
    from scipy.spatial.transform import Rotation

    R = Rotation.random(20, random_state=3).as_matrix()
    np.testing.assert_allclose(qvec_to_rotmat(rotmat_to_qvec(R)), R, atol=1e-14)


def test_images_txt_with_odd_lines_is_one_line_error(tmp_path: Path):
    write_model(_random_model(), tmp_path / "m")
    lines = (tmp_path / "m/images.txt").read_text().splitlines()
    (tmp_path / "m/images.txt").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(SceneError, match="odd number of lines"):
        read_model(tmp_path / "m")


def test_model_referencing_missing_point_or_camera(tmp_path: Path):
    m = _random_model()
    write_model(m, tmp_path / "m")
    pts = (tmp_path / "m/points3D.txt").read_text().splitlines()
    (tmp_path / "m/points3D.txt").write_text("\n".join(pts[:-3]) + "\n")
    with pytest.raises(SceneError, match="missing 3D point"):
        read_model(tmp_path / "m")
    write_model(m, tmp_path / "c")
    cams = (tmp_path / "c/cameras.txt").read_text().splitlines()
    (tmp_path / "c/cameras.txt").write_text("\n".join(c for c in cams if not c.startswith("3 ")) + "\n")
    with pytest.raises(SceneError, match="missing camera 3"):
        read_model(tmp_path / "c")


def test_geotiff_crs_transform_nodata_roundtrip(tmp_path: Path):
    grid = Grid((0.5, 0.0, 431000.25, 0.0, -0.5, 4428000.75), 30, 20, "EPSG:32617")
    data = np.arange(600, dtype=np.float32).reshape(20, 30)
    data[0, 0] = -9999
    write_geotiff(tmp_path / "a.tif", data, grid, nodata=-9999.0)
    r = read_raster(tmp_path / "a.tif", expect_crs="EPSG:32617")
    assert r.grid == grid
    np.testing.assert_array_equal(r.data[0], data)
    assert r.nodata_mask[0, 0] and r.nodata_mask.sum() == 1
    with pytest.raises(SceneError, match="differs from the scene CRS"):
        read_raster(tmp_path / "a.tif", expect_crs="EPSG:32633")


def test_geotiff_band_names_and_no_crs(tmp_path: Path):
    import rasterio

    grid = Grid((1.0, 0.0, 0.0, 0.0, -1.0, 10.0), 4, 3, "EPSG:32617")
    write_geotiff(tmp_path / "o.tif", np.zeros((4, 3, 4), np.uint8), grid, band_names=("nir", "red", "green", "blue"))
    assert read_raster(tmp_path / "o.tif").band_names == ("nir", "red", "green", "blue")
    with rasterio.open(tmp_path / "n.tif", "w", driver="GTiff", width=4, height=3, count=1, dtype="float32") as ds:
        ds.write(np.zeros((1, 3, 4), np.float32))
    with pytest.raises(SceneError, match="no CRS"):
        read_raster(tmp_path / "n.tif")


def test_grid_pixel_world_inverse():
    grid = Grid((0.5, 0.0, 431000.0, 0.0, -0.5, 4428000.0), 100, 80, "EPSG:32617")
    rows, cols = np.array([0, 5, 79]), np.array([0, 7, 99])
    back = grid.world_to_pixel(grid.pixel_to_world(rows, cols))
    np.testing.assert_allclose(back, np.stack([rows, cols], 1), atol=1e-9)


def test_ply_keeps_float64_utm_coordinates(tmp_path: Path):
    xyz = np.array([[431234.123456789, 4428765.987654321, 201.000000001]] * 3) + np.arange(3)[:, None]
    write_ply(tmp_path / "c.ply", xyz, colors=np.full((3, 3), 7, np.uint8))
    back, rgb = read_points(tmp_path / "c.ply", with_colors=True)
    np.testing.assert_array_equal(back, xyz)
    assert (rgb == 7).all()


def test_ply_ascii_and_open3d_files_read(tmp_path: Path):
    import open3d as o3d

    pts = np.random.default_rng(0).normal(size=(50, 3))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    o3d.io.write_point_cloud(str(tmp_path / "a.ply"), pcd, write_ascii=True)
    o3d.io.write_point_cloud(str(tmp_path / "b.pcd"), pcd)
    np.testing.assert_allclose(read_points(tmp_path / "a.ply"), pts, atol=1e-5)  # Open3D writes 6 digits
    np.testing.assert_allclose(read_points(tmp_path / "b.pcd"), pts, atol=1e-6)


def test_las_and_laz_read(tmp_path: Path):
    import laspy

    pts = np.random.default_rng(1).uniform(0, 100, size=(200, 3)) + [431000, 4428000, 200]
    for ext in ("las", "laz"):
        hdr = laspy.LasHeader(point_format=3, version="1.2")
        hdr.offsets, hdr.scales = pts.min(0), [0.001] * 3
        las = laspy.LasData(hdr)
        las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
        las.write(tmp_path / f"c.{ext}")
        np.testing.assert_allclose(read_points(tmp_path / f"c.{ext}"), pts, atol=1e-3)


@pytest.mark.parametrize("content,match", [
    (b"", "empty"), (b"not a ply\n", "not a PLY"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty double x\nproperty double y\n"
     b"property double z\nend_header\n" + b"\0" * 50, "truncated"),
])
def test_bad_ply_is_one_line_scene_error(tmp_path: Path, content: bytes, match: str):
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(SceneError, match=match) as err:
        read_points(tmp_path / "bad.ply")
    assert "\n" not in str(err.value)


def test_nan_cloud_rejected(tmp_path: Path):
    write_ply(tmp_path / "n.ply", np.array([[0, 0, 0], [np.nan, 1, 2]], float))
    with pytest.raises(SceneError, match="NaN or Inf"):
        read_points(tmp_path / "n.ply")


def test_last_image_without_observations_reads(tmp_path: Path):
    import dataclasses

    m = _random_model(4)
    m = dataclasses.replace(m, observations=m.observations[m.observations[:, 0] != len(m.image_names) - 1])
    write_model(m, tmp_path / "m")
    assert (tmp_path / "m/images.txt").read_text().endswith("\n\n")
    _assert_same(m, read_model(tmp_path / "m"))


def test_ply_streams_in_chunks(tmp_path: Path, monkeypatch):
    """Records are read and written a bounded chunk at a time; the bytes and values stay the same."""
    import toolkit.io.cloud as cloud

    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(1001, 3)) * 1000 + [431000.0, 4428000.0, 200.0]
    rgb = rng.integers(0, 256, size=(1001, 3)).astype(np.uint8)
    seg = rng.integers(-2, 50, size=1001).astype(np.int32)
    write_ply(tmp_path / "whole.ply", xyz, colors=rgb, extra={"segment": seg})
    monkeypatch.setattr(cloud, "CHUNK_BYTES", 7 * 31)  # 7 records of 31 bytes per chunk: 143 chunks
    write_ply(tmp_path / "chunked.ply", xyz, colors=rgb, extra={"segment": seg})
    assert (tmp_path / "whole.ply").read_bytes() == (tmp_path / "chunked.ply").read_bytes()
    back, back_rgb = read_points(tmp_path / "chunked.ply", with_colors=True)
    np.testing.assert_array_equal(back, xyz)
    np.testing.assert_array_equal(back_rgb, rgb)
    raw = (tmp_path / "chunked.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(raw[:-40])
    with pytest.raises(SceneError, match="truncated \\(999 of 1001"):
        read_points(tmp_path / "cut.ply")


def test_laz_read_in_chunks(tmp_path: Path):
    """LAS/LAZ go through laspy's chunk iterator: many chunks give the same points and colours."""
    import laspy

    from toolkit.io.cloud import _read_las

    rng = np.random.default_rng(2)
    pts = rng.uniform(0, 100, size=(1000, 3)) + [431000, 4428000, 200]
    rgb = rng.integers(0, 65536, size=(1000, 3)).astype(np.uint16)
    hdr = laspy.LasHeader(point_format=3, version="1.2")
    hdr.offsets, hdr.scales = pts.min(0), [0.001] * 3
    las = laspy.LasData(hdr)
    las.x, las.y, las.z = pts[:, 0], pts[:, 1], pts[:, 2]
    las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.write(tmp_path / "c.laz")
    whole_xyz, whole_rgb = _read_las(tmp_path / "c.laz")
    xyz, col = _read_las(tmp_path / "c.laz", chunk_points=64)  # 16 chunks
    np.testing.assert_array_equal(xyz, whole_xyz)
    np.testing.assert_allclose(xyz, pts, atol=1e-3)
    np.testing.assert_array_equal(col, whole_rgb)
    np.testing.assert_array_equal(col, (rgb >> 8).astype(np.uint8))
