"""Writing moved clouds a chunk at a time: LAS/LAZ (laspy) in the scene CRS, and binary PLY.

LAS: version 1.4, the scene CRS as a WKT VLR, coordinates at ``LasGrid.scale_m`` (1 mm) about a
round offset. A LAS/LAZ input keeps its point format and every dimension, raw (the records are
copied as they are, then x, y, z and the normals replaced); a PLY/PCD input gets point format 7
with its red, green, blue (8-bit values × 257) or 6 without, its ``intensity`` when it is 8 or 16
bit, and every other property as an extra dimension of its own type (a name the point format
already uses is prefixed ``ply_``). Last comes the extra dimension ``segment`` (int32).

PLY: binary little endian, x, y, z as double, then every input attribute in input order with its
own type (64-bit integers as double: PLY has none), then ``segment``.
"""

from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.errors import CrossviewError
from toolkit.io.attributes import CloudChunk, CloudSource

LAS_SCALES_M = (0.001, 0.01, 0.1)   # the first that holds the cloud's extent in int32 is used
OFFSET_ROUND_M = 100.0
LAS_DATE = datetime.date(2000, 1, 1)  # a fixed creation date: the same run gives the same bytes
SEGMENT = "segment"
_PLY_NAMES = {"i1": "char", "u1": "uchar", "i2": "short", "u2": "ushort", "i4": "int", "u4": "uint",
              "f4": "float", "f8": "double"}
_INT32 = 2**31 - 1


@dataclass(frozen=True)
class LasGrid:
    """LAS integer coordinates: (xyz − offset_m) / scale_m, rounded."""

    offset_m: np.ndarray
    scale_m: float

    @classmethod
    def around(cls, lo: np.ndarray, hi: np.ndarray) -> LasGrid:
        """A round offset at the centre of the box [lo, hi], 1 mm when the box fits in int32 at 1 mm."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        offset = np.round((lo + hi) / 2 / OFFSET_ROUND_M) * OFFSET_ROUND_M
        reach = float(np.max(np.maximum(np.abs(hi - offset), np.abs(lo - offset))))
        scale = next((s for s in LAS_SCALES_M if reach / s < 0.9 * _INT32), 1.0)
        return cls(offset, scale)

    def integers(self, xyz: np.ndarray, path: Path) -> np.ndarray:
        q = np.round((np.asarray(xyz, np.float64) - self.offset_m) / self.scale_m)
        if len(q) and np.abs(q).max() > _INT32:
            far = float(np.abs(xyz - self.offset_m).max())
            raise CrossviewError(f"{path}: points reach {far:.0f} m from the LAS offset {self.offset_m.tolist()}, "
                                 f"beyond what {self.scale_m} m integer coordinates hold; write PLY instead (--out "
                                 "NAME.ply)")
        return q.astype(np.int32)


def segment_name(names: tuple[str, ...]) -> str:
    return SEGMENT if SEGMENT not in names else f"crossview_{SEGMENT}"


class LasWriter:
    """``write(chunk, xyz, values, segment)`` per chunk, in order; a context manager."""

    def __init__(self, path: Path, source: CloudSource, crs_wkt: str, grid: LasGrid):
        import laspy

        self.path, self.source, self.grid = path, source, grid
        self.header, self.plan, self.segment = las_header(source, crs_wkt, grid)
        self._writer = laspy.open(path, mode="w", header=self.header)

    def write(self, chunk: CloudChunk, xyz: np.ndarray, values: dict[str, np.ndarray], segment: np.ndarray) -> None:
        import laspy

        rec = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=self.header)
        if chunk.las is not None:
            for name in chunk.las.dtype.names:
                if name not in ("X", "Y", "Z"):
                    rec.array[name] = chunk.las[name]
        for src, dst, convert in self.plan:
            rec[dst] = convert(values[src])
        q = self.grid.integers(xyz, self.path)
        rec.array["X"], rec.array["Y"], rec.array["Z"] = q[:, 0], q[:, 1], q[:, 2]
        rec.array[self.segment] = segment
        self._writer.write_points(rec)

    def close(self) -> None:
        self._writer.close()

    def __enter__(self) -> LasWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def las_header(source: CloudSource, crs_wkt: str, grid: LasGrid) -> tuple[Any, list, str]:
    """(laspy header, [(input field, LAS dimension, conversion)] of the values written per chunk,
    name of the segment dimension)."""
    import laspy
    import pyproj

    if source.las_format is not None:
        fmt_id, plan, extra = source.las_format.id, _las_normals_plan(source), _las_extra(source.las_format)
    else:
        fmt_id, plan, extra = _ply_layout(source)
    header = laspy.LasHeader(point_format=fmt_id, version="1.4")
    for params in extra:
        header.add_extra_dim(params)
    segment = segment_name(tuple(header.point_format.dimension_names))
    header.add_extra_dim(laspy.ExtraBytesParams(segment, np.int32, description="crossview carrier segment"))
    header.offsets, header.scales = grid.offset_m, np.full(3, grid.scale_m)
    header.add_crs(pyproj.CRS.from_wkt(crs_wkt), keep_compatibility=False)
    header.creation_date = LAS_DATE
    header.generating_software = "crossview"
    return header, plan, segment


def _las_extra(fmt) -> list:
    import laspy

    return [laspy.ExtraBytesParams(d.name, d.dtype, d.description, d.offsets, d.scales, d.no_data)
            for d in fmt.extra_dimensions]


def _las_normals_plan(source: CloudSource) -> list:
    """A LAS input's normals (extra dimensions) are the only values replaced: turned with the points."""
    return [(n, n, _same) for n in (source.normals or ())]


