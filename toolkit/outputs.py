"""Write a run's outputs into its (temporary) folder: cloud, transforms, model, metrics, report, logs."""

from __future__ import annotations

import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.metrics_model import RunMetrics
from toolkit.refine.transforms import scale_of
from toolkit.types import RunOutputs


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating, float)):
        f = float(value)
        return f if np.isfinite(f) else None
    if isinstance(value, (np.bool_,)):
        return bool(value)
    return value


def dump_json(path: Path, value: Any) -> None:
    path.write_text(json.dumps(_jsonable(value), indent=2, sort_keys=False) + "\n")


def transforms_table(outputs: RunOutputs) -> list[dict[str, Any]]:
    """One row per street segment: match, 4×4 transform, cost, confidence, validity."""
    street, overview = outputs.street, outputs.overview
    matches, transforms = outputs.matches, outputs.transforms
    if street is None or (matches is None and transforms is None):
        return []
    rows = []
    for i, sid in enumerate(street.ids):
        row: dict[str, Any] = {"segment": int(sid)}
        if matches is not None:
            m = int(matches.segment_match[i])
            row["overview_segment"] = int(overview.ids[m]) if (m >= 0 and overview is not None) else None
            row["match_cost"] = float(matches.cost[i])
            row["match_confidence"] = float(matches.confidence[i])
        if transforms is not None:
            row["transform"] = transforms.T[i]
            row["valid"] = bool(transforms.valid[i])
            row["cost"] = float(transforms.cost[i])
            row["confidence"] = float(transforms.confidence[i])
        rows.append(row)
    return rows


PARTIAL_SHARE = 0.7  # below this share of registered street segments a run is called partial


def coverage(outputs: RunOutputs) -> dict[str, Any] | None:
    """How much of the street cloud was registered by its own segment's transform (no truth needed)."""
    street, matches, transforms = outputs.street, outputs.matches, outputs.transforms
    if street is None or (matches is None and transforms is None):
        return None
    n = len(street)
    matched = int((matches.segment_match >= 0).sum()) if matches is not None else None
    valid = np.asarray(transforms.valid, bool) if transforms is not None else matches.segment_match >= 0
    carrier = np.asarray(street.carrier)
    on_valid = valid[carrier[carrier >= 0]].sum() if n else 0
    return {
        "n_street_segments": n, "n_matched": matched, "n_registered": int(valid.sum()),
        "registered_share": float(valid.mean()) if n else 0.0,
        "points_on_registered_segments_share": float(on_valid / max(len(carrier), 1)),
        "points_without_carrier_share": float((carrier < 0).mean()) if len(carrier) else 0.0,
    }


def write_outputs(out: Path, plan, outputs: RunOutputs, timings: dict[str, float],
                  warnings: list[str], assessment=None, notes: list[str] = (), progress=None, tries=()) -> None:
    """``assessment``: the run's ``toolkit.status.Assessment`` (assessed here when None); ``notes``:
    what the readers noted (e.g. a raster resampled onto the scene grid); ``progress``: an observer's
    ``progress``, shown while a large cloud is written a chunk at a time; ``tries``: every registration
    of a run that ran again at another street scale (``toolkit.runner.Try``), written when there are several."""
    from toolkit.status import assess

    if assessment is None:
        assessment = assess(outputs)

    cov = coverage(outputs)
    if cov is not None and cov["n_street_segments"] and cov["registered_share"] < PARTIAL_SHARE:
        warnings.append(
            f"partial registration: only {cov['n_registered']} of {cov['n_street_segments']} street segments "
            f"({100 * cov['points_on_registered_segments_share']:.0f} % of the points) were registered by their "
            "own transform; " + ("the other points are carried by the blended transforms of registered neighbours"
                                 if outputs.registration is not None else "no registered cloud was written"))

    if outputs.registration is not None:
        from toolkit.export import write_registered

        import time

        t0 = time.perf_counter()
        write_registered(out, plan, outputs, warnings, progress)
        timings = {**timings, "write_clouds": time.perf_counter() - t0}
    rows = transforms_table(outputs)
    if rows:
        dump_json(out / "transforms.json", {"crs": plan.scene.crs, "segments": rows})
    cameras = outputs.cameras
    if cameras is not None:
        from toolkit.io.colmap import write_model

        write_model(cameras.model, out / "sparse", binary=False)
        write_model(cameras.model, out / "sparse", binary=True)
        from toolkit.export import crs_wkt

        (out / "sparse" / "crs.wkt").write_text(crs_wkt(plan.scene.crs) + "\n")  # COLMAP has no CRS field
    metrics = outputs.metrics
    # the self-assessment first: it is what a user without truth reads
    metrics_values: dict[str, Any] = assessment.to_json()
    metrics_values.update(metrics.values if metrics is not None else {})
    if cov is not None:
        metrics_values["coverage"] = cov
    metrics_values["crs"] = plan.scene.crs
    metrics_values["street_scale"] = plan.scene.street_scale.as_dict()
    if len(tries) > 1:
        metrics_values["tries"] = [t.as_dict() for t in tries]
    if outputs.capture is not None and outputs.capture.cloud_path is not None:
        metrics_values["street_cloud"] = street_cloud_entry(outputs.capture)
    metrics_values["heights"] = height_kind(plan.scene, outputs.overview)
    if outputs.transforms is not None:
        metrics_values["segment_scale"] = segment_scales(outputs.transforms)
    metrics_values["warnings"] = list(warnings)
    metrics_values["input_notes"] = list(notes)  # "notes" is the evaluation's
    # written from the model (toolkit.metrics_model): an entry of another type than it declares fails here
    dump_json(out / "metrics.json", RunMetrics.checked(_jsonable(metrics_values)).to_json())
    # timings vary run to run: kept apart so metrics.json is reproducible byte for byte
    dump_json(out / "timings.json", {k: round(v, 3) for k, v in timings.items()})
    (out / "recipe.yaml").write_text(plan.recipe.to_yaml())
    _write_log(out / "run.log", plan, timings, warnings, assessment, notes)
    _write_report(out, plan, outputs, timings, warnings, assessment)


