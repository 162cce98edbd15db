"""One look per variant everywhere: the Rerun recordings, the report figures (pipeline.results.report) and
the sweep figures and recording (pipeline.results.sweep, pipeline.views.sweep_recording) take a variant's colour,
line width, dash and marker from here, so FSIMM is the same blue in the viewer and in the PNGs.

- **Colour** by the variant's place in the display order (the experiment's variant order, which
  summary.parquet keeps): the first variant blue, then orange, green, red, ...
- **Width and drawing order** by the variant key's place in sorted order. Rerun draws the lines of
  a time-series view in entity-path order (``/metrics/<metric>/<key>``, keys sorted), so the first
  key is drawn first, widest, and each later one narrower on top of it: where two variants' curves
  coincide, both stay visible (a thin line inside a wider one of another colour). The report
  figures draw in the same order with the same widths.
- **Dash and marker** (the report and sweep figures; Rerun has neither) by display order, so
  overlapping curves also differ in pattern, and a figure printed in grey still tells them apart.

Mode colours (the jump-Markov modes of study 004: CV, left and right turn) and the colours of an
IMM's models (study 001's 13 models) live here too, with the report's way of recognising a series
label as a variant or a mode.
"""

from __future__ import annotations

import colorsys
import re
from dataclasses import dataclass
from typing import Mapping, Sequence

RGB = tuple[int, int, int]

# One colour per variant, in display order (tracks, estimates, ellipses, metric lines, figures).
VARIANT_COLOURS: tuple[RGB, ...] = ((31, 119, 255), (255, 127, 14), (44, 200, 80), (214, 39, 40), (160, 103, 219),
                                    (23, 190, 207), (227, 119, 194), (188, 189, 34), (140, 86, 75), (127, 127, 127))
TRUTH_COLOUR: RGB = (235, 235, 235)
# series of a figure that are neither a variant nor a mode (e.g. an axis X / Y): greys, so they are
# never read as a variant
OTHER_COLOURS: tuple[RGB, ...] = ((80, 80, 80), (160, 160, 160), (40, 40, 40), (200, 200, 200))

# study 004's jump-Markov modes: the particle clouds, the mode probabilities, the report's figure
MODE_COLOURS: dict[str, RGB] = {"cv": (0, 195, 205), "ccw": (215, 75, 215), "cw": (240, 185, 0)}
MODE_WORDS = {"cv": "cv", "ccw": "ccw", "cw": "cw", "left": "ccw", "right": "cw"}

# Rerun widths (ui points) and matplotlib widths (points) of the widest and the narrowest variant
RERUN_WIDTHS = (3.75, 1.25)
FIGURE_WIDTHS = (3.2, 1.1)
# matplotlib dash patterns and markers, by display order
DASHES: tuple = ("-", (0, (6, 2)), (0, (4, 1.5, 1, 1.5)), (0, (1.5, 1.5)), (0, (8, 2, 2, 2, 2, 2)), (0, (3, 3)),
                 (0, (10, 3)), (0, (2, 1, 2, 4)))
MARKERS = "osD^vPX*<>"


