"""Runs of the dsm recipe on the tiny synthetic scene, once per test process, shared by
test_outputs_laz.py and test_apply.py: as given (PLY cloud) and with the cloud as a LAZ that has
intensity, RGB, classification and an extra dimension."""

from __future__ import annotations

import atexit
import functools
import shutil
import tempfile
from pathlib import Path

import numpy as np

from tests.conftest import REPO, synthetic_scene

RECIPE = REPO / "recipes" / "dsm.yaml"
LAZ_SCALE_M = 0.0001


@functools.lru_cache(maxsize=1)
def workdir() -> Path:
    path = Path(tempfile.mkdtemp(prefix="crossview-registered-"))
    atexit.register(shutil.rmtree, path, True)
    return path


@functools.lru_cache(maxsize=None)
def tiny_run(kind: str = "ply"):
    """(RunResult, scene folder) of recipes/dsm.yaml on tiny; kind "laz": the cloud as LAZ."""
    from toolkit.runner import run_recipe

    scene = synthetic_scene("tiny") if kind == "ply" else laz_scene()
    return run_recipe(RECIPE, scene=scene, out=workdir() / f"run-{kind}", rerun=False), scene


def tiny_cloud() -> tuple[np.ndarray, np.ndarray]:
    from toolkit.io.cloud import read_points

    return read_points(synthetic_scene("tiny") / "street/cloud.ply", with_colors=True)


def input_attributes(n: int) -> dict[str, np.ndarray]:
    """Deterministic intensity, classification and an extra dimension for the LAZ input."""
    rng = np.random.default_rng(5)
    return {"intensity": rng.integers(0, 65535, n, dtype=np.uint16),
            "classification": rng.integers(0, 31, n, dtype=np.uint8),
            "reflectance": rng.normal(size=n).astype(np.float32)}


def write_laz(path: Path, xyz: np.ndarray, rgb: np.ndarray, point_format: int = 3) -> dict[str, np.ndarray]:
    """The tiny cloud as LAZ (0.1 mm steps) with 16-bit RGB, intensity, classification, reflectance."""
    import laspy

    extra = input_attributes(len(xyz))
    header = laspy.LasHeader(point_format=point_format, version="1.2")
    header.add_extra_dim(laspy.ExtraBytesParams("reflectance", np.float32))
    header.offsets = np.floor(xyz.min(axis=0))
    header.scales = np.full(3, LAZ_SCALE_M)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.red, las.green, las.blue = (rgb.astype(np.uint16) * 257).T
    las.intensity, las.classification, las.reflectance = extra["intensity"], extra["classification"], extra["reflectance"]
    las.write(path)
    return extra


@functools.lru_cache(maxsize=1)
def laz_scene() -> Path:
    """The tiny scene with its street cloud as LAZ (everything else linked)."""
    import yaml

    src = synthetic_scene("tiny")
    root = workdir() / "tiny-laz"
    (root / "street").mkdir(parents=True)
    for name in ("overview", "truth"):
        (root / name).symlink_to(src / name)
    for name in ("sparse", "gps.csv"):
        (root / "street" / name).symlink_to(src / "street" / name)
    xyz, rgb = tiny_cloud()
    write_laz(root / "street/cloud.laz", xyz, rgb)
    manifest = yaml.safe_load((src / "scene.yaml").read_text())
    manifest["street"]["cloud"] = "street/cloud.laz"
    manifest.pop("synth", None)
    (root / "scene.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return root
