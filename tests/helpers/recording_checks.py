"""The viewer checks every study's recording test shares (issue 19: titles that fit, keys instead of
legends, tracks up to now, no viewer warning), written once. A recording test module imports these
and defines what they read: the fixtures ``case``, ``chunks`` and ``entities``, and ``VARIANTS`` (key ->
display name) and ``_write(case, path)`` (writes the .rrd)."""

from __future__ import annotations

import pytest

from pipeline.views.blueprints import title_chars
from pipeline.views.colours import variant_colour
from tests.helpers.rrd_reading import blueprint_views, capture_blueprint, legend_visible, up_to_now

@pytest.fixture(scope="module")
def recording_variants(request):
    return request.module.VARIANTS


@pytest.fixture(scope="module")
def write_recording(request):
    return request.module._write


@pytest.fixture(scope="module")
def blueprint(case, tmp_path_factory, write_recording):
    return capture_blueprint(lambda: write_recording(case, tmp_path_factory.mktemp("bp") / "bp.rrd"))


def test_every_title_fits_its_view(blueprint):
    too_long = [(str(v.name), round(w)) for v, _, w in blueprint_views(blueprint)
                if v.name is not None and v.titlebar is None and len(str(v.name)) > title_chars(w)]
    assert not too_long, too_long


def test_plots_have_no_legend_and_the_key_names_the_variants(blueprint, chunks, recording_variants):
    plots = [v for v, _, _ in blueprint_views(blueprint) if v.class_identifier == "TimeSeries"]
    assert plots and all(legend_visible(v) is False for v in plots), \
        [str(v.name) for v in plots if legend_visible(v) is not False]
    key = next(df for p, static, _, df in chunks if p == "/key/variants" and static)
    labels = key["Points2D:labels"].explode().to_list()
    colours = key["Points2D:colors"].explode().to_list()
    assert labels[:len(recording_variants)] == list(recording_variants.values())
    assert [((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for c in colours[:len(recording_variants)]] == \
        [variant_colour(i) for i in range(len(recording_variants))]
    keys = [v for v, _, _ in blueprint_views(blueprint) if str(v.origin) == "/key/variants"]
    assert len(keys) == 1 and keys[0].titlebar is not None


def test_tracks_are_drawn_up_to_now(blueprint, entities):
    tracks = [p for p in entities if p.endswith("/track") or p.endswith("/path")]
    assert tracks
    for view, _, _ in blueprint_views(blueprint):
        if view.class_identifier != "2D" or str(view.origin).startswith("/key"):
            continue
        contents = [str(c) for c in (view.contents or [])]
        shown = [p for p in tracks if any(p.startswith(c.removesuffix("/**")) for c in contents)]
        assert shown, view.name
        missing = [p for p in shown if not up_to_now(view, p)]
        assert not missing, (view.name, missing)


def test_no_viewer_warning_while_writing_quiet(case, tmp_path, capfd, write_recording):
    write_recording(case, tmp_path / "quiet.rrd")
    err = capfd.readouterr().err
    assert "Dropping chunk" not in err and "WARN" not in err, err
