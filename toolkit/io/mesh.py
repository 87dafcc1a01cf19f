"""Wavefront OBJ meshes for ``crossview apply``: vertices (``v``) and vertex normals (``vn``)
replaced, every other line (faces, texture coordinates, groups, materials) copied verbatim.

A ``vn`` is turned with the map of the first vertex a face pairs it with (``f v/vt/vn``); a normal
no face uses, with the first vertex's. The whole file is read into memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from toolkit.errors import SceneError


@dataclass(frozen=True)
class ObjMesh:
    lines: tuple[str, ...]     # every line, without its newline
    v_line: np.ndarray         # (V,) line of each vertex
    xyz: np.ndarray            # (V,3) float64
    v_rest: tuple[str, ...]    # what follows x y z on each vertex line (w, or r g b), verbatim
    vn_line: np.ndarray        # (M,) line of each vertex normal
    vn: np.ndarray             # (M,3)
    vn_vertex: np.ndarray      # (M,) vertex a face first pairs each normal with (−1: none)


def read_obj(path: Path) -> ObjMesh:
    try:
        lines = tuple(Path(path).read_text(encoding="utf-8", errors="replace").splitlines())
    except OSError as exc:
        raise SceneError(f"{path}: cannot read ({exc.strerror or exc})") from exc
    v_line, xyz, rest, vn_line, vn, pairs = [], [], [], [], [], []
    for i, line in enumerate(lines):
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "v":
                v_line.append(i)
                xyz.append([float(w) for w in words[1:4]])
                rest.append(" ".join(words[4:]))
            elif words[0] == "vn":
                vn_line.append(i)
                vn.append([float(w) for w in words[1:4]])
            elif words[0] == "f":
                pairs += _face_pairs(words[1:], len(xyz), len(vn))
        except (ValueError, IndexError) as exc:
            raise SceneError(f"{path}: line {i + 1}: not a valid OBJ {words[0]!r} line ({line.strip()[:60]!r})") from exc
    if not xyz or any(len(p) != 3 for p in xyz):
        raise SceneError(f"{path}: OBJ has no vertices with x, y, z")
    first = np.full(len(vn), -1, np.int64)
    for v, n in reversed(pairs):      # reversed: the first pairing written last wins
        if 0 <= n < len(vn) and 0 <= v < len(xyz):
            first[n] = v
    return ObjMesh(lines, np.asarray(v_line), np.asarray(xyz, np.float64), tuple(rest), np.asarray(vn_line, np.int64),
                   np.asarray(vn, np.float64).reshape(-1, 3), first)


def _face_pairs(corners: list[str], n_v: int, n_vn: int) -> list[tuple[int, int]]:
    """(vertex, normal) 0-based index pairs of a face's ``v/vt/vn`` corners (negative: relative)."""
    out = []
    for corner in corners:
        parts = corner.split("/")
        if len(parts) < 3 or not parts[2]:
            continue
        v, n = int(parts[0]), int(parts[2])
        out.append((v - 1 if v > 0 else n_v + v, n - 1 if n > 0 else n_vn + n))
    return out


def write_obj(path: Path, mesh: ObjMesh, xyz: np.ndarray, vn: np.ndarray, comment: str) -> None:
    lines = list(mesh.lines)
    for i, (x, y, z), rest in zip(mesh.v_line, xyz, mesh.v_rest):
        lines[i] = f"v {x:.6f} {y:.6f} {z:.6f}" + (f" {rest}" if rest else "")
    for i, (x, y, z) in zip(mesh.vn_line, vn):
        lines[i] = f"vn {x:.6f} {y:.6f} {z:.6f}"
    Path(path).write_text("\n".join([f"# {comment}", *lines]) + "\n", encoding="utf-8")
