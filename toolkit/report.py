"""report.html: a self-contained page a person would rather look at than metrics.json.

``write_report(out_dir, context)`` writes ``out_dir/report.html`` with its PNG figures embedded
(base64) and also saved in ``out_dir/figures/``. Every part of ``ReportContext`` may be None (a
partial recipe): the page shows what exists and says what is missing.
"""

from __future__ import annotations

import base64
import html
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from toolkit.metrics_model import RunMetrics, SegmentRow
from toolkit.types import (
    Matches,
    Metrics,
    OverviewSegments,
    Registration,
    Scene,
    SegmentTransforms,
    StreetSegments,
)


@dataclass
class ReportContext:
    recipe_text: str | None = None
    scene: Scene | None = None
    overview: OverviewSegments | None = None
    street: StreetSegments | None = None
    matches: Matches | None = None
    transforms: SegmentTransforms | None = None
    registration: Registration | None = None
    metrics: Metrics | None = None
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    street_points: np.ndarray | None = None  # input street frame, input order (a large cloud: its analysis rows)
    analysis_step: int = 1                    # the run analysed one street point in this many
    cloud_points: int | None = None           # the street cloud's points (None: len(street_points))
    title: str | None = None
    assessment: Any = None  # toolkit.status.Assessment: the truth-free self-assessment, shown first


# (label, toolkit.metrics_model.KeyFigures attributes, format)
HEADLINE: tuple[tuple[str, tuple[str, ...], str], ...] = (
    ("Chamfer 3D mean ± std", ("chamfer_3d_mean_m", "chamfer_3d_std_m"), "{:.2f} ± {:.2f} m"),
    ("Chamfer 2D mean ± std", ("chamfer_2d_mean_m", "chamfer_2d_std_m"), "{:.2f} ± {:.2f} m"),
    ("points paired (3D)", ("paired_fraction",), "{:.0%}"),
    ("error vs truth, horizontal median", ("error_h_median_m",), "{:.2f} m"),
    ("error vs truth, 3D p95", ("error_3d_p95_m",), "{:.2f} m"),
    ("points within 1 m (horizontal)", ("within_1m_h",), "{:.0%}"),
    ("match precision / recall", ("match_precision", "match_recall"), "{:.0%} / {:.0%}"),
    ("camera centre error, median", ("camera_median_m",), "{:.2f} m"),
)


# Truth-free figures of the self-assessment: (label, "|"-joined figure keys, format)
ASSESSMENT_CARDS: tuple[tuple[str, str, str], ...] = (
    ("street segments / points registered", "registered_share|registered_point_share", "{:.0%} / {:.0%}"),
    ("façade points on an over-view outline", "facade_support_share", "{:.0%}"),
    ("façade distance to an outline, median", "facade_distance_median_m", "{:.2f} m"),
    ("neighbour disagreement, median", "neighbour_gap_median_m", "{:.2f} m"),
    ("neighbour pairs disagreeing", "neighbour_disagree_share", "{:.0%}"),
    ("segments matched / vote confidence", "matched_share|match_confidence_mean", "{:.0%} / {:.2f}"),
    ("matching converged (iterations)", "bp_converged|bp_iterations", "{} ({})"),
    ("points outside the over-view data", "outside_grid_share", "{:.1%}"),
    ("camera spread, median / p95", "camera_spread_median_m|camera_spread_p95_m", "{:.2f} / {:.2f} m"),
    ("cameras bridged across route gaps", "bridged_camera_share", "{:.0%}"),
    ("route to a camera seeing a registered façade, p90", "camera_gap_p90_m", "{:.0f} m"),
    ("BA reprojection RMS, before / after", "ba_rms_before_px|ba_rms_after_px", "{:.2f} / {:.2f} px"),
    ("GPS residual of the cameras, median", "gps_residual_median_m", "{:.2f} m"),
)