def _ply_layout(source: CloudSource) -> tuple[int, list, list]:
    import laspy

    names = source.names
    dtypes = dict(source.fields)
    rgb = all(c in dtypes and dtypes[c].kind == "u" and dtypes[c].itemsize <= 2 for c in ("red", "green", "blue"))
    fmt_id = 7 if rgb else 6
    standard = set(laspy.PointFormat(fmt_id).dimension_names)
    plan, extra = [], []
    for name in names:
        kind = dtypes[name]
        if rgb and name in ("red", "green", "blue"):
            plan.append((name, name, _to_16bit if kind.itemsize == 1 else _same))
        elif name == "intensity" and kind.kind == "u" and kind.itemsize <= 2:
            plan.append((name, name, _same))
        else:
            dst = name if name not in standard else f"ply_{name}"
            extra.append(laspy.ExtraBytesParams(dst, kind.newbyteorder("=")))
            plan.append((name, dst, _same))
    return fmt_id, plan, extra


def _same(values: np.ndarray) -> np.ndarray:
    return values


def _to_16bit(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, np.uint16) * np.uint16(257)  # 255 → 65535: the LAS colour range


def ply_fields(source: CloudSource) -> list[tuple[str, np.dtype]]:
    """The vertex properties of a PLY written from ``source``: x, y, z double, the input's fields, segment."""
    fields = [("x", np.dtype("f8")), ("y", np.dtype("f8")), ("z", np.dtype("f8"))]
    for name, kind in source.fields:
        fields.append((name, ply_dtype(kind)))
    fields.append((segment_name(source.names), np.dtype("i4")))
    return fields


def ply_dtype(kind: np.dtype) -> np.dtype:
    kind = np.dtype(kind).newbyteorder("=")
    if kind == np.bool_:
        return np.dtype("u1")
    return kind if kind.str.lstrip("<>|=") in _PLY_NAMES else np.dtype("f8")


class PlyWriter:
    """A PLY whose vertex element is written a chunk at a time (``write``), then optionally the
    header lines and data of the other elements of a mesh, copied (``tail_lines``, ``copy_tail``)."""

    def __init__(self, path: Path, count: int, fields: list[tuple[str, np.dtype]], comments: tuple[str, ...] = (),
                 fmt: str = "binary_little_endian", tail_lines: tuple[str, ...] = ()):
        self.fmt = fmt
        endian = ">" if fmt == "binary_big_endian" else "<"
        self.dtype = np.dtype([(n, endian + np.dtype(t).str.lstrip("<>|=")) for n, t in fields])
        header = ["ply", f"format {fmt} 1.0", *comments, f"element vertex {count}"]
        header += [f"property {_PLY_NAMES[np.dtype(t).str.lstrip('<>|=')]} {n}" for n, t in fields]
        header += [*tail_lines, "end_header"]
        self._fh = open(path, "wb")
        self._fh.write(("\n".join(header) + "\n").encode("ascii"))

    def write(self, columns: dict[str, np.ndarray]) -> None:
        n = len(next(iter(columns.values())))
        rec = np.empty(n, dtype=self.dtype)
        for name in self.dtype.names:
            rec[name] = columns[name]
        if self.fmt == "ascii":
            np.savetxt(self._fh, _text_columns(rec), fmt="%s")
        else:
            rec.tofile(self._fh)

    def copy_tail(self, path: Path, offset: int) -> None:
        import shutil

        with open(path, "rb") as src:
            src.seek(offset)
            shutil.copyfileobj(src, self._fh, 16 << 20)

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> PlyWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _text_columns(rec: np.ndarray) -> np.ndarray:
    """ASCII PLY rows: floats in the shortest form that reads back exactly, integers as integers."""
    cols = []
    for name in rec.dtype.names:
        v = rec[name]
        cols.append(np.array([repr(float(x)) for x in v]) if v.dtype.kind == "f" else v.astype(str))
    return np.column_stack(cols) if cols else np.zeros((len(rec), 0), str)
