"""A small PIL plotting canvas for the report's figures: panels with ticks, labels, legends, colour bars.

matplotlib costs ~0.4 s CPU to import and ~0.15 s per figure to lay out, draw and encode; the
report's figures are a few rasters, lines and labels, which PIL draws in milliseconds. Sizes are
pixels of a 100 dpi figure (matplotlib's defaults: 10 pt text ≈ 14 px).
"""

from __future__ import annotations

import functools
import importlib.util
import io
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from PIL import Image, ImageColor, ImageDraw, ImageFont

Colour = tuple[int, int, int]
TEXT_PX, TITLE_PX, SMALL_PX = 14, 16, 11
TICK_PX, PAD_PX = 5, 4
BLACK: Colour = (0, 0, 0)
MINUS = "\u2212"  # a typographic minus, as matplotlib prints it


def rgb(colour: str | Colour) -> Colour:
    return ImageColor.getrgb(colour)[:3] if isinstance(colour, str) else tuple(int(c) for c in colour[:3])


@functools.lru_cache(maxsize=8)
def font(size_px: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    """DejaVu Sans (the system's, else matplotlib's copy), else Pillow's built-in font."""
    candidates = ["DejaVuSans.ttf"]
    spec = importlib.util.find_spec("matplotlib")  # locates the package without importing it
    if spec is not None and spec.submodule_search_locations:
        candidates.append(str(Path(spec.submodule_search_locations[0]) / "mpl-data/fonts/ttf/DejaVuSans.ttf"))
    for name in candidates:
        try:
            return ImageFont.truetype(name, size_px)
        except OSError:
            continue
    return ImageFont.load_default(size_px)


def nice_ticks(lo: float, hi: float, max_ticks: int = 8) -> np.ndarray:
    """Round tick positions in [lo, hi]: steps of 1, 2, 2.5 or 5 × 10^k (as matplotlib's default)."""
    if not (np.isfinite(lo) and np.isfinite(hi)) or hi <= lo:
        return np.array([lo]) if np.isfinite(lo) else np.zeros(0)
    raw = (hi - lo) / max(max_ticks - 1, 1)
    magnitude = 10.0 ** np.floor(np.log10(raw))
    step = next(m * magnitude for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * magnitude >= raw * (1 - 1e-9))
    first = np.ceil(lo / step - 1e-9) * step
    count = int(np.floor((hi - first) / step + 1e-9)) + 1
    return first + step * np.arange(count)


def tick_labels(ticks: np.ndarray) -> list[str]:
    """Shortest fixed-point labels that tell the ticks apart (typographic minus)."""
    if len(ticks) == 0:
        return []
    step = float(np.min(np.diff(ticks))) if len(ticks) > 1 else max(abs(float(ticks[0])), 1.0)
    decimals = next((d for d in range(7) if abs(round(step, d) - step) <= 1e-9 * max(step, 1.0)), 6)
    return [f"{0.0 if abs(t) < step * 1e-9 else t:.{decimals}f}".replace("-", MINUS) for t in ticks]


@dataclass(frozen=True)
class Panel:
    """A plotting area: its pixel box in the canvas and the data limits it shows (y up)."""

    left: int
    top: int
    width: int
    height: int
    xlim: tuple[float, float]
    ylim: tuple[float, float]

    @property
    def right(self) -> int:
        return self.left + self.width

    @property
    def bottom(self) -> int:
        return self.top + self.height

    def to_px(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Data → canvas pixel coordinates (column, row), as floats."""
        (x0, x1), (y0, y1) = self.xlim, self.ylim
        col = self.left + (np.asarray(x, float) - x0) * (self.width / (x1 - x0))
        row = self.top + (y1 - np.asarray(y, float)) * (self.height / (y1 - y0))
        return col, row

    def to_local_px(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Data → pixel coordinates inside the panel's own image (origin at its top-left)."""
        col, row = self.to_px(x, y)
        return col - self.left, row - self.top


def fit_equal(left: int, top: int, width: int, height: int, xlim, ylim) -> Panel:
    """The largest centred box inside the given one with 1 m in x as long as 1 m in y."""
    sx, sy = xlim[1] - xlim[0], ylim[1] - ylim[0]
    scale = min(width / sx, height / sy)
    w, h = max(1, int(round(sx * scale))), max(1, int(round(sy * scale)))
    return Panel(left + (width - w) // 2, top + (height - h) // 2, w, h, tuple(xlim), tuple(ylim))


class Canvas:
    """A white RGB image with drawing helpers in canvas pixels."""

    def __init__(self, width_px: int, height_px: int) -> None:
        self.image = Image.new("RGB", (width_px, height_px), "white")
        self.draw = ImageDraw.Draw(self.image)

    def text(self, xy, s: str, size_px: int = TEXT_PX, anchor: str = "la", fill: str | Colour = BLACK) -> None:
        self.draw.text((float(xy[0]), float(xy[1])), s, font=font(size_px), anchor=anchor, fill=rgb(fill))

    def text_width(self, s: str, size_px: int = TEXT_PX) -> int:
        return int(np.ceil(self.draw.textlength(s, font=font(size_px))))

    def vertical_text(self, centre, s: str, size_px: int = TEXT_PX, fill: str | Colour = BLACK) -> None:
        """Text read bottom to top, centred on ``centre`` (an axis label)."""
        f = font(size_px)
        left, top, right, bottom = f.getbbox(s)
        tile = Image.new("L", (right - left + 2, bottom - top + 2), 0)
        ImageDraw.Draw(tile).text((1 - left, 1 - top), s, font=f, fill=255)
        tile = tile.transpose(Image.Transpose.ROTATE_90)
        x, y = int(round(centre[0] - tile.width / 2)), int(round(centre[1] - tile.height / 2))
        self.image.paste(rgb(fill), (x, y, x + tile.width, y + tile.height), tile)

    def raster(self, panel: Panel, picture: np.ndarray | Image.Image) -> None:
        """An (height, width, 3) uint8 image (or a PIL image of the panel's size) filling the panel."""
        if isinstance(picture, np.ndarray):
            picture = Image.fromarray(np.ascontiguousarray(picture, np.uint8), "RGB")
        self.image.paste(picture, (panel.left, panel.top))

    def axes(self, panel: Panel, title: str = "", xlabel: str = "", ylabel: str = "", max_ticks: int = 8,
             title_px: int = TITLE_PX) -> None:
        """Frame, outward ticks with labels, axis labels and title around a panel."""
        d = self.draw
        d.rectangle((panel.left - 1, panel.top - 1, panel.right, panel.bottom), outline=BLACK)
        xt = nice_ticks(*panel.xlim, max_ticks)
        for t, label in zip(xt, tick_labels(xt)):
            col = float(panel.to_px(t, panel.ylim[0])[0])
            d.line((col, panel.bottom, col, panel.bottom + TICK_PX), fill=BLACK)
            self.text((col, panel.bottom + TICK_PX + PAD_PX), label, anchor="mt")
        yt = nice_ticks(*panel.ylim, max_ticks)
        widest = 0
        for t, label in zip(yt, tick_labels(yt)):
            row = float(panel.to_px(panel.xlim[0], t)[1])
            d.line((panel.left - 1 - TICK_PX, row, panel.left - 1, row), fill=BLACK)
            self.text((panel.left - TICK_PX - PAD_PX - 1, row), label, anchor="rm")
            widest = max(widest, self.text_width(label))
        if xlabel:
            self.text(((panel.left + panel.right) / 2, panel.bottom + TICK_PX + 2 * PAD_PX + TEXT_PX), xlabel, anchor="mt")
        if ylabel:
            x = panel.left - TICK_PX - 2 * PAD_PX - widest - TEXT_PX // 2 - 2
            self.vertical_text((x, (panel.top + panel.bottom) / 2), ylabel)
        if title:
            self.text(((panel.left + panel.right) / 2, panel.top - 7), title, size_px=title_px, anchor="md")

    def colour_bar(self, left: int, top: int, width: int, height: int, lut: np.ndarray, vmax: float,
                   label: str) -> None:
        """A vertical colour bar from 0 (bottom) to vmax (top) of a (256, 3) uint8 colour table."""
        levels = np.linspace(255, 0, height).round().astype(np.int64)
        self.image.paste(Image.fromarray(np.repeat(lut[levels][:, None, :], width, axis=1), "RGB"), (left, top))
        self.draw.rectangle((left - 1, top - 1, left + width, top + height), outline=BLACK)
        ticks = nice_ticks(0.0, vmax, 7)
        widest = 0
        for t, text in zip(ticks, tick_labels(ticks)):
            row = top + (1 - t / vmax) * (height - 1)
            self.draw.line((left + width, row, left + width + TICK_PX, row), fill=BLACK)
            self.text((left + width + TICK_PX + PAD_PX, row), text, anchor="lm")
            widest = max(widest, self.text_width(text))
        self.vertical_text((left + width + TICK_PX + 2 * PAD_PX + widest + TEXT_PX // 2 + 2, top + height / 2), label)

    def legend(self, panel: Panel, entries: list[tuple[str, str, str]]) -> None:
        """Upper-right legend; entries are (kind "line"|"dot", colour, label)."""
        if not entries:
            return
        row_px, sample_px = SMALL_PX + 6, 24
        width = sample_px + 14 + max(self.text_width(label, SMALL_PX) for _, _, label in entries)
        right, top = panel.right - 6, panel.top + 6
        left, bottom = right - width, top + 6 + row_px * len(entries)
        self.draw.rounded_rectangle((left, top, right, bottom), radius=3, fill=(255, 255, 255), outline=(204, 204, 204))
        for k, (kind, colour, label) in enumerate(entries):
            y = top + 4 + row_px * k + row_px / 2
            if kind == "line":
                self.draw.line((left + 6, y, left + 6 + sample_px, y), fill=rgb(colour), width=2)
            else:
                cx = left + 6 + sample_px / 2
                self.draw.ellipse((cx - 3.5, y - 3.5, cx + 3.5, y + 3.5), fill=rgb(colour))
            self.text((left + 10 + sample_px, y), label, size_px=SMALL_PX, anchor="lm")


def encode_png(image: Image.Image) -> bytes:
    """PNG bytes; zlib level 1: the figures are flat colours, a higher level saves little and costs more."""
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", compress_level=1)
    return buffer.getvalue()
