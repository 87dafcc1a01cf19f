"""``crossview apply``: the stored warp (warp.npz) moves other clouds and meshes of the street frame
like the run's own points (docs/apply.md)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from tests.registered_runs import input_attributes, tiny_cloud, tiny_run, write_laz
from toolkit.cli import main


def _ply(path: Path):
    from toolkit.io.attributes import open_cloud

    src = open_cloud(path)
    chunk = next(src.chunks(src.count))
    return chunk.xyz, chunk.values


def test_the_stored_warp_reloads_as_the_run_built_it():
    from toolkit.warp.store import load_warp

    res, _ = tiny_run("ply")
    warp, stored = res.results.registration.warp, load_warp(res.out_dir)
    assert stored.crs == "EPSG:32617" and np.allclose(stored.las_offset_m % 100, 0)
    w = stored.warp
    assert np.array_equal(w.T, warp.T) and np.array_equal(w.index.valid, warp.index.valid)
    assert w.index.neighbours.keys() == warp.index.neighbours.keys()
    for i, listed in warp.index.neighbours.items():
        assert np.array_equal(w.index.neighbours[i], listed)
        assert np.array_equal(w.index.trees[i].data, warp.index.trees[i].data)
    assert (w.neighbours_k, w.min_distance_m, w.weight_cell_m, w.relative_distance) == \
        (warp.neighbours_k, warp.min_distance_m, warp.weight_cell_m, warp.relative_distance)


@pytest.mark.parametrize("chunk_points", [1 << 20, 40_000])
def test_applying_a_run_to_its_own_cloud_reproduces_registered_laz_and_ply(tmp_path, chunk_points):
    import laspy

    from toolkit.apply_warp import apply_run

    res, scene = tiny_run("ply")
    cloud = scene / "street/cloud.ply"
    t0 = time.perf_counter()
    done = apply_run(res.out_dir, cloud, tmp_path / "own.laz", chunk_points=chunk_points)
    seconds = time.perf_counter() - t0
    print(f"apply on the tiny cloud: {done.count / seconds:,.0f} points/s ({seconds:.2f} s, chunks {chunk_points})")
    ref, got = laspy.read(res.out_dir / "registered.laz"), laspy.read(done.out)
    for axis in "XYZ":
        assert np.array_equal(np.asarray(got[axis]), np.asarray(ref[axis])), axis   # the same 1 mm integers
    assert np.array_equal(got.segment, ref.segment) and np.array_equal(got.red, ref.red)
    assert done.carriers.max_m == 0.0
    apply_run(res.out_dir, cloud, tmp_path / "own.ply", chunk_points=chunk_points)
    xyz, values = _ply(tmp_path / "own.ply")
    reg_xyz, reg_values = _ply(res.out_dir / "registered.ply")
    assert np.abs(xyz - reg_xyz).max() < 0.001
    assert np.array_equal(values["segment"], reg_values["segment"])


def test_a_laz_cloud_keeps_its_dimensions_and_lands_on_the_registered_points(tmp_path):
    import laspy

    from toolkit.apply_warp import apply_run

    res, _ = tiny_run("ply")
    xyz, rgb = tiny_cloud()
    write_laz(tmp_path / "in.laz", xyz, rgb, point_format=3)
    out = apply_run(res.out_dir, tmp_path / "in.laz", chunk_points=50_000).out
    assert out == res.out_dir / "in.registered.laz"
    las = laspy.read(out)
    extra = input_attributes(len(xyz))
    assert np.array_equal(las.intensity, extra["intensity"]) and np.array_equal(las.reflectance, extra["reflectance"])
    assert np.array_equal(las.red, rgb[:, 0].astype(np.uint16) * 257)
    reg = res.results.registration.points
    # the input's 0.1 mm steps and the output's 1 mm ones: within 1 mm of the registered points, but
    # for the few that the 0.1 mm steps put in the next 0.5 m weight cell (its blend: mm away)
    err = np.abs(np.column_stack([las.x, las.y, las.z]) - reg).max(axis=1)
    assert np.percentile(err, 99.9) < 0.001 and err.max() < 0.01, (np.percentile(err, 99.9), err.max())
    out.unlink()


def _mesh_vertices(n: int = 3000) -> np.ndarray:
    xyz, _ = tiny_cloud()
    return np.random.default_rng(2).choice(len(xyz), n, replace=False)


def test_a_ply_mesh_moves_its_vertices_like_the_points_and_keeps_its_faces(tmp_path):
    from toolkit.apply_warp import apply_run

    res, _ = tiny_run("ply")
    xyz, _ = tiny_cloud()
    rows = _mesh_vertices()
    faces = np.arange(len(rows) - 2)[:, None] + np.arange(3)
    path = tmp_path / "mesh.ply"
    header = ["ply", "format binary_little_endian 1.0", "comment made by a test", f"element vertex {len(rows)}",
              "property float x", "property float y", "property float z", "property float quality",
              f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    local = xyz[rows] - xyz[rows].mean(axis=0)
    # float32 vertices, as meshing tools write them (a street frame a few hundred metres wide: ~0.03 mm)
    vert = np.empty(len(rows), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("quality", "<f4")])
    for axis, c in enumerate("xyz"):
        vert[c] = xyz[rows, axis]
    vert["quality"] = local[:, 0]
    face = np.empty(len(faces), [("n", "u1"), ("v", "<i4", (3,))])
    face["n"], face["v"] = 3, faces
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode())
        vert.tofile(fh)
        face.tofile(fh)
    out = apply_run(res.out_dir, path, tmp_path / "moved.ply").out
    got, values = _ply(out)
    reg = res.results.registration.points[rows]
    assert np.abs(got - reg).max() < 0.005     # float32 input vertices: a few hundredths of a mm off
    assert np.array_equal(values["quality"], vert["quality"])
    assert out.read_bytes().endswith(face.tobytes())
    text = out.read_bytes()[:400].decode("ascii", "replace")
    assert "element face" in text and "property double x" in text and "comment made by a test" in text


def test_an_obj_mesh_moves_vertices_and_turns_normals(tmp_path):
    from toolkit.apply_warp import apply_run
    from toolkit.io.mesh import read_obj

    res, _ = tiny_run("ply")
    xyz, _ = tiny_cloud()
    rows = _mesh_vertices(500)
    lines = ["# test mesh", "o part"] + [f"v {x!r} {y!r} {z!r}" for x, y, z in xyz[rows].tolist()]
    lines += ["vn 0 0 1", "vt 0.5 0.5"]
    lines += [f"f {i + 1}/1/1 {i + 2}/1/1 {i + 3}/1/1" for i in range(len(rows) - 2)]
    path = tmp_path / "mesh.obj"
    path.write_text("\n".join(lines) + "\n")
    out = apply_run(res.out_dir, path).out
    assert out == res.out_dir / "mesh.registered.obj"
    mesh = read_obj(out)
    reg = res.results.registration
    assert np.abs(mesh.xyz - reg.points[rows]).max() < 0.001
    turned = mesh.vn[0]
    own = np.asarray(res.results.transforms.T)[reg.point_segment[rows[0]], :3, :3] @ [0, 0, 1]
    assert abs(np.linalg.norm(turned) - 1) < 1e-5 and np.degrees(np.arccos(min(1.0, own @ turned))) < 5
    assert "vt 0.5 0.5" in out.read_text() and out.read_text().count("\nf ") == len(rows) - 2
    out.unlink()


def test_ply_normals_are_turned(tmp_path):
    from toolkit.apply_warp import apply_run
    from toolkit.io.cloud import write_ply

    res, _ = tiny_run("ply")
    xyz, rgb = tiny_cloud()
    up = np.zeros((len(xyz), 3), np.float32)
    up[:, 2] = 1
    write_ply(tmp_path / "n.ply", xyz, rgb, extra={"nx": up[:, 0], "ny": up[:, 1], "nz": up[:, 2]})
    apply_run(res.out_dir, tmp_path / "n.ply", tmp_path / "n_out.ply")
    _, values = _ply(tmp_path / "n_out.ply")
    turned = np.column_stack([values["nx"], values["ny"], values["nz"]]).astype(np.float64)
    reg, T = res.results.registration, np.asarray(res.results.transforms.T)
    own = T[reg.point_segment, :3, 2]
    angle = np.degrees(np.arccos(np.clip((own * turned).sum(axis=1), -1, 1)))
    assert np.median(angle) < 1.0 and angle.max() < 10.0


def _cli(args: list[str], capsys) -> tuple[int, list[str]]:
    code = main(["apply", *args])
    return code, capsys.readouterr().err.strip().splitlines()


def test_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    res, scene = tiny_run("ply")
    cloud = str(scene / "street/cloud.ply")
    out = tmp_path / "x.laz"
    cases = [
        ([str(tmp_path / "missing"), "--cloud", cloud, "--out", str(out)], "run folder not found"),
        ([str(tmp_path), "--cloud", cloud, "--out", str(out)], "no stored warp"),
        ([str(res.out_dir), "--cloud", str(tmp_path / "c.xyz"), "--out", str(out)], "unsupported cloud or mesh format"),
        ([str(res.out_dir), "--cloud", str(tmp_path / "none.ply"), "--out", str(out)], "file not found"),
        ([str(res.out_dir), "--cloud", cloud, "--out", str(tmp_path / "x.txt")], "a cloud is written as"),
    ]
    (tmp_path / "c.xyz").write_text("1 2 3\n")
    for args, message in cases:
        code, err = _cli(args, capsys)
        assert code == 2 and len(err) == 1 and message in err[0], (args, err)
        assert not out.exists() and not list(tmp_path.glob(".*partial*"))
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    bad_run = tmp_path / "bad_run"
    bad_run.mkdir()
    (bad_run / "warp.npz").write_bytes(b"not a zip")
    code, err = _cli([str(bad_run), "--cloud", cloud, "--out", str(out)], capsys)
    assert code == 2 and len(err) == 1 and "cannot read the stored warp" in err[0]
    assert not out.exists()


def test_existing_output_is_refused_unless_overwrite(tmp_path, capsys):
    res, scene = tiny_run("ply")
    out = tmp_path / "o.laz"
    out.write_bytes(b"keep")
    code, err = _cli([str(res.out_dir), "--cloud", str(scene / "street/cloud.ply"), "--out", str(out)], capsys)
    assert code == 2 and "already exists" in err[0] and out.read_bytes() == b"keep"
    code = main(["apply", str(res.out_dir), "--cloud", str(scene / "street/cloud.ply"), "--out", str(out),
                 "--overwrite", "-q"])
    assert code == 0 and out.read_bytes()[:4] == b"LASF"


def test_a_warp_without_blending_moves_each_point_by_its_carrier_transform():
    """warp.nearest stores neighbours_k = 0: the carrier's own transform, through the same function
    (the stored warp without the adjust step's camera following)."""
    from dataclasses import replace

    from toolkit.warp.store import load_warp

    res, _ = tiny_run("ply")
    xyz, _ = tiny_cloud()
    warp = replace(load_warp(res.out_dir).warp, neighbours_k=0, cameras=None)
    carriers, _ = warp.carriers(xyz[:5000])
    moved = warp.maps(xyz[:5000], carriers).apply(xyz[:5000])
    T = warp.T[carriers]
    metric = xyz[:5000] / warp.street_scale         # the transforms act on the frame in metres
    assert np.abs(moved - (np.einsum("nab,nb->na", T[:, :3, :3], metric) + T[:, :3, 3])).max() < 1e-6


def test_a_stored_warp_that_follows_the_cameras_moves_each_point_with_its_capture_camera():
    """After the adjust step the run's points follow their capture cameras; the stored warp does too."""
    from toolkit.io.colmap import read_model
    from toolkit.warp.store import load_warp

    res, scene = tiny_run("ply")
    xyz, _ = tiny_cloud()
    warp = load_warp(res.out_dir).warp
    assert warp.cameras is not None and len(warp.source.camera) == len(xyz)
    before, after = read_model(scene / "street/sparse"), read_model(res.out_dir / "sparse")
    cam = warp.source.camera[:5000].astype(np.int64)
    moved = warp.maps(xyz[:5000], warp.carriers(xyz[:5000])[0]).apply(xyz[:5000])
    metric = xyz[:5000] / warp.street_scale
    seen = np.einsum("nab,nb->na", before.R[cam], metric) + before.t[cam] / warp.street_scale
    # the adjusted camera sees the moved point in the direction the input camera saw the input
    # point, at the warp's local scale times its depth
    again = np.einsum("nab,nb->na", after.R[cam], moved) + after.t[cam]
    ratio = np.linalg.norm(again, axis=1) / np.linalg.norm(seen, axis=1)
    assert np.abs(again - ratio[:, None] * seen).max() < 1e-6
    assert np.abs(ratio - 1).max() < 0.05
