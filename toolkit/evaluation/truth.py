"""Ground-truth comparisons: true camera poses, true building footprints and segment matches.

Read only by ``evaluate.*`` stages (and the rigid oracle baseline): the pipeline never sees truth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import SceneError
from toolkit.evaluation.metrics import error_stats
from toolkit.types import Grid, Matches, OverviewSegments, StreetSegments


@dataclass(frozen=True)
class TruePoses:
    """World-to-camera poses from a lone COLMAP images.txt. names: (C,); R: (C,3,3); t: (C,3)."""

    names: tuple[str, ...]
    R: np.ndarray
    t: np.ndarray

    @property
    def centres(self) -> np.ndarray:
        return -np.einsum("cji,cj->ci", self.R, self.t)


def read_images_txt(path: str | Path) -> TruePoses:
    """Read a lone COLMAP images.txt (no cameras.txt / points3D.txt beside it needed).

    Pose lines and observation lines alternate; the last image's empty observation line is often
    missing (stripped as trailing whitespace), so an odd count is padded rather than rejected.
    """
    from toolkit.io.colmap import qvec_to_rotmat

    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    with open(path) as fh:
        lines = [ln.rstrip("\n") for ln in fh if not ln.startswith("#")]
    while lines and not lines[-1].strip():
        lines.pop()
    if len(lines) % 2:
        lines.append("")
    names, qs, ts = [], [], []
    for ln in lines[0::2]:
        w = ln.split()
        try:
            qs.append([float(v) for v in w[1:5]])
            ts.append([float(v) for v in w[5:8]])
        except ValueError:
            raise SceneError(f"{path}: bad image line {ln[:60]!r}") from None
        if len(w) < 10:
            raise SceneError(f"{path}: bad image line {ln[:60]!r}")
        names.append(" ".join(w[9:]))
    if not names:
        return TruePoses((), np.zeros((0, 3, 3)), np.zeros((0, 3)))
    return TruePoses(tuple(names), qvec_to_rotmat(np.array(qs)), np.array(ts, dtype=np.float64))


def camera_centre_errors(names: tuple[str, ...], R: np.ndarray, t: np.ndarray, truth: TruePoses) -> dict:
    """Error statistics of camera centres matched by image name (3D and horizontal)."""
    index = {n: k for k, n in enumerate(truth.names)}
    pairs = [(k, index[n]) for k, n in enumerate(names) if n in index]
    if not pairs:
        return {"n": 0, "n_missing": len(names), "error_3d": error_stats([]), "horizontal": error_stats([])}
    mine, theirs = np.array(pairs).T
    c_est = -np.einsum("cji,cj->ci", np.asarray(R)[mine], np.asarray(t)[mine])
    c_true = truth.centres[theirs]
    diff = c_est - c_true
    return {"n": len(pairs), "n_missing": len(names) - len(pairs),
            "error_3d": error_stats(np.linalg.norm(diff, axis=1)),
            "horizontal": error_stats(np.linalg.norm(diff[:, :2], axis=1))}


def read_true_buildings(path: str | Path, crs: str) -> tuple[np.ndarray, list]:
    """(ids (B,) int64, shapely geometries in the scene CRS) from an RFC 7946 lon/lat GeoJSON.

    The building id is taken from the feature property ``id`` / ``building_id`` or the feature's
    own ``id``, matching ``truth/street_labels.npy``.
    """
    import json

    import shapely
    from pyproj import Transformer
    from shapely.geometry import shape

    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except Exception as exc:
        raise SceneError(f"{path}: cannot read GeoJSON ({exc})") from exc
    to_scene = Transformer.from_crs("EPSG:4326", crs, always_xy=True)
    ids, geoms = [], []
    for k, feat in enumerate(doc.get("features", [])):
        props = feat.get("properties") or {}
        bid = props.get("id", props.get("building_id", feat.get("id")))
        if bid is None:
            raise SceneError(f"{path}: feature {k} has no building id (properties.id or id)")
        geom = shape(feat["geometry"])
        geom = shapely.transform(geom, lambda xy: np.column_stack(to_scene.transform(xy[:, 0], xy[:, 1])))
        ids.append(int(bid))
        geoms.append(geom)
    return np.asarray(ids, dtype=np.int64), geoms


def rasterise_buildings(ids: np.ndarray, geoms: list, grid: Grid) -> np.ndarray:
    """(H,W) int32 index into ``ids`` (or -1) of the building covering each pixel centre."""
    from rasterio.features import rasterize
    from rasterio.transform import Affine

    if len(geoms) == 0:
        return np.full((grid.height, grid.width), -1, np.int32)
    shapes = ((g, k + 1) for k, g in enumerate(geoms) if not g.is_empty)
    img = rasterize(shapes, out_shape=(grid.height, grid.width), transform=Affine(*grid.transform),
                    fill=0, dtype="int32")
    img -= 1  # in place: the district's grid is 0.2 GB
    return img


def overlap_pixels(label_image: np.ndarray, n_segments: int, building_index: np.ndarray,
                   n_buildings: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(n_segments, n_buildings) shared pixel counts, segment areas, building areas (pixels).

    Counted ``block`` pixels at a time: the district's 49 M-pixel grid as int64 pairs took 1.2 GB."""
    labels, index = label_image.ravel(), building_index.ravel()
    inter = np.zeros(n_segments * n_buildings, np.int64)
    seg_area, bld_area = np.zeros(n_segments, np.int64), np.zeros(n_buildings, np.int64)
    block = 1 << 22
    for s in range(0, len(labels), block):
        seg = labels[s:s + block].astype(np.int64)
        bld = index[s:s + block].astype(np.int64)
        both = (seg >= 0) & (bld >= 0)
        inter += np.bincount(seg[both] * n_buildings + bld[both], minlength=n_segments * n_buildings)
        seg_area += np.bincount(seg[seg >= 0], minlength=n_segments)[:n_segments]
        bld_area += np.bincount(bld[bld >= 0], minlength=n_buildings)[:n_buildings]
    return inter.reshape(n_segments, n_buildings).astype(float), seg_area.astype(float), bld_area.astype(float)


