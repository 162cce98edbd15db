"""Pieces every study's blueprint and recording share, so that the viewer reads at a glance:

- **Paths up to now**: a trajectory is logged as one short segment per step (``log_path``) and the
  spatial views show its segments from the start up to the time cursor (``upto_now`` on that
  entity only), so the future of a track is not drawn at time t. The whole true trajectory stays
  as a faint static line (where the target goes, not where the filter went).
- **Colour keys instead of legends**: a plot's legend covers its lines and Rerun cuts it to the
  view's height (13 models showed 4). The variants' (and modes', models') colours are the same in
  every view, so one key strip (``log_key`` + ``key_view``: labelled points in the colours) names
  them once and the plots' legends are off (``NO_LEGEND``); a view with lines of its own (two
  groups, a band) keeps a legend in its quietest corner (``quiet_corner``).
- **Titles that fit**: ``fit_title`` picks the longest of a view's titles that fits its width on
  the 1600 x 900 window the layouts are made for (tools/screenshot.py's default size).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

WINDOW = (1600, 900)            # the viewer window the layouts are sized for [px]
CHAR_PX = 6.4                   # mean width of a title character [px] (5.5-6.1 measured on screenshots)
TITLE_CHROME_PX = 112           # icon, help, visibility and maximise buttons of a view's title bar [px]
KEY_GAP = 5                     # room between colour-key entries [characters]
KEY_HEIGHT_PX = 34              # the height the key row gets on the 1600 x 900 window [px]


def title_chars(width_px: float) -> int:
    """How many title characters fit a view ``width_px`` wide."""
    return max(int((width_px - TITLE_CHROME_PX) / CHAR_PX), 8)


def fit_title(width_px: float, *titles: str) -> str:
    """The first of ``titles`` (longest first) that fits a view ``width_px`` wide, else the last."""
    room = title_chars(width_px)
    for title in titles:
        if len(title) <= room:
            return title
    return titles[-1]


def fit_titles(width_px: float, options: Sequence[Sequence[str]]) -> list[str]:
    """One title per view of a row of views ``width_px`` wide each: every view gets the same level
    of ``options`` (its titles, longest first), the longest level at which all of them fit."""
    if not options:
        return []
    room = title_chars(width_px)
    levels = max(len(o) for o in options)
    for level in range(levels):
        chosen = [o[min(level, len(o) - 1)] for o in options]
        if all(len(t) <= room for t in chosen):
            return chosen
    return [o[-1] for o in options]


def column_width(columns: int, share: float = 1.0, total_share: float | None = None) -> float:
    """The width [px] of one of ``columns`` equal columns across the window, or of a column with
    ``share`` of ``total_share`` when given."""
    if total_share:
        return WINDOW[0] * share / total_share
    return WINDOW[0] / max(columns, 1)


def whole_run(rrb):
    """A time axis over the whole recording (time-series views do not scroll with the cursor)."""
    return rrb.TimeAxis(view_range=rrb.TimeRange(start=rrb.TimeRangeBoundary.infinite(),
                                                 end=rrb.TimeRangeBoundary.infinite()))


def upto_now(rrb):
    """Visible time range from the start to the time cursor, on both timelines."""
    return rrb.VisibleTimeRanges([
        rrb.VisibleTimeRange(timeline, start=rrb.TimeRangeBoundary.infinite(),
                             end=rrb.TimeRangeBoundary.cursor_relative())
        for timeline in ("time", "step")])


def path_overrides(rrb, paths: Sequence[str]) -> dict:
    """Per-entity overrides for a spatial view: each path entity shown from the start to the cursor."""
    ranges = upto_now(rrb)
    return {p: ranges for p in paths}


def path_segments(pos: np.ndarray, ok: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Segments joining each row's positions to the previous row's: ``pos`` (N, D) for one object or
    (N, T, D) for T objects, ``ok`` (N[, T]) the valid ones (default: finite). Returns (rows with at
    least one segment, their segment counts, the segments (S, 2, D) in row order)."""
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim == 2:
        pos = pos[:, None, :]
        ok = None if ok is None else np.asarray(ok)[:, None]
    valid = np.isfinite(pos).all(-1) if ok is None else (np.asarray(ok, dtype=bool) & np.isfinite(pos).all(-1))
    both = valid[1:] & valid[:-1]                                        # (N-1, T)
    counts = both.sum(-1)
    rows = np.nonzero(counts)[0]
    segments = np.stack([pos[:-1][both], pos[1:][both]], axis=1)          # (S, 2, D), row-major
    return (rows + 1).astype(np.int64), counts[rows].astype(np.int64), segments