def variant_colour(i: int) -> RGB:
    """The colour of the variant at display position ``i`` (0-based)."""
    if i < len(VARIANT_COLOURS):
        return VARIANT_COLOURS[i]
    r, g, b = colorsys.hsv_to_rgb((i * 0.61803398875) % 1.0, 0.75, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def variant_colours(keys: Sequence[str]) -> dict[str, RGB]:
    """key -> colour, ``keys`` in display order."""
    return {key: variant_colour(i) for i, key in enumerate(keys)}


def width_fraction(keys: Sequence[str]) -> dict[str, float]:
    """key -> 1.0 (widest, drawn first) .. 0.0 (narrowest, drawn last), by sorted key (Rerun's
    drawing order within a view); 0.5 for a lone variant."""
    order = sorted(set(keys))
    n = len(order)
    return {key: 0.5 if n == 1 else 1.0 - order.index(key) / (n - 1) for key in keys}


def rerun_widths(keys: Sequence[str]) -> dict[str, float]:
    """key -> SeriesLines width [ui points]: the first key in path order widest."""
    wide, narrow = RERUN_WIDTHS
    return {key: round(narrow + f * (wide - narrow), 3) for key, f in width_fraction(keys).items()}


def mpl(colour: Sequence[int]) -> tuple[float, ...]:
    """An 0-255 RGB(A) colour as matplotlib's 0-1 floats."""
    return tuple(c / 255 for c in colour)


def lighter(colour: Sequence[int], amount: float = 0.45) -> RGB:
    """``colour`` moved ``amount`` of the way towards white."""
    return tuple(int(round(c + (255 - c) * amount)) for c in colour[:3])  # type: ignore[return-value]


def model_colour(i: int, n: int) -> RGB:
    """Colour of model ``i`` of an IMM's ``n`` models (a hue circle: neighbours in the model list
    are neighbours in hue)."""
    r, g, b = colorsys.hsv_to_rgb(i / max(n, 1), 0.7, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


@dataclass(frozen=True)
class LineStyle:
    """How one series is drawn in a matplotlib figure."""
    colour: RGB
    width: float           # points
    dash: object           # a matplotlib linestyle
    marker: str
    zorder: float          # later (higher) on top: the narrow lines over the wide ones
    variant: str | None = None     # the variant key it belongs to, if any

    def plot_kwargs(self, points: int = 0) -> dict:
        """Keyword arguments for ``Axes.plot``; markers on about 8 of ``points`` points."""
        kwargs = {"color": mpl(self.colour), "linewidth": self.width, "linestyle": self.dash, "zorder": self.zorder}
        if self.marker:
            kwargs |= {"marker": self.marker, "markersize": 4.5, "markevery": max(points // 8, 1) if points else None,
                       "markerfacecolor": "none"}
        return kwargs


def variant_styles(keys: Sequence[str]) -> dict[str, LineStyle]:
    """key -> its figure style, ``keys`` in display order."""
    wide, narrow = FIGURE_WIDTHS
    fraction = width_fraction(keys)
    rank = {key: i for i, key in enumerate(sorted(set(keys)))}
    return {key: LineStyle(variant_colour(i), round(narrow + fraction[key] * (wide - narrow), 3),
                           DASHES[i % len(DASHES)], MARKERS[i % len(MARKERS)], 2.0 + 0.01 * rank[key], key)
            for i, key in enumerate(keys)}


_SEPARATOR = re.compile(r"^[\s,;:·(\[/|-]")


def match_variant(label: str, names: Mapping[str, str]) -> str | None:
    """The variant key a figure's series ``label`` belongs to: ``names`` maps each variant's display
    name and key to its key; the label is one of them, or starts with one followed by a separator
    ("proposed, radar 1", "FSIMM (bound_model)"); the longest such name wins. None otherwise."""
    text = str(label)
    if text in names:
        return names[text]
    best = None
    for name, key in names.items():
        if name and text.startswith(name) and _SEPARATOR.match(text[len(name):]) and \
                (best is None or len(name) > len(best[0])):
            best = (name, key)
    return None if best is None else best[1]


def match_mode(label: str) -> str | None:
    """The mode (``cv``, ``ccw``, ``cw``) a series label names as a word ("CV", "left turn (ccw, ...)",
    "right turn (cw, ...)"), when it names exactly one."""
    words = set(re.findall(r"[a-z]+", str(label).lower()))
    modes = {MODE_WORDS[w] for w in words if w in MODE_WORDS}
    return modes.pop() if len(modes) == 1 else None


def figure_styles(labels: Sequence[str], variants: Sequence[tuple[str, str]]) -> dict[str, LineStyle]:
    """label -> style for a figure's series: a variant's label (or one that starts with its name) in
    that variant's style, a later label of the same variant with the next dash and marker; a mode's
    label in the mode's colour; anything else in greys. ``variants``: (key, display name) in
    display order."""
    keys = [k for k, _ in variants]
    styles = variant_styles(keys)
    names: dict[str, str] = {}
    for key, name in variants:
        names[str(key)] = key
        names[str(name)] = key
    seen: dict[str, int] = {}
    out: dict[str, LineStyle] = {}
    others = 0
    for label in labels:
        key = match_variant(label, names)
        if key is not None:
            base, n = styles[key], seen.get(key, 0)
            seen[key] = n + 1
            i = keys.index(key) + n
            out[label] = base if n == 0 else LineStyle(base.colour, base.width, DASHES[(i + 1) % len(DASHES)],
                                                       MARKERS[(i + 1) % len(MARKERS)], base.zorder + 0.001 * n, key)
            continue
        mode = match_mode(label)
        if mode is not None:
            i = list(MODE_COLOURS).index(mode)
            out[label] = LineStyle(MODE_COLOURS[mode], 1.8, DASHES[i], "", 2.0 + 0.01 * i)
            continue
        out[label] = LineStyle(OTHER_COLOURS[others % len(OTHER_COLOURS)], 1.6, DASHES[others % len(DASHES)],
                               MARKERS[others % len(MARKERS)], 1.5 + 0.01 * others)
        others += 1
    return out
