"""report.html: figures, tables, partial pipelines, and a real render in headless Chromium."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from plugins.evaluate_chamfer import Chamfer
from toolkit.io.cloud import write_ply
from toolkit.observe import NullObserver
from toolkit.report import ReportContext, write_report
from toolkit.types import (
    Grid,
    Matches,
    OverviewSegments,
    Registration,
    Scene,
    SceneFiles,
    SegmentTransforms,
    StreetSegments,
)

CHROMIUM = Path("/usr/bin/chromium")
E0, N0 = 500_000.0, 4_400_000.0
RECTS = [(10, 10, 30, 25), (45, 8, 70, 30), (12, 45, 35, 70), (50, 48, 75, 72)]  # local x0, y0, x1, y1


def _facade_points(rng, rect, per_m: int = 6) -> np.ndarray:
    x0, y0, x1, y1 = rect
    edges = [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
    pts = []
    for (ax, ay), (bx, by) in edges:
        n = int(np.hypot(bx - ax, by - ay) * per_m)
        t = rng.uniform(0, 1, n)
        pts.append(np.column_stack([ax + t * (bx - ax), ay + t * (by - ay), rng.uniform(0, 8, n)]))
    return np.concatenate(pts)


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A hand-made registered scene: 4 buildings, 4 street segments (one matched wrongly)."""
    tmp = tmp_path_factory.mktemp("scene")
    rng = np.random.default_rng(0)
    grid = Grid((0.5, 0.0, E0, 0.0, -0.5, N0 + 90.0), 180, 180, "EPSG:32617")
    label_image = np.full((180, 180), -1, np.int32)
    for k, (x0, y0, x1, y1) in enumerate(RECTS):
        label_image[int((90 - y1) / 0.5):int((90 - y0) / 0.5), int(x0 / 0.5):int(x1 / 0.5)] = k
    overview = OverviewSegments(
        grid=grid, label_image=label_image, ids=np.arange(4, dtype=np.int64) + 10,
        boundary_px=tuple(np.zeros((1, 2), np.int32) for _ in RECTS),
        centroids=np.array([[E0 + (a + c) / 2, N0 + (b + d) / 2] for a, b, c, d in RECTS]),
        polygons=(None,) * 4, ground_height=np.zeros(4), ground_normal=np.tile([0.0, 0, 1], (4, 1)),
        source="overview.osm")
    facades = [_facade_points(rng, r) for r in RECTS]
    ground = np.column_stack([rng.uniform(0, 90, 3000), rng.uniform(0, 90, 3000), np.zeros(3000)])
    true_local = np.concatenate(facades + [ground])
    labels = np.concatenate([np.full(len(f), k) for k, f in enumerate(facades)] + [np.full(3000, -1)]).astype(np.int32)
    true = true_local + [E0, N0, 30.0]
    # street input frame: rotated by 40° and shifted; registration = truth + a growing drift
    th = np.deg2rad(40)
    R = np.array([[np.cos(th), -np.sin(th), 0], [np.sin(th), np.cos(th), 0], [0, 0, 1]])
    street_pts = (true_local - 45) @ R.T
    drift = np.column_stack([true_local[:, 0] * 0.02, true_local[:, 1] * 0.01, np.zeros(len(true))])
    registered = true + drift + rng.normal(0, 0.05, true.shape)
    write_ply(tmp / "lidar.ply", true + rng.normal(0, 0.02, true.shape))
    np.save(tmp / "street_points.npy", true)
    scene = Scene(root=tmp, name="hand-made", crs="EPSG:32617",
                  files=SceneFiles(truth_lidar=tmp / "lidar.ply", truth_street_points=tmp / "street_points.npy"))
    S = len(RECTS)
    street = StreetSegments(
        origin=np.zeros(3), up_rotation=np.eye(3), point_labels=labels, carrier=labels,
        ids=np.arange(S, dtype=np.int64) + 100, boundary_xy=tuple(np.zeros((1, 2)) for _ in RECTS),
        centroids=np.zeros((S, 2)), extent_m=np.ones(S), ground_z=np.zeros(S),
        ground_normal=np.tile([0.0, 0, 1], (S, 1)))
    matches = Matches(edge_label=np.zeros(0, int), segment_match=np.array([0, 1, 3, -1]),
                      confidence=np.array([1.0, 0.75, 0.5, 0.0]), T2d=np.tile(np.eye(3), (S, 1, 1)),
                      cost=np.array([0.1, 0.2, 0.6, 1.0]), energy=1.0, energy_trace=np.ones(3),
                      iterations=3, converged=True)
    transforms = SegmentTransforms(T=np.tile(np.eye(4), (S, 1, 1)), valid=np.array([True, True, True, False]),
                                   cost=np.array([0.3, 0.4, 0.9, np.nan]), confidence=np.ones(S))
    registration = Registration(points=registered, image_names=(), R=np.zeros((0, 3, 3)), t=np.zeros((0, 3)),
                                point_segment=labels)
    metrics = Chamfer()(registration, scene, NullObserver(), matches=matches, street=street,
                        overview=overview, transforms=transforms)
    ctx = ReportContext(
        recipe_text="recipe: 1\nname: hand\nsteps:\n  evaluate: {use: evaluate.chamfer}\n", scene=scene,
        overview=overview, street=street, matches=matches, transforms=transforms, registration=registration,
        metrics=metrics, timings={"overview": 0.5, "street": 2.0, "match": 1.25, "evaluate": 0.3},
        warnings=["refine: segment 103 rejected"], street_points=street_pts)
    out = tmp_path_factory.mktemp("out")
    return write_report(out, ctx), ctx


