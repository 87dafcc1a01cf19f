"""Shared fixtures: a minimal hand-made scene folder, paths to ../shared and to the synthetic scenes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
RAW = SHARED / "data" / "raw"


def needs_shared(sub: str = "") -> pytest.MarkDecorator:
    p = RAW / sub
    return pytest.mark.skipif(not p.exists(), reason=f"real data not present: {p} (../shared is only in CI)")


@pytest.fixture
def mini_scene(tmp_path: Path) -> Path:
    """A scene with a 40×40 DSM (one 10 m high block), a street cloud and a 2-image COLMAP model."""
    from toolkit.io.cloud import write_ply
    from toolkit.io.colmap import write_model
    from toolkit.io.raster import write_geotiff
    from toolkit.scene import write_manifest
    from toolkit.types import Camera, Grid, SparseModel

    root = tmp_path / "scene"
    (root / "overview").mkdir(parents=True)
    (root / "street").mkdir()
    grid = Grid((0.5, 0.0, 500000.0, 0.0, -0.5, 4400020.0), 40, 40, "EPSG:32617")
    dsm = np.full((40, 40), 200.0, np.float32)
    dsm[10:30, 10:30] += 10
    write_geotiff(root / "overview/dsm.tif", dsm, grid, nodata=-9999.0)
    rng = np.random.default_rng(0)
    write_ply(root / "street/cloud.ply", rng.normal(size=(500, 3)) * 5 + 1e5)
    cam = Camera(1, "PINHOLE", 640, 480, np.array([500.0, 500.0, 320.0, 240.0]))
    model = SparseModel(
        cameras={1: cam}, image_names=("a.jpg", "b.jpg"), image_ids=np.array([1, 2]),
        camera_ids=np.array([1, 1]), R=np.stack([np.eye(3)] * 2), t=np.array([[0, 0, 0], [1.0, 0, 0]]),
        points3d_ids=np.array([7]), points3d=np.array([[0.0, 0.0, 5.0]]),
        points3d_rgb=np.array([[1, 2, 3]], np.uint8),
        observations=np.array([[0, 0, 320.0, 240.0], [1, 0, 420.0, 240.0]]),
    )
    write_model(model, root / "street/sparse")
    # metric by declaration: its two cameras are no street capture for the assumed-scale check
    write_manifest(root, "mini", "EPSG:32617", {
        "overview": {"dsm": "overview/dsm.tif"},
        "street": {"cloud": "street/cloud.ply", "sparse": "street/sparse"},
    }, extra={"street_scale": 1.0})
    return root


def synthetic_scene(name: str) -> Path:
    """A synthetic scene generated once per session under data/ (tiny is fast)."""
    import fcntl

    root = REPO / "data" / f"test-{name}"
    root.parent.mkdir(exist_ok=True)
    # several pytest processes (developers, helpers) may ask at once: generate under a lock
    with open(root.parent / f".test-{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not (root / "scene.yaml").is_file():
            from toolkit.synth.generate import generate

            generate(name, 0, root)
    return root
