"""Point cloud I/O: PLY (binary/ascii, float64 kept), LAS/LAZ (laspy), PCD (Open3D).

``read_points`` returns (N,3) float64 and never silently drops rows: a file whose points cannot be
read whole, or that holds NaN/Inf coordinates, is a ``SceneError`` naming the file. A PLY or PCD
storing x, y, z as float32 with coordinates beyond ``FLOAT32_WARN_M`` gets a warning naming the
precision lost (float32 keeps 24 significant bits: 0.5 m steps at a 4.4e6 m northing).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from toolkit.errors import SceneError

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
CHUNK_BYTES = 64 << 20  # binary PLY records are read and written this many bytes at a time
FLOAT32_WARN_M = 1e5  # float32 steps are ~8 mm there, and grow with the coordinates
log = logging.getLogger("crossview.io")


def read_points(path: str | Path, with_colors: bool = False, allow_nonfinite: bool = False):
    """Read (N,3) float64 xyz (and (N,3) uint8 colours or None when ``with_colors``)."""
    path = Path(path)
    if not path.is_file():
        raise SceneError(f"{path}: file not found")
    if path.stat().st_size == 0:
        raise SceneError(f"{path}: file is empty")
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            xyz, rgb = _read_ply(path)
        elif suffix in (".las", ".laz"):
            xyz, rgb = _read_las(path)
        elif suffix == ".pcd":
            xyz, rgb = _read_o3d(path)
        else:
            raise SceneError(f"{path}: unsupported point cloud format {suffix!r} (use .ply, .las, .laz, .pcd)")
    except SceneError:
        raise
    except Exception as exc:  # corrupt or truncated files surface here from the parsers
        raise SceneError(f"{path}: cannot read point cloud ({type(exc).__name__}: {exc})") from exc
    if len(xyz) == 0:
        raise SceneError(f"{path}: point cloud has no points")
    if not allow_nonfinite and not np.isfinite(xyz).all():
        bad = int((~np.isfinite(xyz).all(axis=1)).sum())
        raise SceneError(f"{path}: {bad} points have NaN or Inf coordinates")
    _warn_float32(path, xyz)
    return (xyz, rgb) if with_colors else xyz


def _warn_float32(path: Path, xyz: np.ndarray) -> None:
    if coordinate_dtype(path) != "f4":
        return
    top = max(float(np.nanmax(xyz)), -float(np.nanmin(xyz)))
    if top > FLOAT32_WARN_M:
        step_mm = float(np.spacing(np.float32(top))) * 1000
        log.warning("%s: x, y, z are stored as float32 with coordinates up to %.0f m, which keeps them only "
                    "to %g mm steps; write them as double, or relative to a local origin", path, top, step_mm)


def coordinate_dtype(path: Path) -> str | None:
    """The numpy dtype code ('f4', 'f8', ...) of x in a PLY or PCD header; None for other formats."""
    suffix = path.suffix.lower()
    head = _header_lines(path, b"end_header" if suffix == ".ply" else b"DATA")
    if suffix == ".ply":
        return next((_PLY_TYPES.get(w[1]) for w in head if w[:1] == ["property"] and w[-1] == "x"), None)
    if suffix == ".pcd":
        fields = {w[0].upper(): w[1:] for w in head if w}
        names = fields.get("FIELDS", [])
        if "x" in names and len(fields.get("SIZE", [])) == len(fields.get("TYPE", [])) == len(names):
            i = names.index("x")
            return f"{fields['TYPE'][i].lower()}{fields['SIZE'][i]}"
    return None


def _header_lines(path: Path, last: bytes, max_lines: int = 256) -> list[list[str]]:
    """The words of each header line up to the one starting with ``last`` (binary data never read)."""
    lines = []
    with open(path, "rb") as fh:
        for _ in range(max_lines):
            line = fh.readline(4096)
            lines.append(line.decode("ascii", "replace").split())
            if not line or line.startswith(last):
                break
    return lines


def _read_ply(path: Path):
    with open(path, "rb") as fh:
        if fh.readline().strip() != b"ply":
            raise SceneError(f"{path}: not a PLY file (missing 'ply' magic)")
        fmt, elements, current = None, [], None
        while True:
            line = fh.readline()
            if not line:
                raise SceneError(f"{path}: PLY header has no end_header")
            words = line.decode("ascii", "replace").split()
            if not words or words[0] in ("comment", "obj_info"):
                continue
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                current = [words[1], int(words[2]), []]
                elements.append(current)
            elif words[0] == "property":
                if current is None:
                    raise SceneError(f"{path}: PLY property before any element")
                if words[1] == "list":
                    current[2].append((words[-1], None))
                else:
                    current[2].append((words[2], _PLY_TYPES[words[1]]))
            elif words[0] == "end_header":
                break
        if not elements or elements[0][0] != "vertex":
            raise SceneError(f"{path}: PLY has no leading vertex element")
        _, count, props = elements[0]
        if any(t is None for _, t in props):
            raise SceneError(f"{path}: PLY vertex element has list properties")
        names = [n for n, _ in props]
        if not {"x", "y", "z"} <= set(names):
            raise SceneError(f"{path}: PLY vertices lack x, y, z")
        if fmt in ("binary_little_endian", "binary_big_endian"):
            endian = "<" if fmt == "binary_little_endian" else ">"
            return _read_binary_vertices(fh, path, np.dtype([(n, endian + t) for n, t in props]), count)
        if fmt == "ascii":
            table = np.loadtxt(fh, max_rows=count, ndmin=2, dtype=np.float64)
            if table.shape[0] < count or table.shape[1] < len(names):
                raise SceneError(f"{path}: PLY is truncated ({table.shape[0]} of {count} vertices)")
            data = {n: table[:, i] for i, n in enumerate(names)}
        else:
            raise SceneError(f"{path}: unknown PLY format {fmt!r}")
    xyz = np.stack([np.asarray(data[c], dtype=np.float64) for c in "xyz"], axis=1)
    rgb = None
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([np.asarray(data[c]) for c in ("red", "green", "blue")], axis=1).astype(np.uint8)
    return xyz, rgb


def _read_binary_vertices(fh, path: Path, dtype: np.dtype, count: int):
    """Vertex records read straight into the (N,3) float64 / (N,3) uint8 outputs, CHUNK_BYTES at a
    time: the temporary memory stays bounded whatever the cloud size (no whole-file byte copy)."""
    import os

    available = (os.fstat(fh.fileno()).st_size - fh.tell()) // dtype.itemsize
    if available < count:  # checked before allocating: a corrupt count must not allocate gigabytes
        raise SceneError(f"{path}: PLY is truncated ({available} of {count} vertices)")
    names = set(dtype.names)
    xyz = np.empty((count, 3), dtype=np.float64)
    rgb = np.empty((count, 3), dtype=np.uint8) if {"red", "green", "blue"} <= names else None
    step = max(1, CHUNK_BYTES // dtype.itemsize)
    for start in range(0, count, step):
        k = min(step, count - start)
        raw = fh.read(dtype.itemsize * k)
        if len(raw) < dtype.itemsize * k:
            raise SceneError(f"{path}: PLY is truncated ({start + len(raw) // dtype.itemsize} of {count} vertices)")
        rec = np.frombuffer(raw, dtype=dtype, count=k)
        for axis, c in enumerate("xyz"):
            xyz[start:start + k, axis] = rec[c]
        if rgb is not None:
            for axis, c in enumerate(("red", "green", "blue")):
                rgb[start:start + k, axis] = rec[c]
    return xyz, rgb


def check_las_header(path: Path) -> None:
    """Sanity-check the LAS public header block before laspy parses it.

    laspy trusts the header: a corrupt VLR count makes it loop for minutes, a corrupt point count
    makes it allocate gigabytes. The fields checked are at fixed offsets in every LAS version.
    """
    import struct

    size = path.stat().st_size
    with open(path, "rb") as fh:
        head = fh.read(227)
    if len(head) < 227 or head[:4] != b"LASF":
        raise SceneError(f"{path}: not a LAS/LAZ file (missing 'LASF' signature or header too short)")
    major, minor = head[24], head[25]
    header_size, offset, n_vlrs = struct.unpack_from("<HII", head, 94)
    fmt, record_len = head[104] & 0x3F, struct.unpack_from("<H", head, 105)[0]
    if major != 1 or minor > 4 or fmt > 10 or not (227 <= header_size <= offset <= size):
        raise SceneError(f"{path}: corrupt LAS header (version {major}.{minor}, point format {fmt}, "
                         f"header {header_size} B, point data at {offset} of {size} B)")
    if n_vlrs * 54 > offset - header_size or record_len < 20:
        raise SceneError(f"{path}: corrupt LAS header ({n_vlrs} VLRs, record length {record_len})")


def _read_las(path: Path, chunk_points: int = 2_000_000):
    """LAS/LAZ read in chunks (bounded temporary memory) into float64 arrays."""
    import laspy

    check_las_header(path)
    size = path.stat().st_size
    with laspy.open(path) as reader:
        hdr = reader.header
        n = int(hdr.point_count)
        if path.suffix.lower() == ".las":
            need = hdr.offset_to_point_data + n * hdr.point_format.size
            if need > size:
                raise SceneError(f"{path}: LAS is truncated or corrupt (header claims {n} points, "
                                 f"{need} bytes; the file has {size})")
        elif n > 8 * size:  # LAZ never compresses below ~1 bit per point
            raise SceneError(f"{path}: LAZ header is corrupt (claims {n} points in {size} bytes)")
        xyz = np.empty((n, 3), dtype=np.float64)
        has_rgb = "red" in hdr.point_format.dimension_names
        rgb16 = np.empty((n, 3), dtype=np.uint16) if has_rgb else None
        start = 0
        for chunk in reader.chunk_iterator(chunk_points):
            k = len(chunk)
            xyz[start:start + k, 0], xyz[start:start + k, 1], xyz[start:start + k, 2] = chunk.x, chunk.y, chunk.z
            if has_rgb:
                rgb16[start:start + k] = np.stack([chunk.red, chunk.green, chunk.blue], axis=1)
            start += k
    if start != n:
        raise SceneError(f"{path}: LAS/LAZ is truncated ({start} of {n} points)")
    rgb = None
    if rgb16 is not None:
        rgb = (rgb16 >> 8).astype(np.uint8) if rgb16.max(initial=0) > 255 else rgb16.astype(np.uint8)
    return xyz, rgb


def _read_o3d(path: Path):
    from toolkit.open3d_import import open3d
    o3d = open3d()

    pcd = o3d.io.read_point_cloud(str(path))
    xyz = np.asarray(pcd.points, dtype=np.float64)
    rgb = (np.asarray(pcd.colors) * 255).round().astype(np.uint8) if pcd.has_colors() else None
    return xyz, rgb


def write_ply(path: str | Path, xyz: np.ndarray, colors: np.ndarray | None = None,
              extra: dict[str, np.ndarray] | None = None) -> None:
    """Binary little-endian PLY with double x, y, z (exact float64), optional uchar colours."""
    xyz = np.asarray(xyz, dtype=np.float64)
    extra = {name: np.asarray(arr) for name, arr in (extra or {}).items()}
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8)
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    for name, arr in extra.items():
        fields.append((name, arr.dtype.newbyteorder("<").str))
    rev = {v: k for k, v in _PLY_TYPES.items() if k in ("char", "uchar", "short", "ushort", "int", "uint", "float", "double")}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(xyz)}"]
    for name, dt in fields:
        header.append(f"property {rev[np.dtype(dt).str.lstrip('<|>')]} {name}")
    header.append("end_header")
    dtype = np.dtype(fields)
    step = max(1, CHUNK_BYTES // dtype.itemsize)
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        for start in range(0, len(xyz), step):  # records built a chunk at a time: bounded memory
            part = slice(start, start + step)
            data = np.empty(len(xyz[part]), dtype=dtype)
            data["x"], data["y"], data["z"] = xyz[part, 0], xyz[part, 1], xyz[part, 2]
            if colors is not None:
                data["red"], data["green"], data["blue"] = colors[part, 0], colors[part, 1], colors[part, 2]
            for name, arr in extra.items():
                data[name] = arr[part]
            data.tofile(fh)
