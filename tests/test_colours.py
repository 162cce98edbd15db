"""pipeline.views.colours: one look per variant everywhere (issue 19: FSIMM was blue in the viewer and
orange in the report). The recording, the report figures and the sweep figures take a variant's
colour from its place in the run's variant order; where curves coincide they differ in width
(Rerun and matplotlib: the first key in path order widest, drawn first) and dash / marker."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from pipeline.views.colours import (MODE_COLOURS, OTHER_COLOURS, figure_styles, match_mode, match_variant, mpl, rerun_widths,
                              variant_colour, variant_styles)

# the run's order (the experiment's variant list), deliberately not alphabetical
VARIANTS = [("fsimm", "FSIMM"), ("vsimm", "VSIMM"), ("ao_vsimm", "AO-VSIMM")]


def _drawn_lines(monkeypatch, draw) -> dict[str, object]:
    """label -> matplotlib Line2D of the figure ``draw()`` saves."""
    import matplotlib
    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    figures = []
    original = Figure.savefig
    monkeypatch.setattr(Figure, "savefig", lambda self, *a, **k: (figures.append(self), original(self, *a, **k))[1])
    draw()
    (fig,) = figures
    return {line.get_label(): line for ax in fig.axes for line in ax.lines}


def test_report_figure_colours_are_the_recording_colours(monkeypatch, tmp_path):
    from pipeline.results.report import FigureSpec, draw_figure

    t = np.arange(5.0)
    # the query orders by name (AO-VSIMM first): the colours must still follow the run's order
    df = pl.DataFrame({"variant": [n for _, n in sorted(VARIANTS, key=lambda v: v[1]) for _ in t],
                       "time": np.tile(t, 3), "value": np.ones(15)})
    spec = FigureSpec("rmse", "RMSE", "SELECT 1", "time", "value", "variant")
    lines = _drawn_lines(monkeypatch, lambda: draw_figure(df, spec, tmp_path / "f.png", VARIANTS))
    for i, (key, name) in enumerate(VARIANTS):
        assert lines[name].get_color() == pytest.approx(mpl(variant_colour(i))), name
    # identical curves: each a different dash and width, the narrower drawn over the wider
    assert len({str(variant_styles([k for k, _ in VARIANTS])[k].dash) for k, _ in VARIANTS}) == 3
    assert len({lines[n].get_marker() for _, n in VARIANTS}) == 3
    order = sorted(VARIANTS)                  # path order: ao_vsimm, fsimm, vsimm
    widths = [lines[n].get_linewidth() for _, n in order]
    zorders = [lines[n].get_zorder() for _, n in order]
    assert widths == sorted(widths, reverse=True) and zorders == sorted(zorders)


def test_the_recording_uses_the_same_colour_and_width_per_variant(tmp_path):
    import rerun as rr

    from pipeline.views.recording import log_metric_series, time_columns

    series = {("position_rmse", key): (np.arange(3), np.arange(3.0), np.ones(3), name, variant_colour(i))
              for i, (key, name) in enumerate(VARIANTS)}
    rec = rr.RecordingStream("mtt", recording_id="colours")
    stream = rec.binary_stream()
    log_metric_series(rr, rec, time_columns(rr), series)
    path = tmp_path / "c.rrd"
    path.write_bytes(stream.read(flush=True))
    rec.disconnect()
    from tests.helpers.rrd_reading import read_chunks

    style = {p.rsplit("/", 1)[1]: df for p, static, _, df in read_chunks(path) if static and p.startswith("/metrics/")}
    widths = rerun_widths([k for k, _ in VARIANTS])
    for i, (key, _) in enumerate(VARIANTS):
        c = style[key]["SeriesLines:colors"].explode()[0]
        assert ((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) == variant_colour(i)
        assert style[key]["SeriesLines:widths"].explode()[0] == pytest.approx(widths[key])
    assert widths["ao_vsimm"] > widths["fsimm"] > widths["vsimm"]      # path order: the first drawn widest


def test_sweep_figure_colours_and_styles(monkeypatch, tmp_path):
    from pipeline.results.sweep import draw_metric_figure

    rows = [{"panel": "", "job": f"j{j}", "job_num": j, "x": float(j), "variant_key": key, "variant": name,
             "value": 1.0, "ci_low": None, "ci_high": None} for j in range(3) for key, name in VARIANTS]
    data = pl.DataFrame(rows, schema_overrides={"ci_low": pl.Float64, "ci_high": pl.Float64})
    colours = {key: variant_colour(i) for i, (key, _) in enumerate(VARIANTS)}
    lines = _drawn_lines(monkeypatch, lambda: draw_metric_figure(
        data, x="seed", series="position_rmse", window="all", unit="m", path=tmp_path / "s.png", colours=colours))
    styles = variant_styles([k for k, _ in VARIANTS])
    for key, name in VARIANTS:
        assert lines[name].get_color() == pytest.approx(mpl(colours[key]))
        assert lines[name].get_marker() == styles[key].marker
    assert len({lines[n].get_marker() for _, n in VARIANTS}) == 3


def test_series_labels_are_matched_to_variants_and_modes():
    names = {n: k for k, n in VARIANTS} | {k: k for k, _ in VARIANTS}
    assert match_variant("FSIMM", names) == "fsimm"
    assert match_variant("AO-VSIMM (bound_model)", names) == "ao_vsimm"
    assert match_variant("VSIMM, radar 1", names) == "vsimm"
    assert match_variant("VSIMMX", names) is None
    assert match_mode("CV") == "cv" and match_mode("left turn (ccw, Omega > 0)") == "ccw"
    assert match_mode("right turn (cw, Omega < 0; the true turn)") == "cw"
    assert match_mode("X") is None
    styles = figure_styles(["VSIMM, radar 1", "VSIMM, radar 2", "CV", "X axis"], VARIANTS)
    assert styles["VSIMM, radar 1"].colour == styles["VSIMM, radar 2"].colour == variant_colour(1)
    assert styles["VSIMM, radar 1"].dash != styles["VSIMM, radar 2"].dash
    assert styles["CV"].colour == MODE_COLOURS["cv"]
    assert styles["X axis"].colour in OTHER_COLOURS


def test_sonobuoy_mode_colours_are_the_palette_modes():
    from pipeline.studies.sonobuoy import recording

    assert recording.MODE_COLOURS is MODE_COLOURS