def test_report_embeds_all_figures_and_tables(run):
    path, ctx = run
    text = path.read_text()
    assert path.name == "report.html"
    figs = sorted(p.name for p in (path.parent / "figures").glob("*.png"))
    assert figs == ["error_histogram.png", "error_map.png", "matches.png", "top_view.png"]
    for name in figs:
        assert (path.parent / "figures" / name).stat().st_size > 10_000
    assert len(re.findall(r'src="data:image/png;base64,', text)) == 4
    assert "Not shown" not in text
    # segment table: one row per street segment, the unmatched one shows a dash
    table = text[text.index('<table class="seg">'):]
    table = table[:table.index("</table>")]
    assert table.count("<tr") == 1 + len(ctx.street)
    assert "✗" in table  # segment 103 was not refined
    for step in ctx.timings:
        assert f"<td>{step}</td>" in text
    assert "refine: segment 103 rejected" in text
    assert "evaluate.chamfer" in text  # the recipe
    chamfer = ctx.metrics.values["chamfer"]["3d"]
    assert f"{chamfer['mean_m']:.2f} ± {chamfer['std_m']:.2f} m" in text


def test_partial_pipeline_says_what_is_missing(tmp_path):
    path = write_report(tmp_path, ReportContext(recipe_text="recipe: 1\n", timings={"overview": 1.0}))
    text = path.read_text()
    assert "Not shown" in text and "no street cloud and no registration" in text
    assert "No metrics" in text and "No street segments" in text
    assert "data:image/png" not in text
    assert list((tmp_path / "figures").glob("*.png")) == []


def test_report_without_truth_or_evaluate(run, tmp_path):
    _, ctx = run
    partial = ReportContext(recipe_text="x", scene=ctx.scene, overview=ctx.overview, street=ctx.street,
                            matches=ctx.matches, transforms=ctx.transforms, registration=ctx.registration,
                            street_points=ctx.street_points)
    text = write_report(tmp_path, partial).read_text()
    assert len(re.findall(r"data:image/png;base64,", text)) == 2  # top view and matches
    assert "Per-point error map: needs a registration" in text
    table = text[text.index('<table class="seg">'):]
    assert "match cost" in table and "true building" not in table[:table.index("</table>")]


@pytest.mark.skipif(not CHROMIUM.exists(), reason="headless Chromium (Debian package chromium) not installed")
def test_report_renders_in_chromium(run):
    import matplotlib.image as mpimg

    path, _ = run
    shot = path.parent / "report_screenshot.png"
    cmd = [str(CHROMIUM), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           "--window-size=1400,2600", f"--screenshot={shot}", path.resolve().as_uri()]
    subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    assert shot.is_file()
    img = mpimg.imread(shot)[..., :3]
    assert img.shape[0] >= 2000 and img.shape[1] >= 1300
    # The figures are on screen: many distinct colours, and the over-view segment blue of the top view.
    q = (img * 255).astype(np.uint8).reshape(-1, 3)
    assert len(np.unique(q[::7], axis=0)) > 500
    blue = np.all(np.abs(q.astype(int) - [0xB9, 0xC7, 0xD9]) <= 3, axis=1).mean()
    assert blue > 0.005
    keep = Path("/tmp/crossview_report_screenshot.png")
    shutil.copy(shot, keep)


def _pixel_of(panel, x, y):
    """The plain definition: the pixel whose square holds (x, y), or None outside the panel."""
    (x0, x1), (y0, y1) = panel.xlim, panel.ylim
    col = int(np.floor((x - x0) / (x1 - x0) * panel.width))
    row = int(np.floor((y1 - y) / (y1 - y0) * panel.height))
    return (row, col) if 0 <= col < panel.width and 0 <= row < panel.height else None


