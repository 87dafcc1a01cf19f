"""RerunObserver: the only module that imports rerun.

Entity paths are recipe step names (``overview/tophat``, ``match/graph``) so a stage swap keeps the
viewer layout; ``crossview compare`` prefixes each variant (``/dsm/overview/...``). Timelines:
``stage`` (step index), ``match_iter`` and ``refine_iter`` (given by stages through ``it=``).
Containers are converted by ``to_rerun`` (functools.singledispatch), debug payloads likewise.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any, Iterable, Iterator, Sequence, TypeVar

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from toolkit.observe import (
    DebugGraph, DebugImage, DebugLines, DebugPoints, DebugPoints2D, DebugScalar, DebugText, NullObserver,
)
from toolkit.stage import KINDS
from toolkit.types import AdjustedCameras, Matches, Metrics, OverviewSegments, Registration, StreetSegments

T = TypeVar("T")


def _palette(ids: np.ndarray) -> np.ndarray:
    """Stable pseudo-random colours for integer ids (negative ids grey)."""
    ids = np.asarray(ids, dtype=np.int64)
    h = (ids * 2654435761) & 0xFFFFFF
    rgb = np.stack([(h >> 16) & 255, (h >> 8) & 255, h & 255], axis=-1).astype(np.uint8)
    rgb = (rgb // 2 + 100).astype(np.uint8)
    rgb[ids < 0] = 128
    return rgb


def _subsample(n: int, max_points: int) -> np.ndarray:
    if n <= max_points:
        return np.arange(n)
    return np.linspace(0, n - 1, max_points).astype(np.int64)


@functools.singledispatch
def to_rerun(value: Any, max_points: int) -> list[tuple[str, Any]]:
    """(sub-path, archetype) pairs for a value; empty when the value has no picture."""
    if isinstance(value, np.ndarray):
        if value.ndim == 2 and value.shape[1] == 3 and value.dtype.kind == "f":
            idx = _subsample(len(value), max_points)
            return [("", rr.Points3D(value[idx].astype(np.float32)))]
        if value.ndim == 2:
            return [("", rr.DepthImage(value.astype(np.float32)) if value.dtype.kind == "f"
                     else rr.SegmentationImage(value.astype(np.int32)))]
    if isinstance(value, (int, float, np.floating)):
        return [("", rr.Scalars([float(value)]))]
    return []


def _point_colors(value: DebugPoints | DebugPoints2D, idx: np.ndarray) -> np.ndarray | None:
    """Explicit colours if given, else a palette colour per class id, else None (viewer default)."""
    if value.colors is not None:
        return value.colors[idx]
    return _palette(value.class_ids[idx]) if value.class_ids is not None else None


@to_rerun.register
def _(value: DebugPoints, max_points: int):
    idx = _subsample(len(value.xyz), max_points)
    return [("", rr.Points3D(np.asarray(value.xyz)[idx].astype(np.float32), colors=_point_colors(value, idx),
                             radii=value.radius_m))]


@to_rerun.register
def _(value: DebugPoints2D, max_points: int):
    idx = _subsample(len(value.xy), max_points)
    return [("", rr.Points2D(np.asarray(value.xy)[idx].astype(np.float32), colors=_point_colors(value, idx),
                             radii=value.radius_m))]


@to_rerun.register
def _(value: DebugImage, max_points: int):
    a = np.asarray(value.array)
    if value.kind == "rgb":
        return [("", rr.Image(a.astype(np.uint8)))]
    if value.kind == "mask":
        return [("", rr.SegmentationImage(a.astype(np.uint8)))]
    if value.kind == "segmentation":
        return [("", rr.SegmentationImage((a.astype(np.int64) + 1).astype(np.uint16)))]
    return [("", rr.DepthImage(np.nan_to_num(a.astype(np.float32))))]


@to_rerun.register
def _(value: DebugLines, max_points: int):
    strips = [np.asarray(s, dtype=np.float32) for s in value.strips]
    if strips and strips[0].shape[1] == 3:
        return [("", rr.LineStrips3D(strips, colors=value.colors, radii=value.radius_m))]
    return [("", rr.LineStrips2D(strips, colors=value.colors, radii=value.radius_m))]


@to_rerun.register
def _(value: DebugGraph, max_points: int):
    n = len(value.positions)
    ids = [str(i) for i in range(n)]
    edges = [(str(a), str(b)) for a, b in np.asarray(value.edges).reshape(-1, 2)]
    return [
        ("", rr.GraphNodes(ids, positions=np.asarray(value.positions, np.float32), labels=value.labels)),
        ("", rr.GraphEdges(edges, graph_type="undirected")),
    ]


@to_rerun.register
def _(value: DebugScalar, max_points: int):
    return [("", rr.Scalars([float(value.value)]))]


@to_rerun.register
def _(value: DebugText, max_points: int):
    return [("", rr.TextDocument(value.text, media_type=value.media_type))]


@to_rerun.register
def _(value: OverviewSegments, max_points: int):
    out = [("segments", rr.SegmentationImage((value.label_image + 1).astype(np.uint16)))]
    if len(value):
        out.append(("centroids", rr.Points2D(value.grid.world_to_pixel(value.centroids)[:, ::-1]
                                             .astype(np.float32), radii=2.0)))
    return out


@to_rerun.register
def _(value: StreetSegments, max_points: int):
    strips = [b.astype(np.float32) for b in value.boundary_xy if len(b)]
    if not strips:
        return []
    pts = np.concatenate(strips)
    cls = np.concatenate([np.full(len(b), i) for i, b in enumerate(value.boundary_xy) if len(b)])
    idx = _subsample(len(pts), max_points)
    return [("boundaries", rr.Points2D(pts[idx], colors=_palette(cls[idx]), radii=0.2))]


@to_rerun.register
def _(value: Registration, max_points: int):
    idx = _subsample(len(value.points), max_points)
    pts = value.points[idx]
    origin = np.floor(np.median(pts, axis=0) / 100.0) * 100.0  # keep float32 precision
    return [("cloud", rr.Points3D((pts - origin).astype(np.float32),
                                  colors=_palette(value.point_segment[idx]), radii=0.05))]


@to_rerun.register
def _(value: Matches, max_points: int):
    matched = int((value.segment_match >= 0).sum())
    text = (f"**{matched} / {len(value.segment_match)}** street segments matched; energy {value.energy:.4f} "
            f"after {value.iterations} iterations ({'converged' if value.converged else 'not converged'})"
            + (f"; lower bound {value.lower_bound:.4f}" if value.lower_bound is not None else ""))
    return [("summary", rr.TextDocument(text, media_type="text/markdown"))]


@to_rerun.register
def _(value: AdjustedCameras, max_points: int):
    c = value.model.centres
    origin = np.floor(np.median(c, axis=0) / 100.0) * 100.0 if len(c) else np.zeros(3)
    return [("centres", rr.Points3D((c - origin).astype(np.float32), radii=0.3)),
            ("rms_px", rr.Scalars([value.rms_after_px]))]


@to_rerun.register
def _(value: Metrics, max_points: int):
    import json

    return [("metrics", rr.TextDocument("```json\n" + json.dumps(value.values, indent=1, default=str)
                                        + "\n```", media_type="text/markdown"))]


class RerunObserver(NullObserver):
    """Logs stage outputs and debug payloads to a rerun recording saved at ``path``.

    Pass ``recording`` to share one recording between variants (``crossview compare``) and
    ``prefix`` ("/variant") to place this run under its own root.
    """

    def __init__(self, path: str | Path | None = None, recording: rr.RecordingStream | None = None,
                 prefix: str = "", max_points: int = 200_000, application_id: str = "crossview") -> None:
        super().__init__()
        if recording is None:
            if path is None:
                raise ValueError("RerunObserver needs a path or a recording")
            # A sink from the first call: without one rerun buffers everything in memory.
            recording = rr.RecordingStream(application_id, recording_id="crossview-run")
            recording.save(str(path), default_blueprint=pipeline_blueprint(prefix))
        self.rec = recording
        self.prefix = prefix.rstrip("/")
        self.max_points = max_points
        self._stage_index = 0

    @property
    def wants_debug(self) -> bool:
        return True

    def _path(self, name: str) -> str:
        parts = [self.prefix, self.step, name] if self.step else [self.prefix, name]
        return "/".join(p.strip("/") for p in parts if p and p.strip("/")) or "/"

    def stage_start(self, step: str, stage_key: str) -> None:
        super().stage_start(step, stage_key)
        self._stage_index = KINDS.index(step) if step in KINDS else self._stage_index + 1
        self.rec.set_time("stage", sequence=self._stage_index)

    def stage_end(self, step: str, seconds: float, output: Any) -> None:
        super().stage_end(step, seconds, output)
        self.rec.set_time("stage", sequence=self._stage_index)
        self._log(self._path(""), output)
        self.rec.log(self._path("seconds"), rr.Scalars([seconds]))

    def debug(self, name: str, value: Any, it: int | None = None, timeline: str | None = None) -> None:
        if it is not None:
            self.rec.set_time(timeline or f"{self.step}_iter", sequence=int(it))
        self._log(self._path(name), value)
        if it is not None:
            self.rec.reset_time()
            self.rec.set_time("stage", sequence=self._stage_index)

    def log_text(self, name: str, text: str, media_type: str = "text/markdown") -> None:
        self.rec.log("/".join(p for p in (self.prefix.strip("/"), name) if p),
                     rr.TextDocument(text, media_type=media_type), static=True)

    def _log(self, path: str, value: Any) -> None:
        for sub, archetype in to_rerun(value, self.max_points):
            self.rec.log("/".join(p for p in (path.rstrip("/"), sub) if p) or "/", archetype)

    def progress(self, iterable: Iterable[T], total: int | None = None, desc: str = "") -> Iterator[T]:
        return iter(iterable)

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def pipeline_blueprint(prefix: str = "") -> rrb.Blueprint:
    root = prefix.rstrip("/")
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial2DView(origin=f"{root}/overview", name="over-view"),
        rrb.Spatial2DView(origin=f"{root}/street", name="street segments"),
        rrb.Vertical(
            rrb.TimeSeriesView(origin=f"{root}/match", name="matching energy"),
            rrb.TextDocumentView(origin=f"{root}/recipe", name="recipe"),
        ),
    ))


def compare_blueprint(variants: Sequence[str]) -> rrb.Blueprint:
    """Side by side: one column per variant (over-view segments above, registered cloud below)."""
    return rrb.Blueprint(rrb.Horizontal(*[
        rrb.Vertical(
            rrb.Spatial2DView(origin=f"/{v}/overview", name=f"{v}: over-view"),
            rrb.Spatial3DView(origin=f"/{v}/warp", name=f"{v}: registered"),
        ) for v in variants
    ]))


def open_shared_recording(path: str | Path, variants: Sequence[str]) -> rr.RecordingStream:
    rec = rr.RecordingStream("crossview", recording_id="crossview-compare")
    rec.save(str(path), default_blueprint=compare_blueprint(variants))
    return rec


def entity_paths(path: str | Path) -> list[str]:
    """Entity paths stored in an .rrd (for tests and tools)."""
    store = rr.chunk.RrdReader(str(path)).store()
    return sorted(str(p) for p in store.schema().entity_paths())
