"""The crop atlas of unary.distance_map: each crop holds its segment's truncated, quantised boundary
distance (and its erosions), computed on a tight box around the boundary; checked against the same
quantities computed directly on the whole crop."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage as ndi

from toolkit.matching.atlas import SCALE, build_atlas


def _blobs(seed: int, shape=(160, 200), n=7) -> tuple[np.ndarray, tuple[np.ndarray, ...]]:
    """A label image of n rectangles (one touching the grid edge) and each one's boundary pixels."""
    rng = np.random.default_rng(seed)
    label = np.full(shape, -1, np.int32)
    for p in range(n):
        h, w = rng.integers(4, 30, 2)
        r, c = (0, rng.integers(0, shape[1] - w)) if p == 0 else (rng.integers(0, shape[0] - h), rng.integers(0, shape[1] - w))
        label[r:r + h, c:c + w] = p
    boundary = []
    for p in range(n):
        m = label == p
        edge = m & ~ndi.binary_erosion(m)
        boundary.append(np.argwhere(edge))
    return label, tuple(boundary)


def _crop_reference(boundary: np.ndarray, origin: np.ndarray, size: np.ndarray, truncate: float, e: int) -> np.ndarray:
    """Truncated boundary distance on the whole crop, eroded by e, quantised (the plain definition)."""
    m = np.ones(tuple(size), bool)
    m[boundary[:, 0] - origin[0], boundary[:, 1] - origin[1]] = False
    v = np.minimum(ndi.distance_transform_edt(m), truncate)
    if e > 0:
        v = ndi.grey_erosion(v, size=(2 * e + 1, 2 * e + 1), mode="nearest")
    return np.rint(v * (SCALE / truncate)).astype(np.uint8)


@pytest.mark.parametrize("seed,truncate,reach,erosions", [(0, 10.0, 30, (0, 2, 4)), (1, 7.5, 12, (0, 1, 3)),
                                                           (2, 3.0, 5, (0, 2, 6)), (3, 12.0, 3, (0, 1))])
def test_every_crop_equals_its_whole_crop_definition(seed, truncate, reach, erosions):
    label, boundary = _blobs(seed)
    atlas = build_atlas(label, boundary + (np.zeros((0, 2), np.int64),), truncate, reach, erosions=erosions)
    for k, e in enumerate(erosions):
        plane = atlas.levels[k].reshape(atlas.n_bins, -1, atlas.stride)[0]
        for p, b in enumerate(boundary):
            (r0, c0), (h, w) = atlas.place[p], atlas.size[p]
            np.testing.assert_array_equal(plane[r0:r0 + h, c0:c0 + w],
                                          _crop_reference(b, atlas.origin[p], atlas.size[p], truncate, e))
        (r0, c0), (h, w) = atlas.place[-1], atlas.size[-1]   # a segment without boundary: all plateau
        assert (plane[r0:r0 + h, c0:c0 + w] == SCALE).all()
