"""Chunked passes over a street cloud on disk, in input order (docs/out_of_core.md).

A street cloud with more points than ``StreamSettings.max_points`` is never held whole: the run
analyses every k-th point (``thinned_points``: the *analysis cloud*, k = ⌈N / max_points⌉), and the
per-point passes over all N points (the registered clouds, the truth subset's errors, ``crossview
apply``) read, move and write it a chunk at a time. A chunk is a ``Span`` of rows; a pass is a
function of one span, run here in this process, or as a Dask computation on a ``LocalCluster``
(``workers``) or a user's scheduler (``--scheduler``), with at most ``WINDOW`` spans per worker in
flight and the results handed back in input order, so the outputs are the same bytes either way.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from toolkit.io.attributes import open_cloud

_CLIENT: list[Any] = []  # the client of the run in progress (``use_client``), read by its streamed passes
WINDOW = 2  # spans in flight per worker: the next one is ready when one finishes, memory stays bounded


class StreamSettings(BaseModel):
    """The recipe's ``stream:`` section."""

    model_config = ConfigDict(extra="forbid")
    max_points: int = Field(8_000_000, ge=10_000, description="street clouds with more points are analysed on every k-th point and streamed")
    chunk_points: int = Field(2_000_000, ge=1_000, description="points per chunk of a streamed pass")
    workers: int = Field(0, ge=0, description="LocalCluster worker processes for streamed passes (0: this process)")


@dataclass(frozen=True)
class Span:
    """Rows ``start`` … ``start + count − 1`` of a cloud."""

    start: int
    count: int


def spans(count: int, size: int) -> list[Span]:
    return [Span(s, min(size, count - s)) for s in range(0, count, size)]


def thinning_step(count: int, max_points: int) -> int:
    """k: the analysis cloud is every k-th point (1: the whole cloud)."""
    return max(1, math.ceil(count / max_points))


@contextmanager
def dask_client(scheduler: str | None = None, workers: int = 0):
    """A ``distributed.Client`` on ``scheduler`` (checked: ``toolkit.batch_client``), else on a new
    ``LocalCluster`` of ``workers`` single-threaded processes; None when both are unset."""
    if not scheduler and workers <= 0:
        yield None
        return
    if scheduler:
        from toolkit.batch_client import connect_scheduler

        client = connect_scheduler(scheduler)
        try:
            yield client
        finally:
            client.close()
        return
    import os

    import dask
    from distributed import Client, LocalCluster

    from toolkit.batch import _restore_environ, worker_config

    environ = dict(os.environ)  # the nanny writes the workers' environment into this process's (see batch)
    with dask.config.set(worker_config()):
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                               silence_logs=40)
    _restore_environ(environ)
    try:
        with Client(cluster) as client:
            yield client
    finally:
        cluster.close()


@contextmanager
def use_client(scheduler: str | None = None, workers: int = 0):
    """``dask_client`` made the one the streamed passes of this process use until the block ends."""
    with dask_client(scheduler, workers) as client:
        _CLIENT.append(client)
        try:
            yield client
        finally:
            _CLIENT.pop()


def active_client() -> Any:
    """The client of ``use_client`` (None: the passes run in this process)."""
    return _CLIENT[-1] if _CLIENT else None


def map_spans(fn: Callable[..., Any], parts: list[Any], client: Any = None, shared: Any = None) -> Iterator[Any]:
    """``fn(part, shared)`` for each part (a ``Span``, or what ``fn`` takes), yielded in order. With a
    ``client`` the calls run on its workers (``shared`` sent to each once), at most ``WINDOW`` per
    worker at a time."""
    if client is None:
        for span in parts:
            yield fn(span, shared)
        return
    held = client.scatter(shared, broadcast=True, hash=False) if shared is not None else None
    width = WINDOW * max(1, len(client.scheduler_info().get("workers", {})))
    pending: deque = deque()
    todo = iter(parts)
    for span in todo:
        pending.append(client.submit(fn, span, held, pure=False))
        if len(pending) >= width:
            break
    while pending:
        result = pending.popleft().result()
        nxt = next(todo, None)
        if nxt is not None:
            pending.append(client.submit(fn, nxt, held, pure=False))
        yield result


# --- the analysis cloud ---------------------------------------------------------------------------