def write_report(out_dir: Path, context: ReportContext) -> Path:
    from toolkit import report_figures as F
    from toolkit.report_canvas import encode_png

    out_dir = Path(out_dir)
    fig_dir = out_dir / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    c = context
    metrics = RunMetrics.of(c.metrics)
    per_point = c.metrics.per_point_error_m if c.metrics is not None else None
    rows = list(metrics.segments or []) or _segment_rows(c)
    frame = _frame(c)
    missing: list[str] = []
    figures: list[tuple[str, bytes, str, str]] = []  # (file, PNG bytes, title, caption)

    def add(name: str, image, title: str, caption: str, why_missing: str) -> None:
        if image is None:
            missing.append(f"{title}: {why_missing}")
            return
        png = encode_png(image)
        (fig_dir / name).write_bytes(png)
        figures.append((name, png, title, caption))

    add("top_view.png", F.top_views(c.street_points, c.street, c.registration, c.overview, frame),
        "Top view, before and after", "Street points coloured by street segment (grey: ground and "
        "clutter). Left: the input cloud levelled (up = +z) in its own frame. Right: the registered "
        "cloud in the scene CRS over the over-view building segments.", "no street cloud and no registration")
    add("matches.png", F.matches_view(c.street, c.overview, c.matches, c.registration, rows, frame),
        "Segment matches", "Each matched street segment (registered façade points) is linked to the "
        "centroid of its over-view segment; green/red when the scene's truth says right/wrong.",
        "needs street segments, over-view segments, matches and a registration")
    add("error_map.png", F.error_map(c.registration, per_point, c.overview, frame),
        "Per-point error map", "3D distance of every registered point from its true position "
        "(colour scale clipped at the 95th percentile).", "needs a registration and truth/street_points.npy")
    add("error_histogram.png", F.error_histograms(metrics), "Error distribution (cf. paper Fig. 8)",
        "Distances of the mutually nearest pairs between the registered cloud and the reference cloud "
        f"(pairs beyond {_cutoff_m(metrics):g} m ignored), and errors against the truth.",
        "needs evaluate metrics with a reference cloud or truth")

    page = _page(c, metrics, rows, figures, missing, out_dir)
    path = out_dir / "report.html"
    path.write_text(page, encoding="utf-8")
    return path


# --- content ----------------------------------------------------------------------------------
def _frame(c: ReportContext):
    from toolkit.report_figures import Frame

    if c.registration is not None and len(c.registration.points):
        pts = c.registration.points
        # column by column: the same medians, ~2x faster than along axis 0 of the strided (N,2) view
        x0, y0 = np.floor(np.array([np.median(pts[:, 0]), np.median(pts[:, 1])]) / 100.0) * 100.0
        return Frame(float(x0), float(y0))
    if c.overview is not None:
        _a, _, cx, _, e, f = c.overview.grid.transform
        return Frame(cx, f + e * c.overview.grid.height)
    return Frame(0.0, 0.0)


def _cutoff_m(metrics: RunMetrics) -> float:
    return 10 if metrics.cutoff_m is None else metrics.cutoff_m


def _segment_rows(c: ReportContext) -> list[SegmentRow]:
    """Rows from matches/transforms when the metrics have none (no evaluate step)."""
    if c.street is None:
        return []
    rows = []
    for s in range(len(c.street)):
        m = int(c.matches.segment_match[s]) if c.matches is not None else None
        rows.append(SegmentRow(
            index=s, id=int(c.street.ids[s]),
            n_points=int((c.street.point_labels == s).sum()),
            overview_id=int(c.overview.ids[m]) if (m is not None and m >= 0 and c.overview is not None) else None,
            match_cost=float(c.matches.cost[s]) if c.matches is not None else None,
            match_confidence=float(c.matches.confidence[s]) if c.matches is not None else None,
            refine_valid=bool(c.transforms.valid[s]) if c.transforms is not None else None,
            refine_cost=float(c.transforms.cost[s]) if c.transforms is not None else None,
        ))
    return rows


def _fmt(v: Any, spec: str = "{:.2f}") -> str:
    if v is None:
        return "—"
    if isinstance(v, bool):
        return "✓" if v else "✗"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return spec.format(float(v)) if np.isfinite(v) else "—"
    return html.escape(str(v))


def _assessment(assessment: Any) -> str:
    """Status, confidence, reasons and the figures of the self-assessment (empty without one)."""
    if assessment is None:
        return ""
    f = assessment.figures
    ok = assessment.status == "ok"
    cards = [f'<div class="card"><div class="v {"good" if ok else "bad"}">{html.escape(assessment.status)}</div>'
             f'<div class="l">status</div></div>',
             f'<div class="card"><div class="v">{assessment.confidence:.2f}</div><div class="l">confidence</div></div>']
    for label, keys, fmt in ASSESSMENT_CARDS:
        parts = [f.get(k) for k in keys.split("|")]
        if any(v is None for v in parts):
            continue
        parts = ["yes" if v is True else "no" if v is False else v for v in parts]
        cards.append(f'<div class="card"><div class="v">{html.escape(fmt.format(*parts))}</div>'
                     f'<div class="l">{html.escape(label)}</div></div>')
    reasons = "".join(f'<li class="{"warn" if ok else "bad"}">{html.escape(r)}</li>' for r in assessment.reasons)
    return ("<h2>Self-assessment (no truth needed)</h2>"
            '<div class="cards">' + "".join(cards) + "</div>" + (f"<ul>{reasons}</ul>" if reasons else "") +
            '<p class="note">Measured from the outputs alone (façades against the over-view outlines, '
            "neighbouring transforms against each other, cameras against GPS): "
            "see docs/status.md; every figure is in metrics.json under <code>assessment</code>.</p>")


