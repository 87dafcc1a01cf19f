"""Every per-point attribute of a cloud, read in chunks: PLY (binary via a memory map, or ASCII),
LAS/LAZ (laspy's chunk iterator), PCD (Open3D: colours and normals).

``open_cloud(path)`` gives a ``CloudSource``: the point count, the attributes besides x, y, z in
input order (``fields``) and ``chunks()``, each a ``CloudChunk`` of float64 xyz plus every
attribute, and for LAS the raw point records (copied as they are into a LAS output). A PLY may be
a mesh: its vertices are the points, ``ply`` keeps the header and where the other elements start.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from toolkit.errors import SceneError
from toolkit.io.cloud import _PLY_TYPES, check_las_header

CHUNK_POINTS = 1 << 20
NORMAL_NAMES = (("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"), ("normalx", "normaly", "normalz"))
CLOUD_SUFFIXES = (".ply", ".las", ".laz", ".pcd")


@dataclass(frozen=True)
class PlyElement:
    name: str
    count: int
    props: tuple[tuple[str, str | None], ...]   # (name, numpy type code; None for a list property)
    lines: tuple[str, ...]                       # its header lines, verbatim


@dataclass(frozen=True)
class PlyHeader:
    fmt: str                  # ascii, binary_little_endian, binary_big_endian
    elements: tuple[PlyElement, ...]
    comments: tuple[str, ...]
    data_offset: int          # bytes before the first element's data

    @property
    def endian(self) -> str:
        return ">" if self.fmt == "binary_big_endian" else "<"

    def vertex_dtype(self) -> np.dtype:
        return np.dtype([(n, self.endian + t) for n, t in self.elements[0].props])


@dataclass(frozen=True)
class CloudChunk:
    """``start``: row of the first point; xyz (k,3) float64; values: every field by name;
    las: the raw LAS records (LAS input only)."""

    start: int
    xyz: np.ndarray
    values: dict[str, np.ndarray]
    las: np.ndarray | None = None


@dataclass(frozen=True)
class CloudSource:
    path: Path
    kind: str                                   # "ply", "las", "memory" (PCD, arrays)
    count: int
    fields: tuple[tuple[str, np.dtype], ...]    # attributes besides x, y, z, in input order
    las_format: Any = None                      # laspy.PointFormat of a LAS/LAZ input
    ply: PlyHeader | None = None
    _whole: dict[str, np.ndarray] = field(default_factory=dict, repr=False)  # "memory": xyz and fields

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for n, _ in self.fields)

    @property
    def normals(self) -> tuple[str, str, str] | None:
        """The three fields holding normals (nx, ny, nz or normal_x, ...; any case), or None."""
        lower = {n.lower(): n for n in self.names}
        for triple in NORMAL_NAMES:
            if all(t in lower for t in triple):
                return tuple(lower[t] for t in triple)
        return None

    @property
    def seekable(self) -> bool:
        """``read`` starts at its first row (a binary PLY or LAS/LAZ), not at the file's start."""
        return self.kind == "las" or (self.kind == "ply" and self.ply.fmt != "ascii")

    @property
    def is_mesh(self) -> bool:
        return self.ply is not None and len(self.ply.elements) > 1

    def chunks(self, size: int = CHUNK_POINTS) -> Iterator[CloudChunk]:
        reader = {"ply": _ply_chunks, "las": _las_chunks, "memory": _memory_chunks}[self.kind]
        return reader(self, size)

    def read(self, start: int, count: int, pick: Any = None) -> CloudChunk:
        """Rows ``start`` … ``start + count − 1`` alone, of a ``seekable`` cloud or one held in memory;
        ``pick`` (an index or slice into those rows) keeps only some of them, before any conversion.
        The chunk's ``start`` stays ``start``."""
        if self.kind == "las":
            return _las_read(self, start, count, pick)
        if self.seekable:
            return _ply_read(self, start, count, pick)
        if self.kind == "memory":
            rows = np.arange(start, min(start + count, self.count))
            rows = rows if pick is None else rows[pick]
            return CloudChunk(start, self._whole["xyz"][rows], {n: self._whole[n][rows] for n in self.names})
        raise ValueError(f"{self.path}: an ASCII PLY is read in order (chunks), not from a given row")