def _write_log(path: Path, plan, timings: dict[str, float], warnings: list[str], assessment,
               notes: list[str] = ()) -> None:
    lines = [f"crossview run {plan.recipe.name} on {plan.scene.root} ({plan.scene.crs})",
             f"finished {time.strftime('%Y-%m-%d %H:%M:%S')} on {platform.node()}"]
    for spec, _ in plan.stages:
        lines.append(f"step {spec.name:9s} {spec.use:24s} {timings.get(spec.name, float('nan')):8.2f} s")
    lines += [f"note: {n}" for n in notes]
    lines += [f"warning: {w}" for w in warnings]
    lines.append(f"status: {assessment.status} (confidence {assessment.confidence:.2f})")
    lines += [f"reason: {r}" for r in assessment.reasons]
    path.write_text("\n".join(lines) + "\n")


def _write_report(out: Path, plan, outputs: RunOutputs, timings, warnings, assessment) -> None:
    import importlib.util

    if importlib.util.find_spec("toolkit.report") is None:
        return
    from toolkit.report import ReportContext, write_report

    capture = outputs.capture
    street_points = capture.points if capture is not None and capture.cloud_path is not None else None
    write_report(out, ReportContext(
        recipe_text=plan.recipe.to_yaml(), scene=plan.scene, overview=outputs.overview,
        street=outputs.street, matches=outputs.matches,
        transforms=outputs.transforms, registration=outputs.registration,
        metrics=outputs.metrics, timings=timings, warnings=warnings,
        street_points=street_points, assessment=assessment,
        analysis_step=capture.step if street_points is not None else 1,
        cloud_points=capture.cloud_points if street_points is not None and capture.step > 1 else None,
    ))


def segment_scales(transforms) -> dict[str, float] | None:
    """5th, 50th and 95th percentile of the valid segments' scales (metric frame → scene), or None."""
    T = np.asarray(transforms.T, np.float64)[np.asarray(transforms.valid, bool)]
    if len(T) == 0:
        return None
    s = scale_of(T[:, :3, :3])
    p5, p50, p95 = np.percentile(s, [5, 50, 95])
    return {"p5": round(float(p5), 5), "median": round(float(p50), 5), "p95": round(float(p95), 5)}


def street_cloud_entry(capture) -> dict[str, int]:
    n = capture.cloud_points
    return {"points": n, "analysis_step": capture.step, "analysis_points": len(range(0, n, capture.step))}


def height_kind(scene, overview) -> str:
    """'absolute' when the registration had over-view heights (DSM, terrain model, over-view cloud or
    the over-view segments' ground heights), else 'relative' (the street ground at 0 m)."""
    if any(scene.has(k) for k in ("dsm", "dem", "overview_cloud")):
        return "absolute"
    if overview is not None and np.isfinite(np.asarray(overview.ground_height, np.float64)).any():
        return "absolute"
    return "relative"
