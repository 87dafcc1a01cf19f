"""The foot of report.html: links to the run's other files, only to those its folder holds (a run
with ``--no-rerun`` has no recording, a partial recipe no transforms or COLMAP model)."""

from __future__ import annotations

import html
from pathlib import Path

# (file or folder of the run folder, what it holds), in the order the links are shown
LINKED: tuple[tuple[str, str], ...] = (
    ("metrics.json", "full numbers"),
    ("transforms.json", "per-segment transforms"),
    ("registered.laz", "registered cloud"),
    ("registered.ply", "registered cloud (PLY)"),
    ("sparse", "adjusted COLMAP model"),
    ("recording.rrd", "every intermediate (open with rerun recording.rrd)"),
    ("run.log", "log"),
)


def present_links(out_dir: Path) -> list[tuple[str, str]]:
    """(href, label) of the ``LINKED`` entries that exist in ``out_dir``."""
    out_dir = Path(out_dir)
    return [(f"{name}/" if (out_dir / name).is_dir() else name, label)
            for name, label in LINKED if (out_dir / name).exists()]


def links_html(out_dir: Path) -> str:
    """The ``<p class="foot">`` line of links, or '' when the folder holds none of them."""
    parts = [f'{html.escape(label)}: <a href="{html.escape(href)}">{html.escape(href)}</a>'
             for href, label in present_links(out_dir)]
    return f'<p class="foot">{" · ".join(parts)}</p>' if parts else ""