def log_path(rr, rec, times, entity: str, t: np.ndarray, steps: np.ndarray, pos: np.ndarray,
             ok: np.ndarray | None = None, *, colour, radius: float, draw_order: float | None = None) -> None:
    """Log a trajectory as a segment per row (``t``, ``steps`` of each row of ``pos``), with its
    style static; 2-D or 3-D from the last axis. A view shows it up to now with ``path_overrides``."""
    rows, counts, segments = path_segments(pos, ok)
    three = segments.shape[-1] == 3 if segments.size else np.shape(pos)[-1] == 3
    strips = rr.LineStrips3D if three else rr.LineStrips2D
    style = {"colors": colour, "radii": rr.Radius.ui_points(radius)}
    if draw_order is not None and not three:
        style["draw_order"] = draw_order
    rec.log(entity, strips.from_fields(**style), static=True)
    if rows.size:
        t, steps = np.asarray(t), np.asarray(steps)
        rec.send_columns(entity, indexes=times(t[rows], steps[rows]),
                         columns=strips.columns(strips=segments).partition(counts))


def _key_positions(labels: Sequence[str]) -> tuple[np.ndarray, float]:
    """x of each key entry (in character widths: room for its label, so long names do not overlap)
    and the key's total width."""
    room = np.array([len(str(label)) + KEY_GAP for label in labels], dtype=np.float64)
    return np.cumsum(room) - room / 2, float(room.sum())


def log_key(rr, rec, entity: str, entries: Sequence[tuple[str, Sequence[int]]]) -> None:
    """A colour key: one labelled point per (label, colour), in a row (static); ``key_view`` shows it."""
    if not entries:
        return
    x, _ = _key_positions([label for label, _ in entries])
    rec.log(entity, rr.Points2D(np.c_[x, np.zeros(x.size)], colors=[c for _, c in entries],
                                labels=[label for label, _ in entries], radii=rr.Radius.ui_points(5.0),
                                show_labels=True), static=True)


def key_view(rrb, entity: str, labels: Sequence[str], name: str = "colours"):
    """A short view of the colour key ``log_key`` wrote with these ``labels``: one character width
    of the key is about CHAR_PX on a KEY_HEIGHT_PX high view, the entries centred."""
    _, total = _key_positions(labels)
    height = KEY_HEIGHT_PX / CHAR_PX                 # the view's height in key units
    # no title bar (the labels say what the colours are); the points near the top, their labels below
    return rrb.Spatial2DView(origin=entity, contents=[entity], name=name, titlebar=False,
                             visual_bounds=rrb.VisualBounds2D(x_range=[0.0, max(total, 1.0)],
                                                              y_range=[-0.25 * height, 0.75 * height]))


NO_LEGEND_NOTE = "colours: see the key"


def no_legend(rrb):
    return rrb.PlotLegend(visible=False)


CORNERS = ("RightTop", "LeftTop", "RightBottom", "LeftBottom")


def quiet_corner(curves: Sequence[tuple[np.ndarray, np.ndarray]], entries: int,
                 y_range: tuple[float, float] | None = None) -> str:
    """The corner of a plot whose legend (``entries`` lines) would cover the fewest points of
    ``curves`` ((x, y) pairs), the plot spanning their range (or ``y_range``). Ties: right top first."""
    xs = [np.asarray(x, dtype=np.float64) for x, _ in curves]
    ys = [np.asarray(y, dtype=np.float64) for _, y in curves]
    if not xs or not any(x.size for x in xs):
        return CORNERS[0]
    x = np.concatenate(xs)
    y = np.concatenate(ys)
    keep = np.isfinite(x) & np.isfinite(y)
    x, y = x[keep], y[keep]
    if not x.size:
        return CORNERS[0]
    x0, x1 = float(x.min()), float(x.max())
    y0, y1 = y_range if y_range is not None else (float(y.min()), float(y.max()))
    fx = (x - x0) / ((x1 - x0) or 1.0)
    fy = (y - y0) / ((y1 - y0) or 1.0)
    width, height = 0.35, min(0.15 + 0.12 * entries, 0.9)
    covered = {
        "RightTop": ((fx > 1 - width) & (fy > 1 - height)).sum(),
        "LeftTop": ((fx < width) & (fy > 1 - height)).sum(),
        "RightBottom": ((fx > 1 - width) & (fy < height)).sum(),
        "LeftBottom": ((fx < width) & (fy < height)).sum(),
    }
    return min(CORNERS, key=lambda c: covered[c])


def legend_in_quiet_corner(rrb, curves, entries: int, y_range=None):
    return rrb.PlotLegend(corner=quiet_corner(curves, entries, y_range))
