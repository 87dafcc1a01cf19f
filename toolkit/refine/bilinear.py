"""Bilinear sampling of rasters at world points, shared by the refine searches and the ground step.

Each function performs the same floating-point operations, in the same order, as the plain numpy
expressions it replaces (noted per function), so results are bit-identical; the savings are in
memory traffic: flat 1D gathers instead of 2D fancy indexing, 1D compressions instead of row
compressions, weights computed once, products accumulated in place, and no compression at all
when every point falls inside the raster (the usual case).
"""

from __future__ import annotations

import numpy as np


def world_to_rows_cols(transform: tuple, xy: np.ndarray, row0: int = 0,
                       col0: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Fractional (row, col) of world points xy (N,2) on a window starting at (row0, col0): the
    operations of ``Grid.world_to_pixel`` followed by the subtraction of the window's origin."""
    row, col = rows_cols(transform, xy[:, 0], xy[:, 1])
    if row0:
        row -= row0
    if col0:
        col -= col0
    return row, col


def rows_cols(transform: tuple, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Grid.world_to_pixel`` of world coordinates given as two arrays of any (equal) shape."""
    a, b, c, d, e, f = transform
    det = a * e - b * d
    dx, dy = x - c, y - f
    row = (-d * dx + a * dy) / det - 0.5
    col = (e * dx - b * dy) / det - 0.5
    return row, col


def cells_inside(row: np.ndarray, col: np.ndarray, height: int,
                 width: int) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(floor(row), floor(col), inside) where ``inside`` marks the points whose four neighbouring
    pixels are all on a height × width raster; ``inside`` is None when every point is (told by the
    extremes first: four reductions instead of seven passes)."""
    r0, c0 = np.floor(row), np.floor(col)
    if len(r0) == 0 or (r0.min() >= 0 and c0.min() >= 0 and r0.max() < height - 1 and c0.max() < width - 1):
        return r0, c0, None
    inside = (r0 >= 0) & (c0 >= 0) & (r0 < height - 1) & (c0 < width - 1)
    return r0, c0, (None if inside.all() else inside)


def _corner_index(r0: np.ndarray, c0: np.ndarray, width: int | np.ndarray, origin: int | np.ndarray) -> np.ndarray:
    """Flat index of each top-left corner (whole numbers far below 2**53: exact in float64)."""
    at = r0 * width
    at += c0
    if np.ndim(origin) or origin:
        at += origin
    return at.astype(np.int64)


def interpolate(flat: np.ndarray, width: int, row: np.ndarray, col: np.ndarray, r0: np.ndarray,
                c0: np.ndarray, origin: int = 0) -> np.ndarray:
    """Values of a flattened raster with rows of ``width`` pixels at (row, col) (floors r0, c0, all
    inside) of a window whose top-left pixel is at flat index ``origin``; the operations of
    ``v00·(1-fr)·(1-fc) + v01·(1-fr)·fc + v10·fr·(1-fc) + v11·fr·fc`` (left to right)."""
    fr, fc = row - r0, col - c0
    gr, gc = 1 - fr, 1 - fc
    at = _corner_index(r0, c0, width, origin)
    out = flat.take(at)
    out *= gr
    out *= gc
    for offset, wr, wc in ((1, gr, fc), (width, fr, gc), (width + 1, fr, fc)):
        term = flat[offset:].take(at)            # = flat.take(at + offset)
        term *= wr
        term *= wc
        out += term
    return out


def interpolate_planes(planes: np.ndarray, width: int | np.ndarray, row: np.ndarray, col: np.ndarray,
                       r0: np.ndarray, c0: np.ndarray, origin: int | np.ndarray = 0) -> np.ndarray:
    """(M,F) values of F flattened rasters ``planes`` (F, n) at (row, col), as ``interpolate``; the
    operations of ``np.einsum("mk,mkf->mf", w, v)`` with corner weights
    w = [(1-fr)(1-fc), (1-fr)fc, fr(1-fc), fr·fc] (einsum sums the four corners in order).
    ``width`` and ``origin`` may be per point (several rasters stacked in one flat buffer)."""
    fr, fc = row - r0, col - c0
    gr, gc = 1 - fr, 1 - fc
    at = _corner_index(r0, c0, width, origin)
    weights = (gr * gc, gr * fc, fr * gc, fr * fc)
    if np.ndim(width) == 0:  # one width: shifted views of the plane instead of three more index arrays
        corners = ((0, at), (1, at), (width, at), (width + 1, at))
    else:
        corners = ((0, at), (0, at + 1), (0, at + width), (0, at + (width + 1)))
    out = np.empty((len(at), planes.shape[0]))
    for f, plane in enumerate(planes):
        acc = plane.take(at)
        acc *= weights[0]
        for (shift, index), weight in zip(corners[1:], weights[1:]):
            term = plane[shift:].take(index)
            term *= weight
            acc += term
        out[:, f] = acc
    return out
