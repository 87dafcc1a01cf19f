"""The street frame's scale: street-frame units per metre (a monocular SfM model has no metric scale).

``street_scale`` in scene.yaml or in a recipe (the recipe wins) is ``auto`` (the default) or a
number in [0.05, 20] (1.0: the frame is metric). ``auto`` estimates it from ``street/gps.csv`` when
the scene has one and its fixes match the COLMAP images: the median, over pairs of fixes 50-500 m
apart, of the camera-centre distance over the fix distance (robust to wrong fixes; the route's mean
scale drift is part of it); an estimate within 2 % of 1 is taken as metric (1), since a route's
scale drift alone moves it that much and the per-segment scale (refine) takes it up. Without GPS, ``auto`` assumes 1 and says so in metrics.json. The
pipeline reads the street cloud and the COLMAP model divided by the scale, so every stage works in
metres; the stored warp takes input-frame points (``crossview apply``).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.capture import StreetCapture
from toolkit.errors import SceneError
from toolkit.types import Scene, StreetScale

SCALE_RANGE = (0.05, 20.0)
METRIC_TOLERANCE = 0.02   # a GPS estimate this close to 1 is taken as metric (within the scale drift)
PAIR_RANGE_M = (50.0, 500.0)
MIN_PAIRS = 20


def parse_street_scale(value: Any, where: str) -> float | None:
    """None for ``auto`` (or absent), else the number; a SceneError naming ``where`` otherwise."""
    if value is None or value == "auto":
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SceneError(f"{where}: street_scale must be 'auto' or a number, got {value!r}")
    lo, hi = SCALE_RANGE
    if not lo <= float(value) <= hi:
        raise SceneError(f"{where}: street_scale {value} is outside [{lo:g}, {hi:g}]")
    return float(value)


def resolve_street_scale(scene: Scene, recipe_value: Any = None, recipe_path: Path | None = None) -> Scene:
    """The scene with its street scale set: the recipe's, else the scene's, else estimated."""
    given = parse_street_scale(recipe_value, str(recipe_path or "recipe"))
    source = "recipe"
    if given is None:
        given = parse_street_scale(scene.manifest.get("street_scale"), str(scene.root / "scene.yaml"))
        source = "scene"
    if given is not None:
        return replace(scene, street_scale=StreetScale(given, source))
    found = scale_from_gps(scene) if scene.has("gps") and scene.has("sparse") else None
    return replace(scene, street_scale=found or StreetScale(1.0, "assumed"))


def scale_from_gps(scene: Scene) -> StreetScale | None:
    """The median ratio of camera-centre to fix distances over fix pairs 50-500 m apart (None: < 20 pairs)."""
    from pyproj import Transformer

    from toolkit.io.gps import match_images, read_gps_csv
    from toolkit.scene import read_sparse_raw

    fixes = read_gps_csv(scene.files.gps)
    model = read_sparse_raw(scene)
    image = match_images(list(fixes.names), model.image_names)
    hit = np.flatnonzero(image >= 0)
    if len(hit) < 3:
        return None
    east, north = Transformer.from_crs("EPSG:4326", scene.crs, always_xy=True).transform(
        fixes.lonlat[hit, 0], fixes.lonlat[hit, 1])
    world = np.column_stack([east, north])
    cams = model.centres[image[hit]]
    # pairs along the capture order, at every offset whose fixes are 50-500 m apart
    ratios, count = [], 0
    for step in range(1, len(hit)):
        d_fix = np.linalg.norm(world[step:] - world[:-step], axis=1)
        use = (d_fix >= PAIR_RANGE_M[0]) & (d_fix <= PAIR_RANGE_M[1])
        if not use.any():
            continue
        d_cam = np.linalg.norm(cams[step:] - cams[:-step], axis=1)
        ratios.append(d_cam[use] / d_fix[use])
        count += len(ratios[-1])
        if count > 200_000:
            break
    r = np.concatenate(ratios) if ratios else np.zeros(0)
    if len(r) < MIN_PAIRS:
        return None
    value = float(np.median(r))
    lo, hi = SCALE_RANGE
    if not lo <= value <= hi:
        raise SceneError(f"{scene.files.gps}: the street frame's scale estimated from GPS ({value:.4g}) is outside "
                         f"[{lo:g}, {hi:g}]: check the fixes, or set street_scale")
    if abs(value - 1.0) <= METRIC_TOLERANCE:
        return StreetScale(1.0, "gps", len(r), estimate=value)
    return StreetScale(value, "gps", len(r), estimate=value)


def camera_height(street, capture: StreetCapture) -> float | None:
    """Median height of the cameras above the ground of the street segment nearest to each (levelled
    street frame, in the frame's units as loaded); None without cameras or ground heights."""
    from scipy.spatial import cKDTree

    ground = np.asarray(street.ground_z, np.float64)
    known = np.isfinite(ground)
    centres = capture.require_sparse("the street scale check").centres
    if not known.any() or len(centres) == 0:
        return None
    cams = street.level(centres)
    _, nn = cKDTree(np.asarray(street.centroids, np.float64)[known]).query(cams[:, :2])
    return float(np.median(cams[:, 2] - ground[known][nn]))


def check_assumed_scale(street, capture: StreetCapture, lo_m: float = 0.8, hi_m: float = 6.0) -> None:
    """With the scale assumed (no GPS, none given): a SceneError when the cameras sit implausibly
    high or low above the street ground (``camera_height``): the frame is then not metric, and
    matching it would fail slowly (campus at 10x: over 10 minutes in the data term)."""
    if capture.scale.source != "assumed" or capture.sparse_path is None or street is None or len(street) == 0:
        return
    height = camera_height(street, capture)
    if height is not None and not lo_m <= height <= hi_m:
        raise SceneError(f"{capture.sparse_path}: the cameras sit {height:.2f} frame units above the street "
                         f"ground ({lo_m:g}-{hi_m:g} m expected of a street capture): the street frame is not "
                         f"metric; set street_scale (frame units per metre) or give street/gps.csv")