def _headline(metrics: RunMetrics) -> str:
    figures = metrics.key_figures()
    cards = []
    for label, names, fmt in HEADLINE:
        parts = [getattr(figures, name) for name in names]
        if any(v is None for v in parts):
            continue
        cards.append(f'<div class="card"><div class="v">{html.escape(fmt.format(*parts))}</div>'
                     f'<div class="l">{html.escape(label)}</div></div>')
    if not cards:
        return ('<p class="missing">No metrics against a reference cloud or truth: the recipe has no evaluate '
                "step, or it had nothing to compare with.</p>")
    html_cards = '<div class="cards">' + "".join(cards) + "</div>"
    paired = figures.paired_fraction
    if paired is not None:
        html_cards += (f'<p class="note">{paired:.0%} of the street points found a mutually nearest reference '
                       f'point within {_cutoff_m(metrics):g} m, and the Chamfer numbers describe those '
                       "points alone. Different densities keep this share low even for a perfect registration, "
                       "and misplaced points simply stop pairing: compare the share between runs, and read the "
                       "errors against the truth when the scene has it.</p>")
    return html_cards


SEGMENT_COLUMNS = (
    ("id", "street segment", "{}"), ("n_points", "points", "{}"), ("overview_id", "over-view match", "{}"),
    ("match_cost", "match cost", "{:.3f}"), ("match_confidence", "confidence", "{:.2f}"),
    ("refine_valid", "refined", ""), ("refine_cost", "refine cost", "{:.3f}"),
    ("true_building", "true building", "{}"), ("correct", "correct", ""),
    ("error_mean_m", "mean error (m)", "{:.2f}"), ("error_median_m", "median error (m)", "{:.2f}"),
)


def _segment_table(rows: list[SegmentRow]) -> str:
    if not rows:
        return '<p class="missing">No street segments (the recipe has no street step).</p>'
    cols = [col for col in SEGMENT_COLUMNS if any(getattr(r, col[0]) is not None for r in rows)]
    head = "".join(f"<th>{html.escape(t)}</th>" for _, t, _ in cols)
    body = []
    for r in rows:
        cls = "" if r.correct is None else (' class="ok"' if r.correct else ' class="bad"')
        cells = "".join(f"<td>{_fmt(getattr(r, k), f) if f else _fmt(getattr(r, k))}</td>" for k, _, f in cols)
        body.append(f"<tr{cls}>{cells}</tr>")
    return f'<div class="scroll"><table class="seg"><tr>{head}</tr>{"".join(body)}</table></div>'


def _timings_table(timings: dict[str, float], metrics: RunMetrics) -> str:
    t = dict(timings or metrics.timings_s or {})
    if not t:
        return '<p class="missing">No timings recorded.</p>'
    total = sum(t.values()) or 1.0
    rows = "".join(
        f'<tr><td>{html.escape(k)}</td><td class="num">{v:.2f} s</td>'
        f'<td class="barcell"><div class="bar" style="width:{100 * v / total:.1f}%"></div></td></tr>'
        for k, v in t.items())
    return f'<table class="timing"><tr><th>step</th><th>time</th><th></th></tr>{rows}' \
           f'<tr><td><b>sum of steps</b></td><td class="num"><b>{total:.2f} s</b></td><td></td></tr></table>'


WIDE_FIGURES = ("top_view.png", "error_histogram.png")


