"""registered.laz / registered.ply / warp.npz / the CRS beside the outputs (docs/formats.md, Outputs)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tests.fake_stages import FAKE_RECIPE, fake_registry
from tests.registered_runs import input_attributes, tiny_cloud, tiny_run
from toolkit.errors import RecipeError


def _ply(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray], tuple[str, ...]]:
    from toolkit.io.attributes import open_cloud

    src = open_cloud(path)
    chunk = next(src.chunks(src.count))
    return chunk.xyz, chunk.values, src.names


def test_registered_laz_has_the_scene_crs_1mm_steps_colours_and_segments():
    import laspy
    import pyproj

    res, scene = tiny_run("ply")
    las = laspy.read(res.out_dir / "registered.laz")
    assert las.header.parse_crs() == pyproj.CRS.from_user_input("EPSG:32617")
    assert las.header.global_encoding.wkt and las.header.version.minor == 4
    assert np.allclose(las.header.scales, 0.001)
    assert np.allclose(las.header.offsets % 100, 0)
    xyz, values, names = _ply(res.out_dir / "registered.ply")
    assert names == ("red", "green", "blue", "segment")
    got = np.column_stack([las.x, las.y, las.z])
    assert np.abs(got - xyz).max() <= 0.0005 + 1e-9
    assert np.abs(xyz - res.results.registration.points).max() == 0
    _, rgb = tiny_cloud()
    assert np.array_equal(np.column_stack([las.red, las.green, las.blue]), rgb.astype(np.uint16) * 257)
    assert las.segment.dtype == np.int32 and np.array_equal(las.segment, values["segment"])
    assert np.array_equal(values["segment"], res.results.registration.point_segment)


def test_crs_in_metrics_and_beside_the_colmap_model():
    import pyproj

    res, _ = tiny_run("ply")
    assert json.loads((res.out_dir / "metrics.json").read_text())["crs"] == "EPSG:32617"
    wkt = (res.out_dir / "sparse/crs.wkt").read_text()
    assert pyproj.CRS.from_wkt(wkt) == pyproj.CRS.from_user_input("EPSG:32617")


def test_a_laz_input_keeps_its_point_format_intensity_colours_and_extra_dims_in_input_order():
    import laspy

    res, scene = tiny_run("laz")
    src = laspy.read(scene / "street/cloud.laz")
    out = laspy.read(res.out_dir / "registered.laz")
    assert out.header.point_format.id == src.header.point_format.id == 3
    assert out.header.parse_crs().to_epsg() == 32617 and out.header.global_encoding.wkt
    assert list(out.point_format.dimension_names) == [*src.point_format.dimension_names, "segment"]
    extra = input_attributes(len(src.points))
    for name in ("intensity", "classification", "reflectance"):
        assert np.array_equal(np.asarray(out[name]), extra[name]), name
    for name in ("red", "green", "blue", "gps_time", "return_number", "point_source_id"):
        assert np.array_equal(np.asarray(out[name]), np.asarray(src[name])), name
    reg = res.results.registration.points
    assert np.abs(np.column_stack([out.x, out.y, out.z]) - reg).max() <= 0.0005 + 1e-9
    xyz, values, names = _ply(res.out_dir / "registered.ply")
    assert names[:3] == ("intensity", "return_number", "number_of_returns") and names[-1] == "segment"
    assert np.array_equal(values["intensity"], extra["intensity"])
    assert np.array_equal(values["red"], np.asarray(src.red))


def test_outputs_are_byte_identical_for_the_same_recipe_and_scene(tmp_path):
    from toolkit.runner import run_recipe
    from tests.registered_runs import RECIPE

    res, scene = tiny_run("ply")
    again = run_recipe(RECIPE, scene=scene, out=tmp_path / "again", rerun=False)
    for name in ("registered.laz", "registered.ply", "warp.npz", "sparse/crs.wkt", "metrics.json"):
        assert (res.out_dir / name).read_bytes() == (again.out_dir / name).read_bytes(), name


def test_outputs_ply_false_skips_registered_ply(tmp_path, mini_scene):
    from toolkit.runner import run_recipe

    recipe = tmp_path / "fake.yaml"
    recipe.write_text(FAKE_RECIPE + "outputs: {ply: false}\n")
    res = run_recipe(recipe, scene=mini_scene, out=tmp_path / "out", registry=fake_registry(), rerun=False)
    assert (res.out_dir / "registered.laz").is_file() and not (res.out_dir / "registered.ply").exists()
    assert "outputs" in (res.out_dir / "recipe.yaml").read_text()
    assert not (res.out_dir / "warp.npz").exists()  # the fake warp stage gives no reloadable warp


@pytest.mark.parametrize("block, message", [
    ("outputs: {ply: 0}\n", "outputs.ply: must be true or false"),
    ("outputs: {laz: false}\n", "outputs: unknown key 'laz'"),
    ("outputs: [ply]\n", "outputs: must be a mapping"),
])
def test_bad_outputs_block_is_one_line_naming_the_key(tmp_path, block, message):
    from toolkit.recipe import load_recipe

    recipe = tmp_path / "fake.yaml"
    recipe.write_text(FAKE_RECIPE + block)
    with pytest.raises(RecipeError, match=message):
        load_recipe(recipe)


def test_ply_normals_are_turned_with_the_points(tmp_path):
    """A PLY with normals: registered.* carry them turned by each point's blended rotation."""
    import laspy

    from toolkit.export import export_cloud, registration_mover
    from toolkit.io.attributes import open_cloud
    from toolkit.io.cloud import write_ply
    from toolkit.io.cloud_out import LasGrid

    res, _ = tiny_run("ply")
    xyz, rgb = tiny_cloud()
    rng = np.random.default_rng(1)
    normals = rng.normal(size=xyz.shape)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    extra = {"nx": normals[:, 0].astype(np.float32), "ny": normals[:, 1].astype(np.float32),
             "nz": normals[:, 2].astype(np.float32)}
    write_ply(tmp_path / "in.ply", xyz, rgb, extra=extra)
    reg, transforms = res.results.registration, res.results.transforms
    source = open_cloud(tmp_path / "in.ply")
    grid = LasGrid.around(reg.points.min(axis=0), reg.points.max(axis=0))
    export_cloud(source, registration_mover(reg, transforms, source.normals), "EPSG:32617", grid,
                 laz=tmp_path / "out.laz", ply=tmp_path / "out.ply", chunk_points=50_000)
    out_xyz, values, names = _ply(tmp_path / "out.ply")
    assert names == ("red", "green", "blue", "nx", "ny", "nz", "segment")
    assert np.array_equal(out_xyz, reg.points)
    turned = np.column_stack([values["nx"], values["ny"], values["nz"]]).astype(np.float64)
    assert np.allclose(np.linalg.norm(turned, axis=1), 1, atol=1e-5)
    own = np.einsum("nab,nb->na", np.asarray(transforms.T)[reg.point_segment, :3, :3], normals)
    angle = np.degrees(np.arccos(np.clip((own * turned).sum(axis=1), -1, 1)))
    # the blend mixes the carrier's rotation with its neighbours': close to the carrier's, never equal
    assert np.median(angle) < 1.0 and angle.max() < 10.0, (np.median(angle), angle.max())
    las = laspy.read(tmp_path / "out.laz")
    assert np.array_equal(np.asarray(las.nx), values["nx"])
