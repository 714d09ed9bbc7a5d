"""Labelled heatmap pictures as uint8 RGB arrays, drawn with numpy and Pillow only.

Pillow is already installed with TensorBoard (one of its requirements), so pictures cost the
core no new dependency; matplotlib stays in the ``plots`` extra. A picture is one panel: a
title, the map with its origin at the lower left, three ticks per axis with the axis names,
and a colour bar with its range on the right (or a legend of the discrete values).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from PIL import Image as PILImage
from PIL import ImageDraw, ImageFont

VIRIDIS = np.array(
    [
        [68, 1, 84],
        [71, 44, 122],
        [59, 81, 139],
        [44, 113, 142],
        [33, 144, 141],
        [39, 173, 129],
        [92, 200, 99],
        [170, 220, 50],
        [253, 231, 37],
    ],
    dtype=np.float64,
)
"""matplotlib's viridis at 9 evenly spaced points (perceptually uniform, readable in grey)."""
COOLWARM = np.array([[59, 76, 192], [141, 176, 254], [221, 221, 221], [244, 154, 123], [180, 4, 38]], dtype=np.float64)
"""A diverging map (blue, grey, red), for signed quantities such as a torque."""
CATEGORIES = np.array(
    [
        [31, 119, 180],
        [255, 127, 14],
        [44, 160, 44],
        [214, 39, 40],
        [148, 103, 189],
        [140, 86, 75],
        [227, 119, 194],
        [127, 127, 127],
    ],
    dtype=np.uint8,
)
"""matplotlib's tab10 (first 8), for Discrete actions."""
EMPTY = np.array([205, 205, 205], dtype=np.uint8)
"""Cells without a value (e.g. no held-out transition fell in them)."""
BACKGROUND, INK, DOT = (255, 255, 255), (20, 20, 20), (215, 25, 28)

MAP_SIZE = 256  # pixels of a 2-D map's side; a 1-D map is MAP_SIZE wide and STRIP_HEIGHT high
STRIP_HEIGHT = 48
LEFT, TOP, BOTTOM, BAR_GAP, BAR_WIDTH, RIGHT = 58, 8, 40, 12, 14, 84
FONT_SIZE = 11
LINE_HEIGHT = FONT_SIZE + 3


@dataclass(frozen=True)
class Axis:
    """One axis of a map.

    :param name: the label drawn under (x) or above (y) the axis, units included
    :param low: coordinate of the first cell's outer edge
    :param high: coordinate of the last cell's outer edge
    """

    name: str
    low: float
    high: float


def _font() -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=FONT_SIZE)
    except TypeError:  # Pillow < 10.1: the fixed bitmap font
        return ImageFont.load_default()


def _wrap(text: str, width: float, draw: ImageDraw.ImageDraw, font: ImageFont.ImageFont | ImageFont.FreeTypeFont) -> list[str]:
    """``text`` broken at spaces into lines at most ``width`` pixels wide (a longer word stands alone)."""
    lines: list[str] = []
    for word in text.split(" "):
        if lines and draw.textlength(f"{lines[-1]} {word}", font=font) <= width:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines


def number(value: float) -> str:
    """A tick label: 3 significant digits."""
    return f"{value:.3g}"


def colorize(values: np.ndarray, low: float, high: float, colormap: np.ndarray = VIRIDIS) -> np.ndarray:
    """Map values linearly onto a colormap; NaN cells get :data:`EMPTY`.

    :param values: any shape ``S``
    :param low: the value drawn with the first colour (and below)
    :param high: the value drawn with the last colour (and above)
    :param colormap: (n, 3) anchor colours, interpolated linearly
    :return: ``S + (3,)`` uint8 RGB
    """
    span = high - low if high > low else 1.0
    unit = np.clip((np.nan_to_num(values, nan=low) - low) / span, 0.0, 1.0)
    position = unit * (len(colormap) - 1)
    lower = np.minimum(np.floor(position).astype(int), len(colormap) - 2)
    fraction = (position - lower)[..., None]
    rgb = colormap[lower] * (1 - fraction) + colormap[lower + 1] * fraction
    rgb = np.rint(rgb).astype(np.uint8)
    rgb[np.isnan(values)] = EMPTY
    return rgb


