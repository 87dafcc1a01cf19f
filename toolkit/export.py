"""Moved clouds out: a run's ``registered.laz``/``registered.ply``/``warp.npz``, and the clouds of
``crossview apply``, both streamed a chunk at a time through the same writers (docs/formats.md).

Every input attribute is kept in input order; normals (``nx, ny, nz`` or ``normal_x, ...``) are
turned by each point's blended linear map (``toolkit.warp.blend.PointMaps.rotate``). The moved
coordinates come from a *mover*: the run's ``Registration`` for ``registered.*``, the stored warp
for ``apply``.
"""

from __future__ import annotations

import logging
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from toolkit.errors import CrossviewError
from toolkit.io.attributes import CHUNK_POINTS, CloudChunk, CloudSource, memory_cloud
from toolkit.io.cloud_out import LasGrid, LasWriter, PlyWriter, ply_fields, segment_name
from toolkit.refine.transforms import rotation_part


@dataclass(frozen=True)
class Moved:
    """A chunk moved into the scene CRS: xyz (k,3), carrier segment (k,) int32, turned normals
    (k,3) or None, distance to the run's street point the carrier was taken from (k,) or None."""

    xyz: np.ndarray
    segment: np.ndarray
    normals: np.ndarray | None = None
    carrier_distance_m: np.ndarray | None = None


Mover = Callable[[CloudChunk], Moved]


def crs_wkt(crs: str) -> str:
    import pyproj

    return pyproj.CRS.from_user_input(crs).to_wkt()


def crs_comment(crs: str) -> str:
    import pyproj

    return "comment crs " + " ".join(pyproj.CRS.from_user_input(crs).to_string().split())  # one header line


@dataclass(frozen=True)
class CarrierStats:
    """How far the moved points were from the street points that gave them their carriers."""

    count: int
    mean_m: float
    max_m: float


