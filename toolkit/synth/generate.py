"""Orchestration: a world (procedural or real) → a complete scene folder with truth.

``generate(preset, seed, out)`` and ``generate_from_city(path, seed, out)`` return the scene folder.
The folder is written beside ``out`` under a temporary name and renamed when complete.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.errors import CrossviewError
from toolkit.synth.config import PRESETS, SynthConfig, config_for
from toolkit.synth.timing import timed
from toolkit.synth.world import World

__all__ = ["PRESETS", "SynthConfig", "build_scene", "generate", "generate_from_city"]



def generate(preset: str, seed: int, out: Path, **overrides: Any) -> Path:
    """Synthesise the procedural city of ``preset`` with ``seed`` into ``out``."""
    from toolkit.synth.city import procedural_world

    cfg = config_for(preset, **overrides)
    with timed("procedural city"):
        world = procedural_world(cfg, _rng(seed, "city"))
    return build_scene(world, cfg, seed, Path(out), name=f"synth-{preset}-s{seed}", source={"preset": preset})


def generate_from_city(path: Path, seed: int, out: Path, **overrides: Any) -> Path:
    """The same products built on a real city: CityJSON (LoD1/LoD2) or OSM (.osm/.pbf) buildings."""
    from toolkit.synth.realcity import CITY_DEFAULTS, load_city

    cfg = config_for("campus", **{**CITY_DEFAULTS, **overrides})
    with timed("load city"):
        world = load_city(Path(path), cfg, _rng(seed, "city"))
    cfg = cfg.model_copy(update={"crs": world.crs})  # a real city stays in its own CRS
    return build_scene(
        world,
        cfg,
        seed,
        Path(out),
        name=f"synth-{Path(path).name.split('.')[0]}-s{seed}",
        source={"city": str(path)},
    )


_STREAMS = (
    "city", "route", "capture", "drift", "sparse", "gps", "dsm", "ortho", "labels", "footprints", "dem",
    "density",
)


def _rng(seed: int, stream: str) -> np.random.Generator:
    """Independent, named random streams: changing one product's knobs leaves the others alone."""
    return np.random.default_rng([int(seed), _STREAMS.index(stream)])


def _prepare(out: Path) -> Path:
    if out.exists() and any(out.iterdir()) and not (out / "scene.yaml").is_file():
        raise CrossviewError(f"{out}: exists, is not empty and is not a scene folder; choose another --out")
    tmp = out.parent / f".{out.name}.partial"
    if tmp.exists():
        shutil.rmtree(tmp)
    for sub in ("overview", "street", "truth"):
        (tmp / sub).mkdir(parents=True)
    return tmp


# the scene.yaml entries of every generated scene
SCENE_FILES = {
    "overview": {
        "dsm": "overview/dsm.tif",
        "ortho": "overview/ortho.tif",
        "footprints": "overview/footprints.geojson",
        "osm": "overview/map.osm",
        "labels": "overview/labels.tif",
        "cloud": "overview/cloud.ply",
        "dem": "overview/dem.tif",
    },
    "street": {"cloud": "street/cloud.ply", "sparse": "street/sparse", "gps": "street/gps.csv"},
    "truth": {
        "lidar": "truth/lidar.ply",
        "street_points": "truth/street_points.npy",
        "street_labels": "truth/street_labels.npy",
        "buildings": "truth/buildings.geojson",
        "cameras": "truth/cameras.txt",
    },
}


def scene_files(cfg: SynthConfig) -> dict:
    """SCENE_FILES, with street/cloud.laz and truth/street_rows.npy when street_density_factor > 1."""
    if cfg.street_density_factor == 1:
        return SCENE_FILES
    return {
        **SCENE_FILES,
        "street": {**SCENE_FILES["street"], "cloud": "street/cloud.laz"},
        "truth": {**SCENE_FILES["truth"], "street_rows": "truth/street_rows.npy"},
    }


def build_scene(world: World, cfg: SynthConfig, seed: int, out: Path, name: str, source: dict) -> Path:
    from toolkit.scene import write_manifest
    from toolkit.synth import overview_writer, street_writer
    from toolkit.synth.route import make_track, plan_route

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = _prepare(out)
    with timed("route"):
        # a real city that cannot host the asked loop may get an open route instead (plan_route warns)
        centreline, closed = plan_route(world, cfg, _rng(seed, "route"))
        track = make_track(centreline, world.terrain, cfg, _rng(seed, "route"), closed=closed)
    with timed("over-view products"):
        ov = overview_writer.write_overview(
            world, cfg, tmp, {s: _rng(seed, s) for s in ("dsm", "ortho", "labels", "footprints", "dem")}
        )
    with timed("street capture and truth"):
        st = street_writer.write_street(
            world, track, cfg, tmp, ov, {s: _rng(seed, s) for s in ("capture", "drift", "sparse", "gps", "density")}
        )
    stats = _stats(world, track, ov, st)
    write_manifest(
        tmp,
        name,
        cfg.crs,
        scene_files(cfg),
        extra={
            "synth": {
                "generator": "crossview synth",
                "seed": int(seed),
                **source,
                "drift": "truth/drift.npz",
                "stats": stats,
                "config": cfg.model_dump(mode="json"),
            }
        },
    )
    if cfg.preview:
        _write_preview(tmp / "preview.png", world, track, ov, st, name, stats)
    if out.exists():
        shutil.rmtree(out)
    tmp.rename(out)
    return out


def _stats(world: World, track, ov, st) -> dict:
    return {
        "street_points": st.n_points,
        "cameras": len(track),
        "route_length_m": round(float(track.arclength[-1]), 2),
        "route_closed": bool(track.closed),
        "buildings": len(world.buildings),
        "overview_size_px": [ov.grid.width, ov.grid.height],
        "sparse_points": st.n_sparse,
        "observations": st.n_obs,
        **({"street_truth_rows": st.n_truth} if st.n_truth != st.n_points else {}),
    }


def _write_preview(path: Path, world: World, track, ov, st, name: str, stats: dict) -> None:
    from toolkit.synth.preview import draw_preview

    with timed("preview"):
        draw_preview(
            path,
            ov.dsm,
            ov.dsm_nodata,
            ov.grid,
            ov.footprint_geoms,
            track.centres[:, :2] + world.origin,
            st.preview_drifted,
            st.preview_true,
            f"{name}: {stats['street_points']:,} street points, {len(track)} cameras, "
            f"{stats['route_length_m']:.0f} m route, {len(world.buildings)} buildings",
        )
