"""Reading a written .rrd back for the recording tests (rerun.chunk.RrdReader, no viewer)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import polars as pl


def read_chunks(path: Path) -> list[tuple[str, bool, set, pl.DataFrame]]:
    """(entity path, is static, timeline names, rows) of every chunk in the file."""
    from rerun.chunk import RrdReader

    return [(c.entity_path, c.is_static, set(c.timeline_names), pl.from_arrow(c.to_record_batch()))
            for c in RrdReader(path).stream().to_chunks()]


def entity_index(chunks) -> dict:
    """entity path -> its static and time-varying component columns, timelines and row count."""
    out: dict = defaultdict(lambda: {"static": set(), "temporal": set(), "timelines": set(), "rows": 0})
    for path, static, timelines, df in chunks:
        e = out[path]
        cols = {c for c in df.columns if ":" in c}
        if static:
            e["static"] |= cols
        else:
            e["temporal"] |= cols
            e["timelines"] |= timelines
            e["rows"] += df.height
    return dict(out)


def rows(chunks, entity: str, column: str) -> dict[int, list]:
    """step -> value of ``column`` on ``entity`` (time-varying rows; the last row of a step)."""
    out = {}
    for path, static, _, df in chunks:
        if path == entity and not static and column in df.columns:
            out.update(zip(df["step"].to_list(), df[column].to_list()))
    return out


def temporal(entities, path: str, column: str) -> dict:
    """The entity's index entry, asserting ``column`` varies over the time and step timelines."""
    assert path in entities, f"{path} missing; have {sorted(entities)}"
    e = entities[path]
    assert column in e["temporal"], f"{path}: {column} not time-varying; temporal={e['temporal']}"
    assert {"time", "step"} <= e["timelines"], f"{path}: timelines {e['timelines']}"
    return e


def assert_complete_recording(path: Path, recording_id: str) -> None:
    """One recording of that id, with a store and a blueprint, and no temporary file beside it."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    assert [(r.application_id, r.recording_id) for r in reader.recordings()] == [("mtt", recording_id)]
    assert reader.store() is not None
    assert reader.blueprints(), "no blueprint stored in the .rrd"
    assert [p.name for p in path.parent.iterdir()] == [path.name], "temporary file left behind"


# ---- the blueprint a writer sends (captured in Python: no viewer, no pixels) --------------------
def capture_blueprint(write) -> object:
    """Run ``write()`` (a recording writer) and return the rrb.Blueprint it sent."""
    import pytest
    import rerun as rr

    sent = []
    original = rr.RecordingStream.send_blueprint

    def spy(self, blueprint, *args, **kwargs):
        sent.append(blueprint)
        return original(self, blueprint, *args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(rr.RecordingStream, "send_blueprint", spy)
        write()
    assert len(sent) == 1, f"{len(sent)} blueprints sent"
    return sent[0]


def blueprint_views(blueprint, width: float = 1600.0):
    """(view, its containers from the root, its width [px] on a ``width`` wide window) of every view:
    a Horizontal splits the width by its column shares, a Grid by its columns; Vertical and Tabs keep it."""
    import rerun.blueprint as rrb

    def walk(container, parents, w):
        items = list(container.contents)
        kind = str(container.kind)
        if kind == "Horizontal" and items:
            shares = list(container.column_shares) if container.column_shares is not None else [1.0] * len(items)
            widths = [w * s / sum(shares) for s in shares]
        elif kind == "Grid" and items:
            columns = container.grid_columns or int(np.ceil(np.sqrt(len(items))))
            widths = [w / columns] * len(items)
        else:
            widths = [w] * len(items)
        for item, iw in zip(items, widths):
            if isinstance(item, rrb.Container):
                yield from walk(item, parents + (item,), iw)
            else:
                yield item, parents + (container,), iw

    import numpy as np
    root = blueprint.root_container
    yield from walk(root, (), width)


def legend_visible(view) -> bool | None:
    """The view's PlotLegend visibility (None: not set, i.e. Rerun's default, shown)."""
    legend = view.properties.get("PlotLegend")
    if legend is None or legend.visible is None:
        return None
    return bool(legend.visible.as_arrow_array().to_pylist()[0])


def up_to_now(view, entity: str) -> bool:
    """Whether ``view`` shows ``entity`` from the start to the time cursor on the time timeline."""
    ranges = view.visualizer_overrides.get(entity)
    if ranges is None or not hasattr(ranges, "ranges"):
        return False
    for r in ranges.ranges.as_arrow_array().to_pylist():
        if r["timeline"] == "time" and r["range"]["start"] is None and r["range"]["end"] == 0:
            return True
    return False