def export_cloud(source: CloudSource, mover: Mover, crs: str, grid: LasGrid, laz: Path | None = None,
                 ply: Path | None = None, chunk_points: int = CHUNK_POINTS, client: Any = None,
                 progress: Callable | None = None) -> CarrierStats:
    """Write ``source`` moved by ``mover`` to ``laz`` and/or ``ply`` (the chunks moved on ``client``'s
    workers when given, ``toolkit.stream``; the same bytes either way). ``progress``: an observer's
    ``progress`` to show the chunks go by."""
    wkt, normals, seg = crs_wkt(crs), source.normals, segment_name(source.names)
    total, top = 0.0, 0.0
    with ExitStack() as stack:
        las_out = stack.enter_context(LasWriter(laz, source, wkt, grid)) if laz is not None else None
        ply_out = None
        if ply is not None:
            ply_out = stack.enter_context(PlyWriter(ply, source.count, ply_fields(source), (crs_comment(crs),)))
        pairs = moved_chunks(source, mover, chunk_points, client)
        if progress is not None:
            pairs = progress(pairs, total=-(-source.count // chunk_points), desc=f"moving {source.count:,} points")
        for chunk, moved in pairs:
            values = turned_values(chunk, moved, normals, dict(source.fields))
            if las_out is not None:
                las_out.write(chunk, moved.xyz, values, moved.segment)
            if ply_out is not None:
                ply_out.write({"x": moved.xyz[:, 0], "y": moved.xyz[:, 1], "z": moved.xyz[:, 2], **values,
                               seg: moved.segment})
            if moved.carrier_distance_m is not None and len(moved.carrier_distance_m):
                total += float(moved.carrier_distance_m.sum())
                top = max(top, float(moved.carrier_distance_m.max()))
    return CarrierStats(source.count, total / max(source.count, 1), top)


def moved_chunks(source: CloudSource, mover: Mover, chunk_points: int,
                 client: Any = None) -> Iterator[tuple[CloudChunk, Moved]]:
    """(chunk, moved chunk) in input order; read and moved on the client's workers when there is one
    and the file can be read from any row (not an ASCII PLY nor a cloud held in memory)."""
    if client is None or not source.seekable:
        yield from _ahead(((chunk, mover(chunk)) for chunk in source.chunks(chunk_points)))
        return
    from toolkit.stream import map_spans, spans

    yield from map_spans(_ReadMove(source.path), spans(source.count, chunk_points), client, shared=mover)


def _ahead(items: Iterator):
    """``items`` with the next one made in a second thread while the caller handles this one (reading
    and moving a chunk release the GIL for most of their time, as does writing the one before)."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(1, "crossview-chunk") as pool:
        pending = pool.submit(next, items, None)
        while True:
            item = pending.result()
            if item is None:
                return
            pending = pool.submit(next, items, None)
            yield item


@dataclass(frozen=True)
class _ReadMove:
    """A Dask task: read one span of the cloud at ``path`` and move it."""

    path: Path

    def __call__(self, span, mover: Mover) -> tuple[CloudChunk, Moved]:
        from toolkit.io.attributes import open_cloud

        chunk = open_cloud(self.path).read(span.start, span.count)
        return chunk, mover(chunk)


def turned_values(chunk: CloudChunk, moved: Moved, normals: tuple[str, str, str] | None,
                  dtypes: dict[str, np.dtype]) -> dict[str, np.ndarray]:
    """The chunk's attributes with its normals replaced by the turned ones (in their own type)."""
    values = dict(chunk.values)
    if normals is not None and moved.normals is not None:
        for axis, name in enumerate(normals):
            values[name] = moved.normals[:, axis].astype(dtypes[name])
    return values


def chunk_normals(chunk: CloudChunk, normals: tuple[str, str, str] | None) -> np.ndarray | None:
    if normals is None:
        return None
    return np.column_stack([np.asarray(chunk.values[n], np.float64) for n in normals])


# --- a run's outputs ------------------------------------------------------------------------------

def registration_mover(registration, transforms, normals: tuple[str, str, str] | None) -> Mover:
    """The run's own points: coordinates and carriers from the ``Registration``; normals turned by
    the warp's maps (without a stored warp: by the rotation of the carrier's transform)."""
    points = np.asarray(registration.points, np.float64)
    segment = np.asarray(registration.point_segment, np.int64)
    warp = registration.warp

    def move(chunk: CloudChunk) -> Moved:
        rows = slice(chunk.start, chunk.start + len(chunk.xyz))
        turned = None
        vectors = chunk_normals(chunk, normals)
        if vectors is not None and warp is not None:
            turned = warp.maps(chunk.xyz, segment[rows]).rotate(vectors)
        elif vectors is not None:
            turned = _carrier_rotation(vectors, segment[rows], transforms)
        return Moved(points[rows], segment[rows].astype(np.int32), turned)

    return move


def _carrier_rotation(vectors: np.ndarray, segment: np.ndarray, transforms) -> np.ndarray:
    if transforms is None:
        return vectors
    R = np.concatenate([rotation_part(np.asarray(transforms.T, np.float64)[:, :3, :3]), np.eye(3)[None]])
    return np.einsum("nab,nb->na", R[np.where(segment >= 0, segment, len(R) - 1)], vectors)


def street_source(capture, registration) -> CloudSource:
    """The capture's street cloud with every attribute; bare points when the registration does not
    hold one row per input point (a stage that drops points)."""
    if capture.cloud_path is None:
        return memory_cloud(Path("registration"), registration.points)
    source = capture.attributes()
    if source.count != len(registration.points):
        return memory_cloud(capture.cloud_path, registration.points)
    return source


def write_registered(out: Path, plan, outputs, warnings: list[str], progress: Callable | None = None) -> None:
    """registered.laz (always), registered.ply (unless ``outputs: {ply: false}``) and warp.npz of a
    run's ``RunOutputs``."""
    from toolkit.warp.store import FILE_NAME, StoredWarp, save_warp

    registration = outputs.registration
    scene = plan.scene
    points = np.asarray(registration.points, np.float64)
    grid = LasGrid.around(points.min(axis=0), points.max(axis=0)) if len(points) else LasGrid(np.zeros(3), 0.001)
    if grid.scale_m != 0.001:
        warnings.append(f"registered.laz: the cloud spans more than 1 mm LAS integers hold; written at "
                        f"{grid.scale_m} m steps (registered.ply keeps float64)")
    capture = outputs.capture
    ply = out / "registered.ply" if plan.recipe.outputs.get("ply", True) else None
    if capture is not None and capture.step > 1:
        # the run analysed every k-th point: every input point is moved as ``crossview apply`` does
        if registration.warp is None or registration.warp.source is None:
            raise CrossviewError(f"{capture.cloud_path}: a cloud analysed on one point in {capture.step} needs a "
                                 "warp step that stores its warp (warp.inverse_log)")
        source = capture.attributes()
        from toolkit.stream import active_client

        logging.getLogger("crossview.export").info(
            "%s: moving its %s points with the warp, %s at a time", capture.cloud_path, f"{source.count:,}",
            f"{capture.chunk_points:,}")

        export_cloud(source, warp_mover(registration.warp, source.normals), scene.crs, grid,
                     laz=out / "registered.laz", ply=ply, chunk_points=capture.chunk_points, client=active_client(),
                     progress=progress)
    else:
        source = street_source(capture, registration)
        mover = registration_mover(registration, outputs.transforms, source.normals)
        export_cloud(source, mover, scene.crs, grid, laz=out / "registered.laz", ply=ply)
    if registration.warp is not None and registration.warp.source is not None:
        save_warp(out / FILE_NAME, StoredWarp(registration.warp, scene.crs, crs_wkt(scene.crs), grid.offset_m,
                                              grid.scale_m))


# --- another cloud of the run's street frame (crossview apply) --------------------------------------

def warp_mover(warp, normals: tuple[str, str, str] | None) -> Mover:
    """Each point takes the carrier of the nearest street point of the run, then the blend."""

    def move(chunk: CloudChunk) -> Moved:
        maps, carriers, distance = warp.move(chunk.xyz)
        vectors = chunk_normals(chunk, normals)
        return Moved(maps.apply(chunk.xyz), carriers.astype(np.int32),
                     None if vectors is None else maps.rotate(vectors), distance)

    return move
