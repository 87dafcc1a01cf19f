"""What ``evaluate.chamfer`` computes from the registered points alone: the reference cloud, the
paper's mutual-NN Chamfer metric (3D and 2D) and the per-point errors against the truth.

These need no cameras, so the runner computes them beside the adjust step (the stage's prefetch).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.errors import SceneError
from toolkit.io.attributes import CHUNK_POINTS
from toolkit.evaluation import metrics as M
from toolkit.scene import load_array, load_cloud, need
from toolkit.threads import thread_budget
from toolkit.types import Registration, Scene

REFERENCE_KEYS = ("truth_lidar", "overview_cloud")


@dataclass(frozen=True)
class ChamferConfig:
    """The Chamfer metric's settings (the stage's Params of the same names)."""

    reference: str = "auto"
    cutoff_m: float = 10.0
    max_points: int = 1_000_000
    seed: int = 0
    hist_bin_m: float = 0.1


@dataclass(frozen=True)
class Reference:
    """The reference cloud: its source (a scene key, the path as given, or None: none) and file."""

    source: str | None
    path: Path | None


@dataclass(frozen=True)
class PointErrors:
    """3D and horizontal error of every street point with truth (truth/street_points.npy)."""

    error_3d: np.ndarray
    horizontal: np.ndarray
    rows: np.ndarray | None = None  # the input rows they belong to (None: every row, in order)


@dataclass(frozen=True)
class PointMetrics:
    """What needs only the registered points: metrics.json's street, reference and chamfer entries,
    the notes made on the way, and the errors vs truth (None: no truth points)."""

    values: dict[str, Any]
    notes: list[str]
    errors: PointErrors | None


def find_reference(scene: Scene, reference: str, notes: list[str]) -> Reference:
    """The reference cloud ``reference`` names ('auto': the first of REFERENCE_KEYS the scene has)."""
    if reference == "auto":
        for key in REFERENCE_KEYS:
            if scene.has(key):
                return Reference(key, getattr(scene.files, key))
        notes.append("no reference cloud (scene has neither truth.lidar nor overview.cloud): Chamfer skipped")
        return Reference(None, None)
    if reference in REFERENCE_KEYS:
        if not scene.has(reference):
            raise SceneError(f"evaluate.chamfer: reference {reference!r} is not named by "
                             f"{scene.root / 'scene.yaml'}")
        return Reference(reference, getattr(scene.files, reference))
    path = Path(reference).expanduser()
    if not path.is_absolute() and not path.exists():
        path = scene.root / path
    if not path.is_file():
        raise SceneError(f"{reference}: reference cloud for evaluate.chamfer not found")
    return Reference(reference, path.resolve())


def read_reference(scene: Scene, ref: Reference) -> np.ndarray:
    if ref.source in REFERENCE_KEYS:
        return load_cloud(scene, ref.source, who="evaluate.chamfer")
    from toolkit.io.cloud import read_points

    return read_points(ref.path)


def truth_errors(registration: Registration, scene: Scene) -> PointErrors | None:
    """The error of every registered point with truth vs truth/street_points.npy (None: no truth).

    The truth may hold only some rows (``truth.street_rows``); a run that analysed every k-th point of
    a large cloud (``Registration.rows``) has those rows moved by its warp a chunk at a time."""
    if not scene.has("truth_street_points"):
        return None
    if registration.rows is not None:  # the truth rows read, moved and compared a chunk at a time
        from toolkit.stream import NpyRows, active_client, row_errors

        path = need(scene, "truth_street_points", "truth_street_points")
        try:
            true_pts = NpyRows.open(path)
        except Exception as exc:
            raise SceneError(f"{path}: cannot read .npy ({exc})") from exc
        rows = truth_rows(scene, len(true_pts))
        wanted = np.arange(len(true_pts)) if rows is None else rows
        errors = row_errors(scene.files.street_cloud, wanted, true_pts, registration.warp, CHUNK_POINTS,
                            active_client())
        return PointErrors(*errors, rows=wanted)
    true_pts = load_array(scene, "truth_street_points")
    rows = truth_rows(scene, len(true_pts))
    pts = registration.points if rows is None else np.asarray(registration.points)[rows]
    if true_pts.shape != pts.shape:
        raise SceneError(f"{scene.files.truth_street_points}: shape {true_pts.shape} does not match "
                         f"the {pts.shape} registered street points")
    return PointErrors(*M.point_errors(pts, true_pts), rows=rows)


def truth_rows(scene: Scene, count: int) -> np.ndarray | None:
    """truth.street_rows (sorted, as many as the truth arrays), or None (the truth holds every row)."""
    if not scene.has("truth_street_rows"):
        return None
    rows = np.asarray(load_array(scene, "truth_street_rows"), np.int64)
    if rows.shape != (count,) or (len(rows) > 1 and np.any(np.diff(rows) <= 0)):
        raise SceneError(f"{scene.files.truth_street_rows}: expected {count} increasing row numbers, "
                         f"got shape {rows.shape}")
    return rows


def chamfer_summary(a: np.ndarray, b: np.ndarray, dims: str, cfg: ChamferConfig) -> dict[str, Any]:
    """metrics.json's chamfer entry for ``dims`` '3d' or '2d' (both clouds projected on (x, y))."""
    cols = slice(None) if dims == "3d" else slice(0, 2)
    return M.mutual_nn_chamfer(a[:, cols], b[:, cols], cfg.cutoff_m).summary(cfg.hist_bin_m, cfg.cutoff_m)


def point_metrics(registration: Registration, scene: Scene, cfg: ChamferConfig) -> PointMetrics:
    """The street, reference and chamfer entries and the per-point errors."""
    notes: list[str] = []
    pts = np.asarray(registration.points, np.float64)
    values: dict[str, Any] = {}
    ref = find_reference(scene, cfg.reference, notes)
    street_idx = M.subsample(pts, cfg.max_points, cfg.seed)
    values["street"] = {"n_points": len(pts), "n_used": len(street_idx)}
    pair: tuple[np.ndarray, np.ndarray] | None = None
    if ref.path is None:
        values["reference"] = {"source": None, "path": None, "n_points": 0, "n_used": 0}
    else:
        cloud = read_reference(scene, ref)
        ref_idx = M.subsample(cloud, cfg.max_points, cfg.seed + 1)
        values["reference"] = {"source": ref.source, "path": str(ref.path), "n_points": len(cloud),
                               "n_used": len(ref_idx)}
        pair = (pts[street_idx], cloud[ref_idx])
    dims = ("3d", "2d") if pair is not None else ()
    # with two threads the 3D and 2D metrics run beside the per-point errors (independent
    # computations: the same values either way)
    with ThreadPoolExecutor(2) if dims and thread_budget() >= 2 else nullcontext() as pool:
        pending = {d: pool.submit(chamfer_summary, *pair, d, cfg) for d in dims} if pool is not None else {}
        errors = truth_errors(registration, scene)
        chamfer = {d: pending[d].result() if pending else chamfer_summary(*pair, d, cfg) for d in dims}
    values["chamfer"] = chamfer if pair is not None else None
    return PointMetrics(values, notes, errors)