def open_cloud(path: str | Path) -> CloudSource:
    """Header only (nothing of the points is read); a ``SceneError`` naming the file when unusable."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in CLOUD_SUFFIXES:
        raise SceneError(f"{path}: unsupported point cloud format {suffix!r} (use .ply, .las, .laz, .pcd)")
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    try:
        if suffix == ".ply":
            return _open_ply(path)
        if suffix in (".las", ".laz"):
            return _open_las(path)
        return _open_pcd(path)
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(f"{path}: cannot read point cloud ({type(exc).__name__}: {exc})") from exc


def read_ply_header(path: Path) -> PlyHeader:
    elements: list[list] = []
    comments, fmt = [], None
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise SceneError(f"{path}: not a PLY file (missing 'ply' magic)")
        while True:
            raw = fh.readline()
            if not raw:
                raise SceneError(f"{path}: PLY header has no end_header")
            line = raw.decode("ascii", "replace").rstrip("\r\n")
            words = line.split()
            if not words or words[0] == "obj_info":
                continue
            if words[0] == "comment":
                comments.append(line)
            elif words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append([words[1], int(words[2]), [], [line]])
            elif words[0] == "property":
                if not elements:
                    raise SceneError(f"{path}: PLY property before any element")
                kind = None if words[1] == "list" else _PLY_TYPES.get(words[1])
                if words[1] != "list" and kind is None:
                    raise SceneError(f"{path}: unknown PLY property type {words[1]!r}")
                elements[-1][2].append((words[-1], kind))
                elements[-1][3].append(line)
            elif words[0] == "end_header":
                break
        offset = fh.tell()
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise SceneError(f"{path}: unknown PLY format {fmt!r}")
    if not elements or elements[0][0] != "vertex":
        raise SceneError(f"{path}: PLY has no leading vertex element")
    els = tuple(PlyElement(n, c, tuple(p), tuple(ls)) for n, c, p, ls in elements)
    if any(t is None for _, t in els[0].props):
        raise SceneError(f"{path}: PLY vertex element has list properties")
    if not {"x", "y", "z"} <= {n for n, _ in els[0].props}:
        raise SceneError(f"{path}: PLY vertices lack x, y, z")
    return PlyHeader(fmt, els, tuple(comments), offset)


def _open_ply(path: Path) -> CloudSource:
    head = read_ply_header(path)
    vertex = head.elements[0]
    if head.fmt != "ascii":
        need = head.data_offset + vertex.count * head.vertex_dtype().itemsize
        if path.stat().st_size < need:
            raise SceneError(f"{path}: PLY is truncated ({vertex.count} vertices need {need} bytes)")
    fields = tuple((n, np.dtype(t)) for n, t in vertex.props if n not in ("x", "y", "z"))
    return CloudSource(path, "ply", vertex.count, fields, ply=head)


def _ply_chunks(src: CloudSource, size: int) -> Iterator[CloudChunk]:
    if src.ply.fmt == "ascii":
        yield from _ascii_ply_chunks(src, size)
        return
    for start in range(0, src.count, size):
        yield _ply_read(src, start, size)


def _ply_read(src: CloudSource, start: int, count: int, pick: Any = None) -> CloudChunk:
    head = src.ply
    rec = np.memmap(src.path, dtype=head.vertex_dtype(), mode="r", offset=head.data_offset, shape=(src.count,))
    part = rec[start:start + count]
    if pick is not None:
        part = part[pick]
    return CloudChunk(start, _xyz(part), {n: np.asarray(part[n]).astype(t.newbyteorder("=")) for n, t in src.fields})


def _ascii_ply_chunks(src: CloudSource, size: int) -> Iterator[CloudChunk]:
    props = src.ply.elements[0].props
    with open(src.path, "rb") as fh:
        fh.seek(src.ply.data_offset)
        for start in range(0, src.count, size):
            lines = list(itertools.islice(fh, min(size, src.count - start)))
            table = np.loadtxt(lines, ndmin=2, dtype=np.float64) if lines else np.zeros((0, len(props)))
            if len(lines) < min(size, src.count - start) or table.shape[1] < len(props):
                raise SceneError(f"{src.path}: PLY is truncated ({start + len(lines)} of {src.count} vertices)")
            cols = {n: table[:, i] for i, (n, _) in enumerate(props)}
            yield CloudChunk(start, np.column_stack([cols["x"], cols["y"], cols["z"]]),
                             {n: cols[n].astype(t) for n, t in src.fields})


def ply_tail_offset(src: CloudSource) -> int:
    """Byte offset of the data after the vertex block (the faces of a mesh) in a binary PLY."""
    return src.ply.data_offset + src.count * src.ply.vertex_dtype().itemsize


def _xyz(rec: np.ndarray) -> np.ndarray:
    out = np.empty((len(rec), 3))
    for axis, c in enumerate("xyz"):
        out[:, axis] = rec[c]
    return out


def _open_las(path: Path) -> CloudSource:
    import laspy

    check_las_header(path)
    with laspy.open(path) as reader:
        fmt = reader.header.point_format
        count = int(reader.header.point_count)
    fields = []
    for dim in fmt.dimensions:
        if dim.name in ("X", "Y", "Z"):
            continue
        if dim.scales is not None:
            kind = np.dtype(np.float64)            # a scaled extra dimension reads as float64
        else:
            kind = np.dtype(dim.dtype if dim.dtype is not None else np.uint8)  # bit fields: uint8
        fields.append((dim.name, kind))
    return CloudSource(path, "las", count, tuple(fields), las_format=fmt)


def _las_chunks(src: CloudSource, size: int) -> Iterator[CloudChunk]:
    import laspy

    start = 0
    with laspy.open(src.path) as reader:
        for chunk in reader.chunk_iterator(size):
            yield _las_chunk(src, start, chunk)
            start += len(chunk)
    if start != src.count:
        raise SceneError(f"{src.path}: LAS/LAZ is truncated ({start} of {src.count} points)")


def _las_read(src: CloudSource, start: int, count: int, pick: Any = None) -> CloudChunk:
    import laspy

    with laspy.open(src.path) as reader:
        reader.seek(start)
        chunk = reader.read_points(count)
    if len(chunk) != min(count, src.count - start):
        raise SceneError(f"{src.path}: LAS/LAZ is truncated ({start + len(chunk)} of {src.count} points)")
    if pick is not None:  # before the scaled coordinates are made: 151 M of them cost 7 s
        chunk = chunk[pick]
    return _las_chunk(src, start, chunk)


def _las_chunk(src: CloudSource, start: int, points) -> CloudChunk:
    """laspy points → a ``CloudChunk``: float64 xyz, every field, the raw records."""
    xyz = np.column_stack([np.asarray(points.x), np.asarray(points.y), np.asarray(points.z)])
    return CloudChunk(start, xyz, {n: np.asarray(points[n]) for n, _ in src.fields}, las=points.array)


def _open_pcd(path: Path) -> CloudSource:
    from toolkit.open3d_import import open3d

    pcd = open3d().io.read_point_cloud(str(path))
    whole = {"xyz": np.asarray(pcd.points, np.float64)}
    if pcd.has_colors():
        rgb = (np.asarray(pcd.colors) * 255).round().astype(np.uint8)
        whole.update(red=rgb[:, 0], green=rgb[:, 1], blue=rgb[:, 2])
    if pcd.has_normals():
        n = np.asarray(pcd.normals, np.float32)
        whole.update(nx=n[:, 0], ny=n[:, 1], nz=n[:, 2])
    return memory_cloud(path, whole.pop("xyz"), whole)


def memory_cloud(path: Path, xyz: np.ndarray, values: dict[str, np.ndarray] | None = None) -> CloudSource:
    """A cloud held in memory (a PCD read by Open3D, or bare points), chunked like the others."""
    whole = {"xyz": np.asarray(xyz, np.float64), **(values or {})}
    fields = tuple((n, a.dtype) for n, a in whole.items() if n != "xyz")
    return CloudSource(Path(path), "memory", len(whole["xyz"]), fields, _whole=whole)


def _memory_chunks(src: CloudSource, size: int) -> Iterator[CloudChunk]:
    for start in range(0, src.count, size):
        part = slice(start, start + size)
        yield CloudChunk(start, src._whole["xyz"][part], {n: src._whole[n][part] for n in src.names})
