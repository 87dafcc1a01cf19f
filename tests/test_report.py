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


def test_scatter_by_colour_draws_each_point_once_in_its_colour():
    from matplotlib.colors import to_rgba
    from matplotlib.figure import Figure

    from toolkit.report_figures import SEGMENT_COLOURS, scatter_by_colour, segment_colours

    rng = np.random.default_rng(0)
    xy = rng.normal(size=(500, 2))
    labels = rng.integers(0, 40, 500)
    ax = Figure().subplots()
    scatter_by_colour(ax, xy, labels % len(SEGMENT_COLOURS), SEGMENT_COLOURS, 2.0, 3)
    drawn = [(c.get_offsets().data, c.get_facecolor()) for c in ax.collections]
    assert len(drawn) == len(np.unique(labels % len(SEGMENT_COLOURS)))  # one scatter per colour
    got = np.concatenate([np.column_stack([off, np.repeat(fc, len(off), 0)]) for off, fc in drawn])
    want = np.column_stack([xy, [to_rgba(c) for c in segment_colours(labels)]])
    order = lambda m: m[np.lexsort(m.T[::-1])]  # noqa: E731
    np.testing.assert_array_equal(order(got), order(want))
    assert all(c.get_zorder() == 3 for c in ax.collections)
    scatter_by_colour(ax, xy[:0], labels[:0], SEGMENT_COLOURS, 2.0, 3)  # nothing to draw
    assert len(ax.collections) == len(drawn)


def test_frame_origin_is_the_rounded_median(run):
    from toolkit.report import _frame

    _, ctx = run
    f = _frame(ctx)
    x0, y0 = np.floor(np.median(ctx.registration.points[:, :2], axis=0) / 100.0) * 100.0
    assert (f.x0, f.y0) == (x0, y0)
