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