@dataclass(frozen=True)
class _Thin:
    path: Path
    step: int

    def __call__(self, part: tuple[Span, np.ndarray | None], _: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Rows 0, step, … of the span, and its rows of ``keep`` (sorted, None: none), read in one pass."""
        span, keep = part
        first = (-span.start) % self.step
        if keep is None:
            pick = slice(first, None, self.step)
            return np.ascontiguousarray(open_cloud(self.path).read(span.start, span.count, pick).xyz), np.zeros((0, 3))
        thin = np.arange(first, span.count, self.step)
        pick, where = np.unique(np.concatenate([thin, keep - span.start]), return_inverse=True)
        xyz = open_cloud(self.path).read(span.start, span.count, pick).xyz
        return np.ascontiguousarray(xyz[where[:len(thin)]]), np.ascontiguousarray(xyz[where[len(thin):]])


@dataclass(frozen=True)
class KeptRows:
    """Rows of the cloud read by the analysis pass besides its own (``rows``, sorted) and their points."""

    path: Path
    mtime: int
    rows: np.ndarray
    xyz: np.ndarray


def thinned_points(path: Path, step: int, chunk_points: int, client: Any = None,
                   keep: np.ndarray | None = None) -> tuple[np.ndarray, KeptRows | None]:
    """(⌈N/step⌉, 3) float64: rows 0, step, 2·step, … of the cloud at ``path``, read a chunk at a time;
    with ``keep`` (sorted rows), those rows' points too, read in the same pass."""
    source = open_cloud(path)
    size = max(step, chunk_points // step * step)
    if not source.seekable:  # an ASCII PLY or a PCD: read once, in order, here
        parts = [_pick(chunk, step, keep) for chunk in source.chunks(size)]
    else:
        todo = [(span, None if keep is None else keep[np.searchsorted(keep, span.start):
                                                       np.searchsorted(keep, span.start + span.count)])
                for span in spans(source.count, size)]
        parts = list(map_spans(_Thin(Path(path), step), todo, client))
    if not parts:
        return np.zeros((0, 3)), None
    thin = np.concatenate([p[0] for p in parts])
    kept = None if keep is None else KeptRows(Path(path), Path(path).stat().st_mtime_ns, keep,
                                               np.concatenate([p[1] for p in parts]))
    return thin, kept


def _pick(chunk: Any, step: int, keep: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    thin = chunk.xyz[(-chunk.start) % step::step]
    if keep is None:
        return thin, np.zeros((0, 3))
    lo, hi = np.searchsorted(keep, [chunk.start, chunk.start + len(chunk.xyz)])
    return thin, chunk.xyz[keep[lo:hi] - chunk.start]


def analysis_points(path: Path, step: int, chunk_points: int, street_scale: float = 1.0,
                    keep_file: Path | None = None) -> np.ndarray:
    """The analysis cloud in metres (divided by the street scale), read-only, kept for the run's stages.
    ``keep_file``: a .npy of increasing row numbers whose input points the same read keeps (``kept_rows``)."""
    keep = None if keep_file is None else (Path(keep_file), Path(keep_file).stat().st_mtime_ns)
    return _analysis(Path(path), Path(path).stat().st_mtime_ns, step, chunk_points, float(street_scale), keep)


@functools.lru_cache(maxsize=1)
def _analysis(path: Path, mtime: int, step: int, chunk_points: int, street_scale: float,
              keep: tuple[Path, int] | None) -> np.ndarray:
    pts = _thinned(path, mtime, step, chunk_points, keep)
    if street_scale != 1.0:
        pts = pts / street_scale
    pts.setflags(write=False)
    return pts


_KEPT: list[KeptRows] = []  # the kept rows of ``_thinned``'s one cached read


@functools.lru_cache(maxsize=1)
def _thinned(path: Path, mtime: int, step: int, chunk_points: int, keep: tuple[Path, int] | None) -> np.ndarray:
    rows = None if keep is None else _rows_to_keep(keep[0], open_cloud(path).count)
    pts, kept = thinned_points(path, step, chunk_points, active_client(), rows)
    _KEPT[:] = [] if kept is None else [kept]
    return pts


def _rows_to_keep(path: Path, count: int) -> np.ndarray | None:
    """The increasing row numbers of the .npy at ``path`` (rows of a ``count``-point cloud); None when
    it is not such a file (whoever reads it for itself reports that)."""
    try:
        rows = np.asarray(np.load(path, allow_pickle=False), np.int64)
    except Exception:
        return None
    ok = rows.ndim == 1 and len(rows) > 0 and rows[0] >= 0 and rows[-1] < count
    return rows if ok and np.all(np.diff(rows) > 0) else None


def kept_rows(path: Path, rows: np.ndarray) -> np.ndarray | None:
    """The input points of ``rows`` if the last analysis read of ``path`` kept exactly those, else None."""
    kept = _KEPT[0] if _KEPT else None
    if (kept is None or kept.path != Path(path) or kept.mtime != Path(path).stat().st_mtime_ns
            or not np.array_equal(kept.rows, rows)):
        return None
    return kept.xyz


# --- errors of the truth rows (test scenes) --------------------------------------------------------

@dataclass(frozen=True)
class NpyRows:
    """Rows ``lo``..``hi``−1 of a 2-D .npy file, read when used as an array (``np.asarray``), neither
    loaded nor memory-mapped: a map's pages stay resident once touched (0.4 GB of truth on 17 M points)."""

    path: Path
    offset: int
    dtype: str
    width: int
    lo: int
    hi: int

    @classmethod
    def open(cls, path: Path) -> NpyRows:
        arr = np.load(path, mmap_mode="r", allow_pickle=False)
        if arr.ndim != 2 or not arr.flags.c_contiguous:
            raise ValueError(f"{path}: expected a C-ordered 2-D array, got shape {arr.shape}")
        return cls(Path(path), int(arr.offset), arr.dtype.str, int(arr.shape[1]), 0, int(arr.shape[0]))

    @property
    def shape(self) -> tuple[int, int]:
        return (self.hi - self.lo, self.width)

    def __len__(self) -> int:
        return self.hi - self.lo

    def __getitem__(self, rows: slice) -> NpyRows:
        start, stop, step = rows.indices(len(self))
        if step != 1:
            raise IndexError("NpyRows: only contiguous row ranges")
        return dataclasses.replace(self, lo=self.lo + start, hi=self.lo + max(start, stop))

    def __array__(self, dtype=None, copy=None) -> np.ndarray:
        dt = np.dtype(self.dtype)
        out = np.fromfile(self.path, dt, count=len(self) * self.width,
                          offset=self.offset + self.lo * self.width * dt.itemsize).reshape(self.shape)
        return out if dtype is None else out.astype(dtype, copy=False)


@dataclass(frozen=True)
class _RowErrors:
    path: Path

    def __call__(self, part: tuple[Span, np.ndarray, np.ndarray], warp: Any) -> tuple[np.ndarray, np.ndarray]:
        span, rows, truth = part
        return _moved_errors(warp, open_cloud(self.path).read(span.start, span.count, rows - span.start).xyz, truth)


def _moved_errors(warp: Any, xyz: np.ndarray, truth: Any) -> tuple[np.ndarray, np.ndarray]:
    """(3D, horizontal) error of input points ``xyz`` moved by ``warp`` against ``truth`` (one row each)."""
    from toolkit.evaluation.metrics import point_errors

    return point_errors(warp.move(xyz)[0].apply(xyz), np.asarray(truth))


def row_errors(path: Path, rows: np.ndarray, truth: np.ndarray | NpyRows, warp: Any, chunk_points: int,
               client: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """(3D, horizontal) error of input rows ``rows`` (sorted) of the cloud at ``path`` moved by ``warp``
    (a ``PointWarp`` taking input street-frame units) against ``truth`` (one row each; ``NpyRows`` are
    read a chunk at a time). Each chunk's errors go straight into the result."""
    rows = np.asarray(rows, np.int64)
    err3d, err_h = np.zeros(len(rows)), np.zeros(len(rows))
    kept = kept_rows(path, rows)
    if kept is not None:  # read by the analysis pass: no second pass over the cloud
        for lo in range(0, len(rows), chunk_points):
            sl = slice(lo, lo + chunk_points)
            err3d[sl], err_h[sl] = _moved_errors(warp, kept[sl], truth[sl])
        return err3d, err_h
    source = open_cloud(path)
    if not source.seekable:  # an ASCII PLY or a PCD: read once, in order, here
        for chunk in source.chunks(chunk_points):
            lo, hi = np.searchsorted(rows, [chunk.start, chunk.start + len(chunk.xyz)])
            err3d[lo:hi], err_h[lo:hi] = _moved_errors(warp, chunk.xyz[rows[lo:hi] - chunk.start], truth[lo:hi])
        return err3d, err_h
    parts, at = [], []
    for span in spans(source.count, chunk_points):
        lo, hi = np.searchsorted(rows, [span.start, span.start + span.count])
        if hi > lo:
            parts.append((span, rows[lo:hi], truth[lo:hi]))
            at.append(slice(lo, hi))
    for sl, (e3, eh) in zip(at, map_spans(_RowErrors(Path(path)), parts, client, shared=warp)):
        err3d[sl], err_h[sl] = e3, eh
    return err3d, err_h