class _Canvas:
    """A panel being drawn: the map's pixel box and coordinate transforms."""

    def __init__(self, x_axis: Axis, y_axis: Axis | None, title: Sequence[str]) -> None:
        self.x_axis, self.y_axis = x_axis, y_axis
        self.font = _font()
        self.width, self.height = MAP_SIZE, MAP_SIZE if y_axis is not None else STRIP_HEIGHT
        total_width = LEFT + self.width + BAR_GAP + BAR_WIDTH + RIGHT
        measure = ImageDraw.Draw(PILImage.new("RGB", (1, 1)))
        lines = [wrapped for line in title for wrapped in _wrap(line, total_width - 8, measure, self.font)]
        self.top = TOP + LINE_HEIGHT * (len(lines) + int(y_axis is not None))
        self.image = PILImage.new("RGB", (total_width, self.top + self.height + BOTTOM), BACKGROUND)
        self.draw = ImageDraw.Draw(self.image)
        for i, line in enumerate(lines):
            self.draw.text((4, 4 + i * LINE_HEIGHT), line, fill=INK, font=self.font)

    def pixel(self, x: np.ndarray, y: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Pixel positions of coordinates (y = None: the strip's middle)."""
        px = LEFT + (x - self.x_axis.low) / (self.x_axis.high - self.x_axis.low) * self.width
        if y is None or self.y_axis is None:
            return px, np.full_like(px, self.top + self.height / 2)
        return px, self.top + (self.y_axis.high - y) / (self.y_axis.high - self.y_axis.low) * self.height

    def paste_map(self, rgb: np.ndarray) -> None:
        """Draw an (ny, nx, 3) map, row 0 at the bottom (the lowest y)."""
        cells = PILImage.fromarray(np.ascontiguousarray(rgb[::-1]))
        self.image.paste(cells.resize((self.width, self.height), PILImage.Resampling.NEAREST), (LEFT, self.top))

    def axes(self) -> None:
        """The frame, three ticks per axis and the axis names."""
        right, bottom = LEFT + self.width, self.top + self.height
        self.draw.rectangle((LEFT - 1, self.top - 1, right, bottom), outline=INK)
        x = self.x_axis
        for fraction in (0.0, 0.5, 1.0):
            px = LEFT + fraction * self.width
            self.draw.line((px, bottom, px, bottom + 3), fill=INK)
            self.draw.text(
                (px, bottom + 5), number(x.low + fraction * (x.high - x.low)), fill=INK, font=self.font, anchor="ma"
            )
        self.draw.text((LEFT + self.width / 2, bottom + 7 + FONT_SIZE), x.name, fill=INK, font=self.font, anchor="ma")
        if self.y_axis is not None:
            y = self.y_axis
            for fraction in (0.0, 0.5, 1.0):
                py = bottom - fraction * self.height
                self.draw.line((LEFT - 4, py, LEFT - 1, py), fill=INK)
                label = number(y.low + fraction * (y.high - y.low))
                self.draw.text((LEFT - 6, py), label, fill=INK, font=self.font, anchor="rm")
            self.draw.text((4, self.top - LINE_HEIGHT - 2), f"y: {y.name}", fill=INK, font=self.font)

    def colour_bar(self, low: float, high: float, colormap: np.ndarray, labels: tuple[str, str, str] | None = None) -> None:
        """A vertical colour bar from ``low`` (bottom) to ``high`` (top), labelled at both ends and the middle."""
        left = LEFT + self.width + BAR_GAP
        ramp = colorize(np.linspace(high, low, self.height)[:, None], low, high, colormap)
        bar = PILImage.fromarray(np.ascontiguousarray(np.repeat(ramp, BAR_WIDTH, axis=1)))
        self.image.paste(bar, (left, self.top))
        self.draw.rectangle((left - 1, self.top - 1, left + BAR_WIDTH, self.top + self.height), outline=INK)
        texts = labels or (number(high), number((low + high) / 2), number(low))
        for text, py in zip(texts, (self.top, self.top + self.height / 2, self.top + self.height), strict=True):
            self.draw.text((left + BAR_WIDTH + 4, py), text, fill=INK, font=self.font, anchor="lm")

    def legend(self, names: Sequence[str], colours: np.ndarray) -> None:
        """A legend of discrete values: a colour square and a name per line, right of the map."""
        left = LEFT + self.width + BAR_GAP
        for i, (name, colour) in enumerate(zip(names, colours, strict=True)):
            py = self.top + i * (FONT_SIZE + 4)
            self.draw.rectangle((left, py, left + 9, py + 9), fill=tuple(int(c) for c in colour), outline=INK)
            self.draw.text((left + 13, py + 5), name, fill=INK, font=self.font, anchor="lm")

    def array(self) -> np.ndarray:
        return np.asarray(self.image, dtype=np.uint8).copy()


def heatmap(
    values: np.ndarray,
    x_axis: Axis,
    y_axis: Axis | None,
    title: Sequence[str],
    colormap: np.ndarray = VIRIDIS,
    value_range: tuple[float, float] | None = None,
    log_scale: bool = False,
) -> np.ndarray:
    """A labelled heatmap of values on a regular grid.

    :param values: (ny, nx) values (row 0 at the lowest y), or (nx,) with ``y_axis=None`` for a
        1-D strip; NaN cells are drawn in grey (:data:`EMPTY`)
    :param x_axis: the horizontal axis (its range spans the cells' outer edges)
    :param y_axis: the vertical axis, or None for a 1-D strip
    :param title: the lines written above the map (what is drawn, its units, the iteration)
    :param colormap: (n, 3) anchor colours
    :param value_range: (low, high) of the colour bar; None: the finite values' range
    :param log_scale: colour by log10 of the (positive) values; the bar is labelled in values
    :return: (H, W, 3) uint8 RGB
    """
    grid = np.atleast_2d(np.asarray(values, dtype=np.float64))
    shown = np.where(grid > 0, np.log10(np.where(grid > 0, grid, 1.0)), np.nan) if log_scale else grid
    finite = shown[np.isfinite(shown)]
    if value_range is not None:
        low, high = (np.log10(max(v, 1e-300)) for v in value_range) if log_scale else value_range
    else:
        low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    canvas = _Canvas(x_axis, y_axis, title)
    canvas.paste_map(colorize(shown, low, high, colormap))
    canvas.axes()
    labels = tuple(number(10**v) for v in (high, (low + high) / 2, low)) if log_scale else None
    canvas.colour_bar(low, high, colormap, labels)
    return canvas.array()


def category_map(
    values: np.ndarray, names: Sequence[str], x_axis: Axis, y_axis: Axis | None, title: Sequence[str]
) -> np.ndarray:
    """A labelled map of discrete values (e.g. Discrete actions) with a legend.

    :param values: (ny, nx) or (nx,) integers in ``[0, len(names))``
    :param names: the legend's name of each value
    :param x_axis: the horizontal axis
    :param y_axis: the vertical axis, or None for a 1-D strip
    :param title: the lines written above the map
    :return: (H, W, 3) uint8 RGB
    """
    grid = np.atleast_2d(np.asarray(values, dtype=np.int64))
    colours = CATEGORIES[np.arange(len(names)) % len(CATEGORIES)]
    canvas = _Canvas(x_axis, y_axis, title)
    canvas.paste_map(colours[grid])
    canvas.axes()
    canvas.legend(names, colours)
    return canvas.array()


def scatter(
    x: np.ndarray,
    y: np.ndarray | None,
    x_axis: Axis,
    y_axis: Axis | None,
    title: Sequence[str],
    groups: np.ndarray | None = None,
    names: Sequence[str] | None = None,
) -> np.ndarray:
    """Points on a labelled map (e.g. the feature bank's centres); points outside the axes are left out.

    :param x: (n,) horizontal coordinates
    :param y: (n,) vertical coordinates, or None for a 1-D strip (points on its middle line)
    :param x_axis: the horizontal axis
    :param y_axis: the vertical axis, or None for a 1-D strip
    :param title: the lines written above the map
    :param groups: (n,) integers in ``[0, len(names))``: each group in its colour, with a legend;
        None: all points in one colour
    :param names: the legend's name of each group
    :return: (H, W, 3) uint8 RGB
    """
    canvas = _Canvas(x_axis, y_axis, title)
    px, py = canvas.pixel(np.asarray(x, dtype=np.float64), None if y is None else np.asarray(y, dtype=np.float64))
    inside = (px >= LEFT) & (px <= LEFT + canvas.width) & (py >= canvas.top) & (py <= canvas.top + canvas.height)
    if groups is None or names is None:
        groups, names, colours = np.zeros(len(px), dtype=np.int64), None, np.array([DOT], dtype=np.uint8)
    else:
        colours = CATEGORIES[np.arange(len(names)) % len(CATEGORIES)]
    for u, v, group in zip(px[inside], py[inside], np.asarray(groups)[inside], strict=True):
        canvas.draw.ellipse((u - 2, v - 2, u + 2, v + 2), fill=tuple(int(c) for c in colours[group]))
    canvas.axes()
    if names is not None:
        canvas.legend(names, colours)
    return canvas.array()