def overview_to_building(label_image: np.ndarray, n_segments: int, building_index: np.ndarray,
                         n_buildings: int, min_iou: float = 0.5,
                         overlap: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Per over-view segment: index of the true building with maximal IoU (−1 when < min_iou), and that IoU.

    ``overlap``: ``overlap_pixels`` of the same arguments, when the caller already has it.
    """
    if n_segments == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    if n_buildings == 0:
        return np.full(n_segments, -1, np.int64), np.zeros(n_segments)
    if overlap is None:
        overlap = overlap_pixels(label_image, n_segments, building_index, n_buildings)
    inter, seg_area, bld_area = overlap
    union = seg_area[:, None] + bld_area[None, :] - inter
    iou = np.divide(inter, union, out=np.zeros_like(inter), where=union > 0)
    best = iou.argmax(axis=1)
    best_iou = iou[np.arange(n_segments), best]
    return np.where(best_iou >= min_iou, best, -1), best_iou


def street_to_building(point_labels: np.ndarray, true_labels: np.ndarray, n_segments: int) -> np.ndarray:
    """Per street segment: the true building id held by most of its points (−1 if that is ground/clutter).

    Ties go to the smallest id.
    """
    if n_segments == 0:
        return np.zeros(0, np.int64)
    sel = point_labels >= 0
    seg = point_labels[sel].astype(np.int64)
    lab = true_labels[sel].astype(np.int64)
    if len(lab) == 0:
        return np.full(n_segments, -1, np.int64)
    low, high = int(lab.min()), int(lab.max())
    if n_segments * (high - low + 1) <= max(len(lab), 1 << 16):
        # A count table no larger than the points is cheaper than np.unique's sort. One column per id
        # in [low, high]: absent ids are zero columns, which never win a non-empty row's argmax.
        values, code = np.arange(low, high + 1, dtype=np.int64), lab - low
    else:
        values, code = np.unique(lab, return_inverse=True)
    counts = np.bincount(seg * len(values) + code.ravel(), minlength=n_segments * len(values))
    counts = counts.reshape(n_segments, len(values))
    winner = values[counts.argmax(axis=1)]
    empty = counts.sum(axis=1) == 0
    return np.where(empty | (winner < 0), -1, winner).astype(np.int64)


def segment_match_scores(matches: Matches, street: StreetSegments, overview: OverviewSegments,
                         true_labels: np.ndarray, building_ids: np.ndarray, building_geoms: list,
                         min_cover: float = 0.5) -> dict:
    """Precision / recall of street → over-view segment matches against the true buildings.

    A street segment stands for its majority building B (over its points' true labels). Its match to
    over-view segment O is correct when O covers at least ``min_cover`` of B's footprint: an
    over-view segment that merges B with its neighbours (an OSM outline drawn around a whole block,
    a DSM mask of a terraced row) is B's counterpart, and registering B's façades on its outline is
    right. precision = correct / matched; recall = correct / street segments whose building some
    over-view segment covers. ``precision_iou`` / ``recall_iou`` keep the stricter one-to-one rule
    (O's best-IoU building, IoU ≥ 0.5, must be B), which calls every match to a merged segment wrong
    but one.
    """
    S = len(street)
    if len(true_labels) != len(street.point_labels):
        raise SceneError(f"truth/street_labels.npy has {len(true_labels)} labels for "
                         f"{len(street.point_labels)} street points")
    building_ids = np.asarray(building_ids, np.int64)
    B, n_o = len(building_ids), len(overview)
    building_index = rasterise_buildings(building_ids, building_geoms, overview.grid)
    st_bid = street_to_building(street.point_labels, true_labels, S)
    index_of = {int(b): k for k, b in enumerate(building_ids)}
    st_b = np.array([index_of.get(int(b), -1) for b in st_bid], np.int64)  # one per street segment
    match = np.asarray(matches.segment_match, np.int64)
    matched = match >= 0

    overlap = overlap_pixels(overview.label_image, n_o, building_index, B) if n_o and B else None
    if overlap is not None:
        inter, _, bld_area = overlap
        covers = inter >= min_cover * np.maximum(bld_area, 1)[None, :]          # (n_o, B)
    else:
        covers = np.zeros((n_o, B), bool)
    known = st_b >= 0
    correct = matched & known
    correct[correct] = covers[match[correct], st_b[correct]]
    has_counterpart = known.copy()
    has_counterpart[known] = covers[:, st_b[known]].any(axis=0) if n_o else False

    ov_b, _ = overview_to_building(overview.label_image, n_o, building_index, B, overlap=overlap)
    ov_bid = np.where(ov_b >= 0, building_ids[np.maximum(ov_b, 0)], -1) if B else np.full(n_o, -1)
    target = np.where(matched, ov_bid[np.maximum(match, 0)] if n_o else -1, -1)
    correct_iou = matched & (st_bid >= 0) & (target == st_bid)
    cp_iou = (st_bid >= 0) & np.isin(st_bid, ov_bid[ov_bid >= 0])

    n_matched, n_cp, n_cp_iou = int(matched.sum()), int(has_counterpart.sum()), int(cp_iou.sum())
    return {
        "precision": int(correct.sum()) / n_matched if n_matched else None,
        "recall": int(correct.sum()) / n_cp if n_cp else None,
        "precision_iou": int(correct_iou.sum()) / n_matched if n_matched else None,
        "recall_iou": int(correct_iou.sum()) / n_cp_iou if n_cp_iou else None,
        "n_street_segments": S, "n_matched": n_matched, "n_correct": int(correct.sum()),
        "n_with_counterpart": n_cp, "n_overview_segments": n_o,
        "n_overview_with_building": int((ov_b >= 0).sum()),
        "_per_segment": {"true_building": st_bid, "matched_building": target, "correct": correct,
                         "has_counterpart": has_counterpart},
    }
