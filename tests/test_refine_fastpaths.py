"""The refine stage's fast paths give the same bits as the plain numpy forms they replace."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from toolkit.refine.bilinear import cells_inside, interpolate, interpolate_planes, rows_cols, world_to_rows_cols
from toolkit.refine.columns import centred, column_means
from toolkit.refine.ground3d import GroundParams, HeightGrid, ground_step, prepare_ground, street_ground_normal
from toolkit.refine.search2d import OutlineField, SearchParams, search_segment
from toolkit.refine.transforms import rigid2d, rotation_between
from toolkit.types import Grid


def _wide_range(rng, shape):
    """Values whose sums round differently in another order (magnitudes over many decades)."""
    return rng.standard_normal(shape) * 10.0 ** rng.uniform(-6, 6, shape) + rng.uniform(-1e6, 1e6, shape[-1])


@pytest.mark.parametrize("k", [2, 3])
def test_column_means_and_centred_equal_numpy_bit_for_bit(k):
    rng = np.random.default_rng(20)
    for n in (1, 2, 7, 8, 9, 33, 1000, 4099):
        a = _wide_range(rng, (n, k))
        assert np.array_equal(column_means(a), a.mean(axis=0))
        q = centred(a)
        assert np.array_equal(q, a - a.mean(axis=0)) and q.flags.c_contiguous


def _plain_bilinear(arr, rc):
    """The plain definition: v00·(1-fr)·(1-fc) + v01·(1-fr)·fc + v10·fr·(1-fc) + v11·fr·fc."""
    r0, c0 = np.floor(rc[:, 0]).astype(np.int64), np.floor(rc[:, 1]).astype(np.int64)
    fr, fc = rc[:, 0] - r0, rc[:, 1] - c0
    return (arr[r0, c0] * (1 - fr) * (1 - fc) + arr[r0, c0 + 1] * (1 - fr) * fc
            + arr[r0 + 1, c0] * fr * (1 - fc) + arr[r0 + 1, c0 + 1] * fr * fc)


def test_bilinear_interpolation_equals_the_plain_formulas():
    rng = np.random.default_rng(21)
    g = Grid((0.5, 0.0, 300000.0, 0.0, -0.5, 4400050.0), 90, 70, "EPSG:32617")
    planes = _wide_range(rng, (3, 70, 90))
    xy = np.column_stack([rng.uniform(299995.0, 300050.0, 3000), rng.uniform(4400010.0, 4400055.0, 3000)])
    rc = g.world_to_pixel(xy)
    row, col = world_to_rows_cols(g.transform, xy)
    assert np.array_equal(np.column_stack([row, col]), rc)
    assert all(np.array_equal(u, v) for u, v in zip(rows_cols(g.transform, xy[:, 0], xy[:, 1]), (row, col)))
    r0, c0, inside = cells_inside(row, col, 70, 90)
    assert inside is not None and 0 < inside.sum() < len(xy)           # some points fall off the raster
    ok = inside
    got = interpolate(planes[0].ravel(), 90, row[ok], col[ok], r0[ok], c0[ok])
    assert np.array_equal(got, _plain_bilinear(planes[0], rc[ok]))
    # a window of the raster, addressed through its flat origin
    win = interpolate(planes[0].ravel(), 90, row[ok] - 3, col[ok] - 5, r0[ok] - 3, c0[ok] - 5, origin=3 * 90 + 5)
    assert np.array_equal(win, got)
    # three stacked fields: the einsum of the corner weights (what the Gauss-Newton step used)
    fr, fc = (row - r0)[ok, None], (col - c0)[ok, None]
    weights = np.concatenate([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], axis=1)
    at = (r0[ok].astype(np.int64) * 90 + c0[ok].astype(np.int64))[:, None] + np.array([0, 1, 90, 91])
    ref = np.einsum("mk,mkf->mf", weights, np.moveaxis(planes, 0, 2).reshape(-1, 3).take(at, axis=0))
    assert np.array_equal(interpolate_planes(planes.reshape(3, -1), 90, row[ok], col[ok], r0[ok], c0[ok]), ref)


def test_height_grid_sample_equals_the_plain_formula_and_is_nan_outside():
    rng = np.random.default_rng(22)
    g = Grid((0.5, 0.0, 0.0, 0.0, -0.5, 40.0), 60, 80, "EPSG:32617")
    h = _wide_range(rng, (80, 60))
    xy = np.column_stack([rng.uniform(-2, 32, 2000), rng.uniform(-2, 42, 2000)])
    got = HeightGrid(h, g).sample(xy)
    rc = g.world_to_pixel(xy)
    r0, c0 = np.floor(rc[:, 0]), np.floor(rc[:, 1])
    ok = (r0 >= 0) & (c0 >= 0) & (r0 < 79) & (c0 < 59)
    assert np.array_equal(got[ok], _plain_bilinear(h, rc[ok])) and np.isnan(got[~ok]).all()
    inner = xy[ok]
    assert np.array_equal(HeightGrid(h, g).sample(inner), got[ok])     # all inside: the no-compression path


def test_rotation_between_uses_numpys_cross_product():
    rng = np.random.default_rng(24)
    for _ in range(200):
        a, b = rng.normal(size=3), rng.normal(size=3)
        an, bn = a / np.linalg.norm(a), b / np.linalg.norm(b)
        v = np.cross(an, bn)
        s, c = np.linalg.norm(v), float(an @ bn)
        k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
        ang = np.arctan2(s, c)
        assert np.array_equal(rotation_between(a, b), np.eye(3) + np.sin(ang) * k + (1 - np.cos(ang)) * (k @ k))


def _ground(rng, n=3000):
    xy = rng.uniform(-20, 20, (n, 2))
    z = 3.0 + 0.02 * xy[:, 0] - 0.01 * xy[:, 1] + rng.normal(0, 0.05, n)
    normals = np.tile([0.02, -0.01, 1.0], (n, 1)) + rng.normal(0, 0.05, (n, 3))
    normals[rng.random(n) < 0.3] *= -1                               # some point down
    return np.column_stack([xy, z]), normals / np.linalg.norm(normals, axis=1, keepdims=True)


def test_ground_step_tilt_only_and_prepared_medians_match_the_full_step():
    rng = np.random.default_rng(25)
    g = Grid((0.5, 0.0, -40.0, 0.0, -0.5, 40.0), 160, 160, "EPSG:32617")
    rows, cols = np.mgrid[0:160, 0:160]
    wxy = g.pixel_to_world(rows.ravel(), cols.ravel())
    heights = HeightGrid((230.0 + wxy @ [0.03, 0.01]).reshape(160, 160) + rng.normal(0, 0.1, (160, 160)), g)
    pts, normals = _ground(rng)
    p = GroundParams()
    prep = prepare_ground(pts, normals, p)
    assert np.array_equal(prep.centre, np.median(pts, axis=0))
    flipped = normals * np.sign(normals[:, 2:3] + 1e-12)
    m = np.median(flipped[flipped[:, 2] >= np.cos(np.radians(p.normal_max_angle_deg))], axis=0)
    assert np.array_equal(street_ground_normal(pts, normals, p), m / np.linalg.norm(m))
    T = rigid2d(0.3, np.array([1.0, -2.0]))
    full = ground_step(pts, normals, T, heights, np.array([0, 0, 1.0]), np.nan, p, prepared=prep)
    tilt = ground_step(pts, normals, T, heights, np.array([0, 0, 1.0]), np.nan, p, prepared=prep, with_height=False)
    assert np.array_equal(full.R_z, tilt.R_z) and np.array_equal(full.centre, tilt.centre) and np.isnan(tilt.t_z)
    assert not np.array_equal(full.R_z, np.eye(3)) and np.isfinite(full.t_z)
    assert np.array_equal(ground_step(pts, normals, T, heights, np.array([0, 0, 1.0]), np.nan, p).R_z, full.R_z)


def test_clamped_outline_field_equals_the_exact_one_where_it_is_read():
    rng = np.random.default_rng(26)
    g = Grid((0.5, 0.0, 0.0, 0.0, -0.5, 60.0), 120, 120, "EPSG:32617")
    mask = np.zeros((120, 120), bool)
    mask[30:70, 40:95] = True
    mask[50:90, 20:45] = True
    exact, clamped = OutlineField(g, mask, 10, 20), OutlineField(g, mask, 10, 20, clamp_px=9)
    assert not np.array_equal(exact.sdf, clamped.sdf)                 # it is clamped far from the edge
    assert np.array_equal(exact.truncated(3.0), clamped.truncated(3.0))
    xy = g.pixel_to_world(rng.uniform(5, 125, 20000), rng.uniform(15, 145, 20000))
    assert np.array_equal(exact.sample_truncated(xy, 3.0), clamped.sample_truncated(xy, 3.0))
    inside_e, sg_e = exact.sample_with_gradient(xy)
    inside_c, sg_c = clamped.sample_with_gradient(xy)
    near = np.abs(sg_e[:, 0]) < 1.0
    assert np.array_equal(inside_e, inside_c) and np.array_equal(near, np.abs(sg_c[:, 0]) < 1.0)
    assert near.sum() > 1000 and np.array_equal(sg_e[near], sg_c[near])


def test_search_without_the_seed_cost_finds_the_same_transform():
    rng = np.random.default_rng(27)
    g = Grid((0.5, 0, 500000.0, 0, -0.5, 4400150.0), 300, 300, "EPSG:32617")
    lab = -np.ones((300, 300), np.int32)
    lab[50:101, 80:141] = 0
    rr, cc = np.nonzero(lab == 0)
    a, b = g.pixel_to_world(rr.min(), cc.min()), g.pixel_to_world(rr.max(), cc.max())
    south = np.column_stack([rng.uniform(a[0], b[0], 800), np.full(800, b[1] - 0.25)])
    west = np.column_stack([np.full(400, a[0] - 0.25), rng.uniform(b[1], a[1], 400)])
    world = np.vstack([south, west]) + rng.normal(0, 0.05, (1200, 2))
    street = world - [500000.0, 4400000.0]
    seed = rigid2d(np.radians(3.0), np.array([500000.0 + 1.5, 4400000.0 - 1.0]))
    box = ndimage.find_objects(lab + 1)[0]
    full = search_segment(street, seed, g, lab, 0, box, SearchParams())
    lean = search_segment(street, seed, g, lab, 0, box, SearchParams(), with_seed_cost=False)
    assert np.array_equal(full.T2d, lean.T2d) and full.cost_m == lean.cost_m and np.isnan(lean.seed_cost_m)
    assert full.seed_cost_m > full.cost_m


def _plain_gauss_newton(street_xy, T0, field, p, iterations=10):
    """The step as first written, one problem at a time (the reference for the batched one)."""
    T = T0.copy()
    for _ in range(iterations):
        xy = street_xy @ np.ascontiguousarray(T[:2, :2].T) + T[:2, 2]
        inside, sg = field.sample_with_gradient(xy)
        inside = np.ones(len(xy), bool) if inside is None else inside
        near = np.abs(sg[:, 0]) < p.inlier_m
        if np.count_nonzero(near) < 6:
            return None
        sg, xy = sg[near], xy[inside][near]
        c = xy.mean(axis=0)
        rx, ry = xy[:, 0] - c[0], xy[:, 1] - c[1]
        J = np.empty((len(sg), 3))
        J[:, 0] = sg[:, 1] * -ry + sg[:, 2] * rx
        J[:, 1:] = sg[:, 1:]
        H = J.T @ J
        H[np.diag_indices(3)] += 1e-6
        step = -np.linalg.solve(H, J.T @ sg[:, 0])
        if not np.all(np.isfinite(step)):
            return None
        R = rigid2d(step[0], np.zeros(2))
        R[:2, 2] = c - R[:2, :2] @ c + step[1:]
        T = R @ T
        if abs(step[0]) < 1e-6 and np.hypot(*step[1:]) < 1e-4:
            break
    c0 = (street_xy @ T0[:2, :2].T + T0[:2, 2]).mean(axis=0)
    c1 = (street_xy @ T[:2, :2].T + T[:2, 2]).mean(axis=0)
    dtheta = np.arctan2(T[1, 0], T[0, 0]) - np.arctan2(T0[1, 0], T0[0, 0])
    if np.hypot(*(c1 - c0)) > 2 * field.grid.gsd_m or abs(np.degrees(dtheta)) > 2 * p.rotation_step_deg:
        return None
    return T


def test_batched_searches_equal_one_search_at_a_time():
    from toolkit.refine.search2d import AllOutlines, search_segments
    from toolkit.refine.subpixel import gauss_newton_many

    rng = np.random.default_rng(28)
    g = Grid((0.5, 0, 500000.0, 0, -0.5, 4400150.0), 300, 300, "EPSG:32617")
    lab = -np.ones((300, 300), np.int32)
    lab[50:101, 80:141], lab[160:230, 40:90], lab[170:260, 180:250] = 0, 1, 2
    boxes = ndimage.find_objects(lab + 1)
    problems = []
    for k, box in enumerate(boxes * 3):
        rr, cc = box
        a, b = g.pixel_to_world(rr.start, cc.start), g.pixel_to_world(rr.stop - 1, cc.stop - 1)
        south = np.column_stack([rng.uniform(a[0], b[0], 300), np.full(300, b[1] - 0.25)])
        west = np.column_stack([np.full(200, a[0] - 0.25), rng.uniform(b[1], a[1], 200)])
        street = np.vstack([south, west]) + rng.normal(0, 0.05, (500, 2)) - [500000.0, 4400000.0]
        seed = rigid2d(np.radians(rng.uniform(-6, 6)), np.array([500000.0, 4400000.0]) + rng.uniform(-2, 2, 2))
        problems.append((street, seed, k if k < 3 else None, box))        # own fields, then shared ones
    outlines = AllOutlines(g, lab, 3.0)
    together = search_segments(problems, g, lab, SearchParams(), outlines)
    for prob, res in zip(problems, together):
        alone = search_segment(prob[0], prob[1], g, lab, prob[2], prob[3], SearchParams(), outlines)
        assert np.array_equal(alone.T2d, res.T2d) and alone.cost_m == res.cost_m
    # the batched step against the step as first written, over own and shared fields at once
    fields = [OutlineField(g, lab[30:130, 60:160] >= 0, 30, 60), outlines.field(30, 20, 280, 270, 3.0),
              outlines.field(140, 20, 280, 120, 3.0), OutlineField(g, lab[140:250, 20:110] == 1, 140, 20, 9)]
    cases = [(street, seed, fields[k % 4], SearchParams()) for k, (street, seed, _, _) in enumerate(problems)]
    cases += [(street, res.T2d @ rigid2d(0.002, np.array([0.2, -0.1])), fields[1], SearchParams())
              for (street, _, _, _), res in zip(problems, together)]
    batched = gauss_newton_many(cases)
    refs = [_plain_gauss_newton(*case) for case in cases]
    assert sum(r is not None for r in refs) >= 9                          # most steps are accepted
    assert all((r is None and b is None) or (r is not None and b is not None and np.array_equal(r, b))
               for r, b in zip(refs, batched))