def _figure_html(name: str, png: bytes, title: str, caption: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    wide = " wide" if name in WIDE_FIGURES else ""
    return (f'<figure class="fig{wide}"><h3>{html.escape(title)}</h3><img alt="{html.escape(title)}" '
            f'src="data:image/png;base64,{data}"><figcaption>{html.escape(caption)} '
            f'<a href="figures/{name}">{name}</a></figcaption></figure>')


def _title(c: ReportContext) -> str:
    import yaml

    recipe_name = None
    try:
        doc = yaml.safe_load(c.recipe_text) if c.recipe_text else None
        recipe_name = doc.get("name") if isinstance(doc, dict) else None
    except yaml.YAMLError:
        pass
    scene_name = c.scene.name if c.scene is not None else None
    if recipe_name and scene_name:
        return f"{recipe_name} on {scene_name}"
    return str(recipe_name or scene_name or "run")


def _page(c: ReportContext, metrics: RunMetrics, rows: list[SegmentRow], figures, missing: list[str],
          out_dir: Path) -> str:
    from toolkit.report_links import links_html

    name = c.title or _title(c)
    scene_line = (f"scene <code>{html.escape(str(c.scene.root))}</code> · CRS {html.escape(c.scene.crs)}"
                  if c.scene is not None else "no scene")
    counts = []
    if c.street_points is not None:
        n = c.cloud_points if c.cloud_points is not None else len(c.street_points)
        counts.append(f"{n:,} street points" + (f" (analysed one in {c.analysis_step})" if c.analysis_step > 1 else ""))
    if c.street is not None:
        counts.append(f"{len(c.street)} street segments")
    if c.overview is not None:
        counts.append(f"{len(c.overview)} over-view segments ({html.escape(c.overview.source or '?')})")
    if c.matches is not None:
        counts.append(f"{int((c.matches.segment_match >= 0).sum())} matched")
    notes = list(metrics.notes or [])
    warn = list(c.warnings or metrics.warnings or [])
    parts = [
        f"<h1>crossview report — {html.escape(name)}</h1>",
        f'<p class="sub">{scene_line}<br>{" · ".join(counts) or "nothing computed"}</p>',
        _assessment(c.assessment),
        "<h2>Results</h2>", _headline(metrics),
        "<h2>Figures</h2>", '<div class="figs">', *(_figure_html(*f) for f in figures), "</div>",
    ]
    if missing:
        parts.append('<div class="missing"><b>Not shown:</b><ul>' +
                     "".join(f"<li>{html.escape(m)}</li>" for m in missing) + "</ul></div>")
    parts += ["<h2>Segments</h2>", _segment_table(rows),
              "<h2>Timings</h2>", _timings_table(c.timings, metrics)]
    if warn or notes:
        parts.append("<h2>Warnings and notes</h2><ul>" +
                     "".join(f'<li class="warn">{html.escape(w)}</li>' for w in warn) +
                     "".join(f"<li>{html.escape(n)}</li>" for n in notes) + "</ul>")
    parts += ["<h2>Recipe (resolved)</h2>",
              f"<pre>{html.escape(c.recipe_text)}</pre>" if c.recipe_text else '<p class="missing">No recipe text.</p>',
              links_html(out_dir)]
    return _TEMPLATE.replace("{title}", html.escape(f"crossview — {name}")).replace("{body}", "\n".join(parts))


_TEMPLATE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{title}</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;max-width:1320px;
padding:18px 28px;color:#222;background:#fafafa}
h1{font-size:1.6em;margin:.2em 0}h2{border-bottom:2px solid #dde;padding-bottom:3px;margin-top:1.6em}
h3{margin:.2em 0 .4em}.sub{color:#555}
.cards{display:flex;flex-wrap:wrap;gap:10px}.card{background:#fff;border:1px solid #dde;border-radius:8px;
padding:10px 14px;min-width:170px;box-shadow:0 1px 2px #0001}.card .v{font-size:1.45em;font-weight:600;color:#1f4e79}
.card .l{font-size:.85em;color:#666}.card .v.good{color:#2e7d32}.card .v.bad{color:#c62828}
li.bad{color:#c62828;font-weight:600}
.figs{display:grid;grid-template-columns:1fr 1fr;gap:14px}.figs .wide{grid-column:1 / span 2}
figure{background:#fff;border:1px solid #dde;border-radius:8px;margin:0;padding:10px 14px}
figure img{max-width:100%;height:auto;display:block}figcaption{color:#555;font-size:.9em;margin-top:4px}
table{border-collapse:collapse;background:#fff;font-size:.9em}td,th{border:1px solid #dde;padding:3px 8px;text-align:right}
th{background:#eef2f7}tr.ok td{background:#eef8ee}tr.bad td{background:#fbeaea}
.scroll{max-height:480px;overflow:auto;display:inline-block}
.timing td:first-child{text-align:left}.barcell{width:320px}.bar{background:#4c72b0;height:11px;border-radius:3px}
.missing{color:#8a5a00;background:#fff6e0;border:1px solid #f0d9a0;border-radius:6px;padding:6px 12px}
li.warn{color:#8a5a00}pre{background:#fff;border:1px solid #dde;padding:10px;overflow:auto;font-size:.85em}
.note{color:#444;font-size:.9em;max-width:900px}
.foot{color:#666;font-size:.85em;margin-top:2em}
</style></head><body>
{body}
</body></html>
"""
