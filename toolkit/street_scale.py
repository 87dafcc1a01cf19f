"""The street frame's scale: street-frame units per metre (a monocular SfM model has no metric scale).

``street_scale`` in scene.yaml or in a recipe (the recipe wins) is ``auto`` (the default) or a
number in [0.05, 20] (1.0: the frame is metric). ``auto``:

- with ``street/gps.csv`` (fixes matching the COLMAP images): the median, over pairs of fixes
  50-500 m apart, of the camera-centre distance over the fix distance (``scale_from_gps``), as the
  first guess the matching then checks as without GPS: fixes a few metres off bias that median by
  several per cent, the façades against the outlines do not. A matching estimate more than
  GPS_REACH from the GPS one is not taken. A fixes' estimate within KEEP_BAND (5 %) of 1 is taken
  as metric without the check, as a matching estimate is without GPS;
- without GPS, with street/sparse: from the matching (``first_guess``, ``scale_from_matching``). The
  street step first runs at 1 when the cameras sit 1-4 frame units above the COLMAP points under
  them, else at the scale that puts them 2 m up; then the route's façades are placed on the
  over-view outlines at every scale that puts the cameras 1-4 m above the street ground
  (``toolkit.matching.route_scale``), and the steps run again from the street step when the best
  one is another scale (at most MAX_PASSES street passes);
- otherwise 1 (``assumed``).

An estimate within 2 % of 1 is taken as metric (1): a route's scale drift alone moves it that much,
and the per-segment scale (refine) takes it up. A matching estimate within 5 % (KEEP_BAND) of the
scale the street step ran at keeps that scale: the per-segment scale reaches that far. The pipeline reads the street cloud and the COLMAP model divided by the scale, so every
stage works in metres; the stored warp takes input-frame points (``crossview apply``).
See docs/scale_and_heights.md.
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
METRIC_TOLERANCE = 0.02   # a matching estimate this close to 1 is taken as metric; the band a GPS first guess is checked in
PAIR_RANGE_M = (50.0, 500.0)
MIN_PAIRS = 20
# Without GPS: the heights a street capture's cameras are searched at above the street ground
# (handheld ~1.5 m, car roof ~2.3 m, a mast ~3.5 m), and the one a first guess puts them at.
CAMERA_HEIGHT_M = (1.0, 4.0)
NOMINAL_CAMERA_HEIGHT_M = 2.0
UNDER_POINTS = 30     # COLMAP points nearest each camera horizontally, for its height
MAX_PASSES = 3        # street passes the matching may ask for
# the matching's estimate replaces the scale the street step ran at only beyond the per-segment
# scale's reach (refine.exhaustive scale.max_deviation): within it, refine measures the scale better
KEEP_BAND = 0.05
RESCAN_REACH = 0.1    # a later pass scans the factors within 1 ± this of its scale
GPS_REACH = 0.15      # a matching estimate this far (relative) from the GPS estimate is not taken


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
    if found is None and scene.has("sparse"):
        found = first_guess(scene)
    return replace(scene, street_scale=found or StreetScale(1.0, "assumed"))


def sparse_camera_height(model) -> float | None:
    """Median height of the cameras above the COLMAP points under them, in the model's own units
    (scale-free: 'up' is the cameras' mean image-up axis, 'under' the points nearest each camera
    horizontally); None without points."""
    from scipy.spatial import cKDTree

    if len(model.points3d) < MIN_PAIRS or len(model.R) == 0:
        return None
    up = -np.asarray(model.R, np.float64)[:, 1, :].mean(axis=0)  # COLMAP's image y points down
    up /= np.linalg.norm(up)
    a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    plane = np.stack([a, np.cross(up, a)], axis=1)
    pts, cams = np.asarray(model.points3d, np.float64), model.centres
    _, nn = cKDTree(pts @ plane).query(cams @ plane, k=min(UNDER_POINTS, len(pts)))
    below = (cams @ up)[:, None] - (pts @ up)[nn]
    per_camera = np.nanmedian(np.where(below > 0, below, np.nan), axis=1)
    per_camera = per_camera[np.isfinite(per_camera)]
    return float(np.median(per_camera)) if len(per_camera) else None


def first_guess(scene: Scene) -> StreetScale | None:
    """Without GPS: the scale the street step first runs at, settled later by the matching
    (``scale_from_matching``): 1 when the cameras sit at a street capture's height at 1, else the
    one that puts them at NOMINAL_CAMERA_HEIGHT_M. None without points in the COLMAP model."""
    from toolkit.scene import read_sparse_raw

    h = sparse_camera_height(read_sparse_raw(scene))
    if h is None:
        return None
    lo, hi = CAMERA_HEIGHT_M
    value = 1.0 if lo <= h <= hi else float(np.clip(h / NOMINAL_CAMERA_HEIGHT_M, *SCALE_RANGE))
    return StreetScale(value, "matching", matching={"camera_height_frame": round(h, 6), "first_guess": round(value, 6),
                                                    "passes": 0}, settled=False)


def scale_from_matching(scale: StreetScale, street, overview, capture: StreetCapture, cfg, workers: int = 1,
                        search=None) -> StreetScale:
    """One pass of the scan over street scales (``toolkit.matching.route_scale``) on the street
    segments found at ``scale``: the same value, settled, when the first scan finds no prominent
    peak or the scan's factor is within KEEP_BAND of it (the per-segment scale of refine takes the
    rest up), else the factor's scale, unsettled, for the street step to run again at
    (settled after MAX_PASSES).
    ``cfg``: the route placement's config (the unary stage's)."""
    from toolkit.matching.route_prior import capture_order
    from toolkit.matching.route_scale import ScaleSearchConfig, scan_scale

    search = search or ScaleSearchConfig()
    figures = dict(scale.matching or {})
    passes = int(figures.get("passes", 0)) + 1
    model = capture.require_sparse("the street scale from the matching")
    cams = street.level(model.centres[capture_order(model.image_names)])[:, :2]
    gps = scale.estimate if scale.source == "gps" else None
    if passes == 1:
        h = camera_height(street, capture)
        if h is None or h <= 0:
            return replace(scale, settled=True, matching={**figures, "passes": passes, "reason": "no street ground"})
        lo, hi = CAMERA_HEIGHT_M[0] / h, CAMERA_HEIGHT_M[1] / h   # the factors that put the cameras there
        scan = scan_scale(street, overview, cams, lo, hi, cfg, search, coarse=True, workers=workers)
        if scan.prominence < search.min_prominence:  # no scale stands out: the first guess stays
            figures.update({"passes": passes, "pass_1": {"at": round(scale.value, 6), **scan.figures()},
                            "reason": f"no distinct scale (prominence {scan.prominence:.2f} < {search.min_prominence:g})"})
            return replace(scale, matching=figures, settled=True)
    else:
        r = 1.0 + RESCAN_REACH
        scan = scan_scale(street, overview, cams, 1.0 / r, r, cfg, search, coarse=False, workers=workers)
    estimate = scale.value / scan.factor
    figures.update({"passes": passes, f"pass_{passes}": {"at": round(scale.value, 6), **scan.figures()}})
    if gps is not None and abs(np.log(estimate / gps)) > np.log1p(GPS_REACH):
        figures["reason"] = f"matching scale {estimate:.4g} is more than {GPS_REACH:.0%} from the GPS one"
        return replace(scale, matching=figures, settled=True)
    if gps is not None:
        figures["estimate"] = round(float(estimate), 6)
    # a later pass keeps its own scale when the scan agrees with it (no snap to 1 that would ping-pong)
    value = 1.0 if passes == 1 and abs(estimate - 1.0) <= METRIC_TOLERANCE else estimate
    lo_s, hi_s = SCALE_RANGE
    if not lo_s <= value <= hi_s:
        raise SceneError(f"{capture.sparse_path}: the street frame's scale found by the matching ({value:.4g}) is "
                         f"outside [{lo_s:g}, {hi_s:g}]: set street_scale, or give street/gps.csv")
    kept = replace(scale, matching=figures, settled=True)
    if gps is None:
        kept = replace(kept, estimate=estimate)
    # a GPS first guess is only as good as its fixes: the matching's estimate replaces it beyond 2 %
    band = METRIC_TOLERANCE if gps is not None else KEEP_BAND
    if abs(value / scale.value - 1.0) <= band or passes >= MAX_PASSES:
        return kept
    return replace(kept, value=value, settled=False)


def first_guess_alternative(scale: StreetScale) -> StreetScale | None:
    """The cameras' height first guess as a settled scale, when the façades' scan (no GPS) moved the
    run's scale beyond KEEP_BAND from it; else None. The scan's peak is a hypothesis: a run it
    leaves unreliable is run again at the first guess (``toolkit.runner.execute_assessed``)."""
    guess = (scale.matching or {}).get("first_guess")
    if scale.source != "matching" or guess is None or abs(np.log(scale.value / guess)) <= np.log1p(KEEP_BAND):
        return None
    figures = {**scale.matching, "retried_at_first_guess": True}
    return replace(scale, value=float(guess), matching=figures, settled=True)


def scale_from_gps(scene: Scene) -> StreetScale | None:
    """The median ratio of camera-centre to fix distances over fix pairs 50-500 m apart (None: < 20 pairs)."""
    from toolkit.io.gps import match_images, read_gps_csv
    from toolkit.scene import read_sparse_raw

    fixes = read_gps_csv(scene.files.gps)
    model = read_sparse_raw(scene)
    image = match_images(list(fixes.names), model.image_names)
    hit = np.flatnonzero(image >= 0)
    if len(hit) < 3:
        return None
    world = fixes.scene_xy(scene.crs)[hit]
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
    # within the per-segment scale's reach the frame is taken as metric, as without GPS (KEEP_BAND):
    # refine measures the route's scale better than fixes a few metres off do
    if abs(value - 1.0) <= KEEP_BAND:
        return StreetScale(1.0, "gps", len(r), estimate=value)
    return StreetScale(value, "gps", len(r), estimate=value, matching={"passes": 0}, settled=False)


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
