"""The short table printed at the end of ``crossview run`` (and ``make demo``)."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table

from toolkit.metrics_model import RunMetrics

# Truth-free figures, shown first: (label, "|"-joined keys of the assessment figures, format)
STATUS_ROWS: tuple[tuple[str, str, str], ...] = (
    ("registered share, segments / points", "registered_share|registered_point_share", "{:.0%} / {:.0%}"),
    ("façade support (within {r:g} m of an outline)", "facade_support_share", "{:.0%}"),
    ("façade distance to an outline, median", "facade_distance_median_m", "{:.2f} m"),
    ("neighbour disagreement, median / share > {tol:g} m", "neighbour_gap_median_m|neighbour_disagree_share",
     "{:.2f} m / {:.0%}"),
    ("matching converged (iterations)", "bp_converged|bp_iterations", "{} ({})"),
    ("cameras bridged across route gaps", "bridged_camera_share", "{:.0%}"),
    ("route to a camera seeing a registered façade, p90", "camera_gap_p90_m", "{:.0f} m"),
    ("BA reprojection RMS, before / after", "ba_rms_before_px|ba_rms_after_px", "{:.2f} / {:.2f} px"),
    ("GPS residual of the cameras, median", "gps_residual_median_m", "{:.2f} m"),
)

# The evaluation's figures: (label, toolkit.metrics_model.KeyFigures attribute, unit)
SUMMARY_ROWS: tuple[tuple[str, str, str], ...] = (
    ("per-point error, horizontal median", "error_h_median_m", "m"),
    ("per-point error, horizontal mean", "error_h_mean_m", "m"),
    ("per-point error, 3D median", "error_3d_median_m", "m"),
    ("per-point error, 3D p95", "error_3d_p95_m", "m"),
    ("Chamfer 2D mean (paper metric)", "chamfer_2d_mean_m", "m"),
    ("Chamfer 3D mean (paper metric)", "chamfer_3d_mean_m", "m"),
    ("share of points paired", "paired_fraction", ""),
    ("segment match precision", "match_precision", ""),
    ("segment match recall", "match_recall", ""),
    ("camera centre error, median", "camera_median_m", "m"),
)


def print_summary(res, console: Console | None = None) -> None:
    console = console or Console()
    metrics = res.results.metrics
    figures = RunMetrics.of(metrics).key_figures()
    table = Table(title=f"crossview — {res.out_dir}", show_header=True, header_style="bold")
    table.add_column("measure")
    table.add_column("value", justify="right")
    assessment = getattr(res, "assessment", None)
    if assessment is not None:
        _status_rows(table, assessment)
    scale = getattr(getattr(res, "scene", None), "street_scale", None)
    if scale is not None:
        how = {"gps": "estimated from GPS", "assumed": "assumed (no GPS, no COLMAP model; set street_scale when "
               "not metric)", "matching": "from the façades against the over-view (no GPS)",
               "scene": "from scene.yaml", "recipe": "from the recipe"}[scale.source]
        est = f", estimate {scale.estimate:.4f}" if scale.estimate is not None and scale.estimate != scale.value else ""
        if scale.source == "gps" and (scale.matching or {}).get("estimate") is not None:
            how = f"{how}, checked against the over-view (matching estimate {scale.matching['estimate']:.4f})"
        table.add_row("street scale (frame units per metre)", f"{scale.value:.4f}{est} {how}")
    from toolkit.outputs import height_kind

    capture = getattr(res.results, "capture", None)
    if capture is not None and capture.step > 1:
        table.add_row("street points, analysed", f"{capture.cloud_points:,}, one in {capture.step}")

    if res.scene is not None and height_kind(res.scene, res.results.overview) == "relative":
        table.add_row("heights", "relative: no DSM or terrain model, street ground at 0 m")
    for label, name, unit in SUMMARY_ROWS:
        v = getattr(figures, name)
        if v is not None:
            table.add_row(label, f"{v:.3f} {unit}".strip())
    for step, seconds in res.timings.items():
        table.add_row(f"time: {step}", f"{seconds:.2f} s")
    console.print(table)
    for reason in assessment.reasons if assessment is not None else ():
        colour = "red" if assessment.status != "ok" else "yellow"
        console.print(f"[{colour}]{'reason' if assessment.status != 'ok' else 'concern'}[/] {reason}")
    if res.warnings:
        for w in res.warnings:
            console.print(f"[yellow]warning[/] {w}")
    if res.out_dir is not None:
        for name in ("report.html", "recording.rrd", "metrics.json", "registered.ply"):
            p = res.out_dir / name
            if p.exists():
                console.print(f"{name:14s} {p}")
        if (res.out_dir / "recording.rrd").exists():
            console.print(f"open the recording with: rerun {res.out_dir / 'recording.rrd'}")


def _status_rows(table: Table, assessment) -> None:
    """Status, confidence and the truth-free figures the run has (toolkit.status)."""
    f = assessment.figures
    style = "bold green" if assessment.status == "ok" else "bold red"
    table.add_row("status (no truth needed)", f"[{style}]{assessment.status}[/]")
    table.add_row("confidence", f"{assessment.confidence:.2f}")
    for label, keys, fmt in STATUS_ROWS:
        values = [f.get(k) for k in keys.split("|")]
        if any(v is None for v in values):
            continue
        values = ["yes" if v is True else "no" if v is False else v for v in values]
        text = label.format(r=f.get("facade_radius_m", 0), tol=f.get("neighbour_tol_m", 0))
        table.add_row(text, fmt.format(*values))
    table.add_section()