def test_rasterised_points_keep_the_topmost_point_of_each_pixel():
    from toolkit.point_raster import largest_value, topmost
    from toolkit.report_canvas import Panel

    rng = np.random.default_rng(1)
    panel = Panel(40, 25, 17, 11, (-3.0, 5.0), (-2.0, 4.0))
    xy = rng.uniform([-4.0, -3.0], [6.0, 5.0], (3000, 2))  # some fall outside the panel
    priority = rng.integers(0, 9, len(xy))
    values = rng.normal(size=len(xy))
    want_top = np.full((panel.height, panel.width), -1)
    want_largest = np.full((panel.height, panel.width), np.nan)
    for (x, y), p, v in zip(xy, priority, values):
        pixel = _pixel_of(panel, x, y)
        if pixel is not None:
            want_top[pixel] = max(want_top[pixel], p)
            want_largest[pixel] = v if np.isnan(want_largest[pixel]) else max(want_largest[pixel], v)
            col, row = panel.to_local_px(x, y)  # the panel's drawing coordinates agree
            assert (int(np.floor(row)), int(np.floor(col))) == pixel
    np.testing.assert_array_equal(topmost(panel, xy, priority), want_top)
    np.testing.assert_array_equal(largest_value(panel, xy, values), want_largest)


def test_dilate_max_is_the_block_maximum():
    from toolkit.point_raster import dilate_max

    image = np.random.default_rng(2).integers(-1, 20, (9, 13))
    for size in (1, 2, 3):
        want = np.array([[image[max(r - size + 1, 0):r + 1, max(c - size + 1, 0):c + 1].max()
                          for c in range(image.shape[1])] for r in range(image.shape[0])])
        np.testing.assert_array_equal(dilate_max(image, size), want)


def test_overview_mask_looks_up_each_pixel_centre(run):
    from toolkit.point_raster import overview_mask
    from toolkit.report_canvas import Panel

    _, ctx = run
    ov = ctx.overview
    a, _, c, _, e, f = ov.grid.transform
    panel = Panel(0, 0, 23, 19, (-12.0, 101.0), (-7.0, 95.0))  # wider than the 90 m over-view raster
    got = overview_mask(panel, ov, E0, N0)
    (x0, x1), (y0, y1) = panel.xlim, panel.ylim
    for row in range(panel.height):
        for col in range(panel.width):
            x = E0 + x0 + (col + 0.5) * (x1 - x0) / panel.width
            y = N0 + y1 - (row + 0.5) * (y1 - y0) / panel.height
            i, j = int(np.floor((y - f) / e)), int(np.floor((x - c) / a))
            inside = 0 <= i < ov.label_image.shape[0] and 0 <= j < ov.label_image.shape[1]
            assert got[row, col] == (int(ov.label_image[i, j] >= 0) if inside else -1)
    assert {-1, 0, 1} <= set(np.unique(got).tolist())


def test_nice_ticks_are_round_and_labelled_apart():
    from toolkit.report_canvas import MINUS, nice_ticks, tick_labels

    rng = np.random.default_rng(3)
    for lo, span in zip(rng.uniform(-500, 500, 200), 10.0 ** rng.uniform(-2, 3, 200)):
        ticks = nice_ticks(lo, lo + span, 8)
        assert 3 <= len(ticks) <= 8
        assert ticks[0] >= lo - 1e-9 * span and ticks[-1] <= lo + span + 1e-9 * span
        steps = np.diff(ticks)
        np.testing.assert_allclose(steps, steps[0], rtol=1e-9)
        mantissa = steps[0] / 10.0 ** np.floor(np.log10(steps[0]))
        assert min(abs(mantissa - m) for m in (1, 2, 2.5, 5, 10)) < 1e-6
        labels = tick_labels(ticks)
        assert len(set(labels)) == len(labels)
        np.testing.assert_allclose([float(s.replace(MINUS, "-")) for s in labels], ticks, atol=1e-6 * span)
    assert tick_labels(nice_ticks(-200.0, 250.0)) == [f"{MINUS}200", f"{MINUS}100", "0", "100", "200"]


def test_levelled_xy_is_the_street_levelling(run):
    from toolkit.report_figures import levelled_xy

    _, ctx = run
    th = 0.7
    R = np.array([[np.cos(th), -np.sin(th), 0.1], [np.sin(th), np.cos(th), -0.2], [0.05, 0.1, 1.0]])
    street = type(ctx.street)(**{**ctx.street.__dict__, "origin": np.array([3.0, -4.0, 1.5]), "up_rotation": R})
    pts = np.random.default_rng(4).normal(0, 50, (500, 3))
    np.testing.assert_allclose(levelled_xy(street, pts), street.level(pts)[:, :2], rtol=0, atol=1e-9)


def test_error_colours_follow_matplotlib_inferno_r():
    import matplotlib

    from toolkit.point_raster import inferno_r_lut

    want = np.asarray(matplotlib.colormaps["inferno_r"](np.arange(256))[:, :3]) * 255
    assert np.abs(inferno_r_lut().astype(float) - want).max() <= 8


def test_frame_origin_is_the_rounded_median(run):
    from toolkit.report import _frame

    _, ctx = run
    f = _frame(ctx)
    x0, y0 = np.floor(np.median(ctx.registration.points[:, :2], axis=0) / 100.0) * 100.0
    assert (f.x0, f.y0) == (x0, y0)
