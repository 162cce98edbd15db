"""Issue 16 (reliability, round 2): the items fixed so far, each with the case that went wrong."""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.errors import ConfigError
from pipeline.evaluation.faults import FAULTS, fault_flags, fault_summary
from pipeline.storage.store import inside
from tests.helpers.processes import run_code, run_module, run_pipeline
from tests.helpers.runs import run_in_process


def test_a_never_finite_run_is_flagged_not_taken_for_no_track_yet():
    """Item 3: leading NaN means 'no track yet'; a run that never leaves it was counted as fine."""
    state = np.full((2, 6, 4), np.nan)
    covariance = np.full((2, 6, 4, 4), np.nan)
    state[1, 2:], covariance[1, 2:] = 1.0, np.eye(4)
    flags = fault_flags(state, covariance)
    assert (flags[0] == FAULTS["never_finite"]).all() and (flags[1] == 0).all()
    assert fault_summary(flags)["diverged_runs"] == 1


def test_a_nan_initial_state_is_refused_before_any_stage(tmp_path):
    """Item 3: 'scenario.initial_state=[nan,340,20000,340]' exited 0 with every estimate NaN."""
    with pytest.raises(ConfigError, match=r"scenario.initial_state\[0\]: nan is not allowed; every number"):
        run_in_process(tmp_path, "bad", "mc.runs=2", "scenario.initial_state=[nan,340,20000,340]")
    assert not (tmp_path / "cache").exists()


def test_a_variant_key_cannot_name_a_path_outside_the_run(tmp_path):
    """Item 4: the key '../../../../escaped' wrote <artifacts>/escaped.parquet."""
    conf = tmp_path / "conf_extra" / "experiment"
    conf.mkdir(parents=True)
    (conf / "escape.yaml").write_text(
        "# @package _global_\ndefaults:\n  - /experiment/ao_vsimm_s1\n  - _self_\n"
        "filters:\n  \"../../../../escaped\":\n    _target_: filters.imm.FSIMM\n    models: ${models}\n    name: ESC\n")
    proc = run_pipeline(f"--config-dir={tmp_path / 'conf_extra'}", "experiment=escape", "mc.runs=2",
                        "scenario.steps=20", "record.enabled=false", artifacts=tmp_path)
    assert proc.returncode == 2 and "variant key(s) ['../../../../escaped'] are not allowed" in proc.stderr
    assert not list(tmp_path.rglob("escaped*")) and not list(Path("/").glob("escaped.parquet"))
    with pytest.raises(ValueError, match="resolves outside"):
        inside(tmp_path / "run", Path("estimates") / "../../x.parquet")
    assert inside(tmp_path / "run", Path("estimates") / "kf.parquet") == tmp_path / "run" / "estimates" / "kf.parquet"


def test_an_empty_variant_list_is_refused_up_front(tmp_path):
    """Item 10: variants=[] ran two stages, then failed on an empty concat."""
    with pytest.raises(ConfigError, match=r"variants: \[\] selects no variant"):
        run_in_process(tmp_path, "bad", "mc.runs=2", "variants=[]")
    assert not (tmp_path / "cache").exists()


def test_the_summary_counts_never_finite_runs(tmp_path):
    out, _ = run_in_process(tmp_path, "ok", "mc.runs=2", "scenario.steps=20")
    names = set(out.summary["series"].to_list())
    assert "fault_runs_never_finite" in names
    assert out.summary.filter(pl.col("series") == "fault_runs_never_finite")["value"].sum() == 0


@pytest.mark.parametrize("override, shown", [("record.enabled=2", "2"), ("cache.enabled=maybe", "'maybe'"),
                                             ("cache.enabled='false'", "'false'")])
def test_booleans_are_booleans(tmp_path, override, shown):
    """Item 14: record.enabled=2 and cache.enabled=maybe were taken as true; the quoted 'false' still used the cache."""
    with pytest.raises(ConfigError, match=f"{override.split('=')[0]}: {shown} is not allowed; it must be true or false"):
        run_in_process(tmp_path, "bad", "mc.runs=2", override)
    assert not (tmp_path / "cache").exists()


def test_a_refused_value_names_the_key_the_user_set(tmp_path):
    """Item 18: models.process_noise_std=-10 was reported as bound.process_noise_std (interpolated from it)."""
    with pytest.raises(ConfigError) as info:
        run_in_process(tmp_path, "bad", "mc.runs=2", "models.process_noise_std=-10")
    assert "the value was set as models.process_noise_std. Fix models.process_noise_std" in str(info.value)


def test_summary_windows_fit_the_scenario(tmp_path, caplog):
    """Item 15: windows past the scenario's end gave silent NaN rows, and 'all' stopped at its configured end."""
    short, _ = run_in_process(tmp_path, "short", "experiment=ao_vsimm_s2", "mc.runs=2", "scenario.steps=40")
    assert "metrics.windows.after_switch: [57, 200] starts after the scenario's last step 40" in caplog.text
    assert set(short.summary["window"].drop_nulls().unique().to_list()) <= {"all", "M3 by step 80"}
    long, _ = run_in_process(tmp_path, "long", "experiment=ao_vsimm_s1", "mc.runs=2", "scenario.steps=260")
    per_step = long.metrics.filter((pl.col("series") == "position_rmse") & (pl.col("variant_key") == "fsimm")
                                   ).sort("step")["value"].to_numpy()
    summary = long.summary.filter((pl.col("series") == "position_rmse") & (pl.col("variant_key") == "fsimm")
                                  & (pl.col("window") == "all"))["value"][0]
    assert summary == pytest.approx(np.nanmean(per_step[2:261]))       # 'all' is steps 2..260, not 2..200


def test_sql_reads_the_project_tables_only(tmp_path):
    """Item 6: mtt-query sql "SELECT * FROM read_csv('/etc/passwd')" returned the file."""
    from pipeline.results.query import QueryError, query
    from pipeline.results.report import TargetSpec, evaluate_target, load_run
    secret = tmp_path / "secret.csv"
    secret.write_text("user,password\nroot,hunter2\n")
    _, ctx = run_in_process(tmp_path, "ao_vsimm_s1/run", "mc.runs=2", "scenario.steps=20")
    for sql in (f"SELECT * FROM read_csv('{secret}')", f"select * from READ_PARQUET ('{ctx.run_dir}/summary.parquet')"):
        with pytest.raises(QueryError, match="queries read the project's tables only"):
            query(sql, root=tmp_path)
    assert query("SELECT COUNT(*) AS n FROM summary", root=tmp_path)["n"][0] > 0
    target = TargetSpec("leak", "t", "p", f"SELECT user AS measured, TRUE AS pass FROM read_csv('{secret}')")
    result = evaluate_target(load_run(ctx.run_dir), target)
    assert result.verdict == "ERROR" and "hunter2" not in result.measured


# ---- item 1: content checksums ------------------------------------------------------------------

def _data_region(path: Path) -> tuple[int, int]:
    """(first, end) byte offsets of a Parquet file's pages: after the magic, before the footer."""
    raw = path.read_bytes()
    footer = int.from_bytes(raw[-8:-4], "little")
    return 4, len(raw) - 8 - footer


def _flip(path: Path, offset: int, bit: int = 0) -> None:
    with open(path, "r+b") as f:
        f.seek(offset)
        byte = f.read(1)[0]
        f.seek(offset)
        f.write(bytes([byte ^ (1 << bit)]))


def test_a_cached_table_that_still_parses_after_a_flipped_bit_is_not_served(tmp_path):
    """Item 1: single bit flips in a cached table's data pages (footer intact) were served (59 of 60)."""
    from pipeline.storage.schemas import META_TABLE, META_VERSION, SCHEMA_VERSION
    from pipeline.storage.store import StageCache
    rng = np.random.default_rng(3)
    df = pl.DataFrame({"run": np.repeat(np.arange(20, dtype=np.int32), 50), "x": rng.normal(size=1000) * 80,
                       "P": pl.Series(rng.normal(size=(1000, 4)), dtype=pl.Array(pl.Float64, 4)),
                       "fault": np.zeros(1000, dtype=np.uint8)})
    meta = {META_TABLE: "truth", META_VERSION: SCHEMA_VERSION}
    cache = StageCache(tmp_path)
    path = cache.store("scenario", "k", df, meta)
    pristine = path.read_bytes()
    first, end = _data_region(path)
    parsed_but_wrong = 0
    for offset in np.linspace(first, end - 1, 40).astype(int):
        path.write_bytes(pristine)
        _flip(path, int(offset), bit=int(offset) % 8)
        try:
            wrong = not pl.read_parquet(path).equals(df)       # what the old cache checked: that it parses
        except Exception:
            wrong = False
        parsed_but_wrong += wrong
        hit = cache.load("scenario", "k", "truth")
        # a flip in a page header's statistics leaves the rows as written: serving them is right
        assert hit is None or hit[0].equals(df), f"a flipped bit at byte {offset} was served"
        assert not wrong or not path.exists()                  # wrong rows: moved aside, to be recomputed
    assert parsed_but_wrong >= 10        # many of these flips parse to other rows: only the checksum catches them


def test_other_rows_under_copied_metadata_are_not_served(tmp_path):
    """Item 1: a file with altered rows and the original's metadata (key, checksum) was reused."""
    from pipeline.storage.schemas import META_TABLE, META_VERSION, SCHEMA_VERSION
    from pipeline.storage.store import StageCache
    cache = StageCache(tmp_path)
    path = cache.store("scenario", "k", pl.DataFrame({"x": [81.49, 12.0]}), {META_TABLE: "truth",
                                                                           META_VERSION: SCHEMA_VERSION})
    copied = pl.read_parquet_metadata(path)
    pl.DataFrame({"x": [float("inf"), 12.0]}).write_parquet(path, metadata=copied)
    assert cache.load("scenario", "k", "truth") is None and list(path.parent.glob("k.parquet.*.rejected"))


def test_a_damaged_cache_file_is_recomputed_and_a_damaged_run_table_is_not_queried(tmp_path, caplog):
    """Item 1 end to end: study 002's position_rmse of one target became inf, reused with status ok."""
    from pipeline.results.query import query
    from pipeline.results.report import ReportError, load_run
    first, ctx = run_in_process(tmp_path, "a", "mc.runs=2", "scenario.steps=20")
    tracks = sorted((tmp_path / "cache" / "track").glob("*.parquet"))
    damaged = tracks[0]
    start, end = _data_region(damaged)
    pristine = damaged.read_bytes()
    original = pl.read_parquet(damaged)
    for offset in range(start + 64, end, 7):                   # a flip that still parses, to other rows
        damaged.write_bytes(pristine)
        _flip(damaged, offset)
        try:
            if not pl.read_parquet(damaged).equals(original):
                break
        except Exception:
            continue
    else:
        raise AssertionError("no flipped bit parsed to other rows")
    second, _ = run_in_process(tmp_path, "b", "mc.runs=2", "scenario.steps=20")
    assert "its content checksum does not match its rows" in caplog.text and list(damaged.parent.glob("*.rejected"))
    def numbers(summary):       # what was computed, not timed
        return summary.filter(~pl.col("series").str.contains("compute")).select("variant_key", "series", "window", "value")
    assert numbers(second.summary).equals(numbers(first.summary))        # recomputed: the same numbers
    # a run folder's table damaged after the run: queries leave it out and say so, the report refuses it
    summary = ctx.run_dir / "summary.parquet"
    altered = pl.read_parquet(summary).with_columns(pl.col("value") * 2)
    altered.write_parquet(summary, metadata=pl.read_parquet_metadata(summary))
    warnings = []
    n = query("SELECT COUNT(DISTINCT run_id) AS n FROM summary", root=tmp_path, warn=warnings.append)["n"][0]
    assert n == 1 and any("skipping damaged" in w and "summary.parquet" in w for w in warnings)
    with pytest.raises(ReportError, match="content checksum does not match"):
        load_run(ctx.run_dir)


# ---- item 2: published files are copies -------------------------------------------------------

def test_damage_to_the_cache_does_not_reach_earlier_runs(tmp_path):
    """Item 2: cache files were hard-linked into run folders; truncating one changed earlier runs' tables."""
    import hashlib
    _, ctx = run_in_process(tmp_path, "a", "mc.runs=2", "scenario.steps=20")
    published = sorted(p for p in ctx.run_dir.rglob("*.parquet")
                       if p.name not in ("summary.parquet", "metrics.parquet", "comparisons.parquet", "per_run.parquet",
                                         "resamples.parquet"))
    before = {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in published}
    assert len(published) == 5                         # truth, detections, three variants' estimates
    for cached in (tmp_path / "cache").rglob("*.parquet"):
        with open(cached, "r+b") as f:                 # in place, as truncate or dd would
            f.truncate(100)
    assert {p: hashlib.sha256(p.read_bytes()).hexdigest() for p in published} == before
    assert all(p.stat().st_nlink == 1 for p in published)


def test_publish_by_link_is_chosen_explicitly_and_is_read_only(tmp_path):
    """Item 2's space-saving alternative, cache.publish=link: hard links, made read-only so that an
    in-place write fails rather than reaching every run that shares the file; a bad value is refused."""
    import stat
    _, ctx = run_in_process(tmp_path, "a", "mc.runs=2", "scenario.steps=20", "cache.publish=link")
    truth = ctx.run_dir / "truth.parquet"
    assert truth.stat().st_nlink == 2 and not truth.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)
    with pytest.raises(ConfigError, match="cache.publish: 'hardlink' is not allowed; it must be 'copy'"):
        run_in_process(tmp_path, "b", "mc.runs=2", "cache.publish=hardlink")


# ---- item 9: singular covariances ----------------------------------------------------------------

def test_a_singular_bound_is_nan_from_that_scan_not_a_crash():
    """Item 9: the PCRLB recursion raised LinAlgError on an exactly singular matrix."""
    import warnings
    from filters.bounds import SingularBoundWarning, posterior_crlb
    F, Q = np.stack([np.eye(2)] * 4), np.zeros((2, 2))
    F[2] = 0.0                                                       # scan 2's prediction: the zero matrix
    information = np.zeros((4, 2, 2))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        bounds = posterior_crlb(F, Q, np.eye(2), information)
    assert np.allclose(bounds[:2], np.eye(2)) and np.isnan(bounds[2:]).all()
    assert [w.category for w in caught] == [SingularBoundWarning] and "scans 2..3 are NaN" in str(caught[0].message)


@pytest.mark.parametrize("overrides", [
    ("sensors.noise_std=1e-12", "models.process_noise_std=1e12"),
    ("experiment=sonar_case2", "sensors.bearing_std_deg=1e-9", "sensors.range_std=1e-9", "scenario.duration=1200"),
])
def test_an_exactly_singular_covariance_flags_the_runs_and_the_job_goes_on(tmp_path, caplog, overrides):
    """Item 9: these died with LinAlgError (in the bound); the README promises metrics for the rest."""
    out, ctx = run_in_process(tmp_path, "singular", "mc.runs=2", *overrides)
    assert "the bound is singular at scan" in caplog.text and "the metrics go on" in caplog.text
    assert (ctx.run_dir / "summary.parquet").is_file()
    rmse = out.summary.filter(pl.col("series") == "position_rmse")["value"]
    assert rmse.len() > 0 and rmse.is_finite().all()


# ---- item 13: a paragraph and exit 2 for every input error ------------------------------------------

@pytest.mark.parametrize("args, says", [
    (("paths.artifacts=/proc/x",), "error: paths.artifacts=/proc/x: cannot write in /proc/x: No such file or directory"),
    (("paths.artifacts=/etc/hostname/x",), "A part of that path is a file, not a folder"),
    (("paths.artifacts=.", "mc.runs=${nope.x}"), "mc.runs: '${nope.x}' cannot be resolved"),
    (("paths.artifacts=.", "nonexistent_key=3"), "Could not override 'nonexistent_key'"),   # Hydra's refusal: 2 too
])
def test_bad_paths_and_keys_get_a_paragraph_and_exit_2(tmp_path, args, says):
    """Item 13: /proc/x, a path under a file and an unknown key gave tracebacks or exit 1."""
    proc = run_module("pipeline", "record.enabled=false", *args, cwd=tmp_path, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert says in proc.stderr and "Traceback" not in proc.stderr


def test_a_folder_where_a_cache_file_belongs_is_named(tmp_path):
    """Item 13: a folder in place of a cache file gave IsADirectoryError's traceback."""
    assert run_pipeline("mc.runs=2", "scenario.steps=20", "record.enabled=false", artifacts=tmp_path).returncode == 0
    (cached,) = (tmp_path / "cache" / "scenario").glob("*.parquet")
    cached.unlink()
    cached.mkdir()
    proc = run_pipeline("mc.runs=2", "scenario.steps=20", "record.enabled=false", artifacts=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert f"{cached} is a folder where the pipeline keeps a file; move it out of the way" in proc.stderr


# ---- item 16: a refused run writes nothing; a killed run shows as interrupted ------------------------

def test_a_refused_single_run_leaves_no_folder_but_a_refused_sweep_job_is_listed(tmp_path):
    """Item 16: a refused config still created a run folder with a summary.parquet."""
    proc = run_pipeline("mc.runs=0", artifacts=tmp_path)
    assert proc.returncode == 2 and not (tmp_path / "runs").exists()
    assert not [p for p in tmp_path.rglob("*") if p.is_file()]
    proc = run_pipeline("-m", "mc.runs=0", "record.enabled=false", artifacts=tmp_path)
    (job,) = (tmp_path / "multirun").glob("*/0")
    assert json.loads((job / "status.json").read_text())["status"] == "failed"


def test_a_running_job_whose_process_is_gone_is_listed_as_interrupted(tmp_path):
    """Item 16: killed runs stayed 'running' forever in mtt-query list."""
    from pipeline.run.process import identity
    from pipeline.results.query import runs_frame
    gone = json.loads(run_code("import json; from pipeline.run.process import identity; print(json.dumps(identity()))",
                               check=True, timeout=None).stdout)
    for name, process in (("killed", gone), ("alive", identity()), ("elsewhere", {**gone, "host": "another-host"})):
        folder = tmp_path / "runs" / "ao_vsimm_s1" / name
        folder.mkdir(parents=True)
        (folder / "status.json").write_text(json.dumps({"status": "running", "experiment": "ao_vsimm_s1",
                                                        "started_at": "2026-12-01T10:00:00", "process": process}))
    rows = {r["run_id"].rsplit("/", 1)[1]: r for r in runs_frame(tmp_path).to_dicts()}
    assert rows["killed"]["status"] == "interrupted" and f"pid {gone['pid']}" in rows["killed"]["error"]
    assert rows["alive"]["status"] == "running" and rows["elsewhere"]["status"] == "running"


def test_a_job_records_its_process(tmp_path):
    _, ctx = run_in_process(tmp_path, "a", "mc.runs=2", "scenario.steps=20")
    process = json.loads((ctx.run_dir / "status.json").read_text())["process"]
    assert process["pid"] == os.getpid() and process["host"]


# ---- item 17: a report on a sweep with a failed job --------------------------------------------------

@pytest.mark.full
def test_a_report_on_a_sweep_with_a_failed_job_reports_the_others_and_says_why(tmp_path):
    """Item 17: pipeline.results.report wrote job 0, then exited 2 on the failed job and wrote no index.md."""
    from pipeline.results.report import main as report_main
    proc = run_pipeline("-m", "mc.runs=2,0,3", "scenario.steps=20", "record.enabled=false", artifacts=tmp_path)
    assert proc.returncode == 1 and "2 ok, 1 failed" in proc.stderr
    (sweep,) = (tmp_path / "multirun").iterdir()
    assert report_main([str(sweep)]) == 0
    index = (sweep / "index.md").read_text()
    assert "| 1 | 0 | ao_vsimm_s1 | None | not reported | the job is failed: mc.runs: 0 is not allowed" in index   # 0: its mc.runs
    assert (sweep / "0" / "report" / "report.md").is_file() and (sweep / "2" / "report" / "report.md").is_file()
    assert report_main([str(sweep), "--check"]) == 1          # a job without a report fails the check


# ---- item 5: _target_ names a class of the project or of a listed package -----------------------

@pytest.mark.parametrize("node, says", [
    ("{_target_:builtins.open,file:VICTIM,mode:w}", "'builtins.open' is not allowed (nothing was imported)"),
    ("{_target_:shutil.copyfile,src:VICTIM,dst:VICTIM.copy}", "'shutil.copyfile' is not allowed"),
    ("{_target_:this.nothing}", "'this.nothing' is not allowed (nothing was imported)"),
    ("{_target_:filters.models.constant_velocity_transition,dt:1.0}", "is a function, not a class"),
])
def test_a_target_outside_the_allowed_packages_is_refused_before_import(tmp_path, node, says):
    """Item 5: '+filters.evil={_target_:builtins.open,...}' truncated a file; this.nothing was imported."""
    import importlib
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    sys.modules.pop("this", None)
    with pytest.raises(ConfigError, match=f"filters.evil._target_: .*{re.escape(says)}"):
        run_in_process(tmp_path, "bad", "mc.runs=2", f"+filters.evil={node.replace('VICTIM', str(victim))}")
    assert victim.read_text() == "keep" and not (tmp_path / "victim.txt.copy").exists()
    assert "this" not in sys.modules and importlib.util.find_spec("this") is not None
    assert not (tmp_path / "cache").exists()


def test_a_listed_package_may_name_its_classes(tmp_path):
    with pytest.raises(ConfigError, match=r"'tests.faulty_filters.FaultyFSIMM' is not allowed .*plugins.packages \(now \[\]\)"):
        run_in_process(tmp_path, "no", "mc.runs=2", "filters.fsimm._target_=tests.faulty_filters.FaultyFSIMM")
    out, _ = run_in_process(tmp_path, "yes", "mc.runs=4", "scenario.steps=30", "plugins.packages=[tests]",
                            "filters.fsimm._target_=tests.faulty_filters.FaultyFSIMM", "variants=[fsimm]")
    assert out.summary.height > 0


# ---- item 12: chunks of runs are streamed to the table --------------------------------------------------

def test_the_checksum_is_the_same_however_the_rows_are_chunked():
    """A table streamed in chunks of runs is verified when read back whole: one checksum for both."""
    from pipeline.storage.store import TableChecksum, content_checksum
    rng = np.random.default_rng(0)
    n = 5000
    df = pl.DataFrame({"run": np.arange(n) // 100, "x": rng.normal(size=n),
                       "name": [None if i % 7 == 0 else f"v{i}" for i in range(n)],
                       "P": pl.Series(rng.normal(size=(n, 3)), dtype=pl.Array(pl.Float64, 3)),
                       "count": [None if i % 5 == 0 else i for i in range(n)],
                       "pairs": [[i, i + 1] if i % 3 else None for i in range(n)]})
    whole = content_checksum(df, {"mtt.table": "t"})
    chunked = TableChecksum()
    for first, stop in ((0, 17), (17, 4500), (4500, n)):
        chunked.update(df.slice(first, stop - first))
    assert chunked.hexdigest({"mtt.table": "t"}) == whole
    moved_null = df.with_columns(pl.when(pl.col("run") == 5).then(None).otherwise(pl.col("x")).alias("x"))
    assert content_checksum(moved_null, {"mtt.table": "t"}) != whole
    assert content_checksum(df, {"mtt.table": "u"}) != whole                 # the metadata counts too


def test_chunks_of_runs_are_streamed_to_the_table_one_row_group_each(tmp_path):
    """Item 12: mc.chunk_runs filtered in chunks but concatenated them before writing, so it did not
    bound memory. Each chunk is now written as it comes (a row group), and the table equals the
    unchunked one."""
    import pyarrow.parquet as pq
    whole, _ = run_in_process(tmp_path, "whole", "mc.runs=7", "scenario.steps=30", "cache.enabled=false")
    chunked, ctx = run_in_process(tmp_path, "chunked", "mc.runs=7", "scenario.steps=30", "mc.chunk_runs=3",
                                  "cache.enabled=false")
    table = ctx.run_dir / "estimates" / "fsimm.parquet"
    assert pq.ParquetFile(table).metadata.num_row_groups == 3                  # runs 0-2, 3-5, 6
    assert pl.read_parquet(table).equals(pl.read_parquet(tmp_path / "runs" / "whole" / "estimates" / "fsimm.parquet"))
    def numbers(summary):
        return summary.filter(~pl.col("series").str.contains("compute")).select("variant_key", "series", "window", "value")
    assert numbers(chunked.summary).equals(numbers(whole.summary))


# ---- item 11: too many runs for the machine ----------------------------------------------------------

def test_a_job_estimated_beyond_the_memory_limit_is_refused_before_any_stage(tmp_path):
    """Item 11: mc.runs=200000 ran 63 s and wrote 589 MB of cache, then failed to allocate 4.79 GiB."""
    with pytest.raises(ConfigError, match=r"mc.runs: 20000 runs need about [0-9.]+ GB at the job's peak .* more "
                                          r"than the 1.0 GB mc.max_memory_gb=1. Lower mc.runs to at most \d+"):
        run_in_process(tmp_path, "big", "mc.runs=20000", "mc.max_memory_gb=1")
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()


def test_without_a_limit_the_memory_available_now_is_the_limit(tmp_path, monkeypatch):
    from pipeline.run import memory
    monkeypatch.setattr(memory, "available_bytes", lambda: 512 * 2**20)
    with pytest.raises(ConfigError, match=r"more than the 0.5 GB available on this machine now"):
        run_in_process(tmp_path, "big", "mc.runs=200000")
    with pytest.raises(ConfigError, match=r"mc.max_memory_gb: -1 is not allowed"):
        run_in_process(tmp_path, "bad", "mc.runs=2", "mc.max_memory_gb=-1")


def test_the_estimate_scales_with_runs_and_allows_what_fits():
    from pipeline.run.memory import BASELINE_BYTES, MemoryEstimate
    guess = MemoryEstimate(runs=1000, steps=201, per_run_inputs=26_000, per_run_estimates=150_000, per_run_peak=300_000)
    assert guess.peak == BASELINE_BYTES + 1000 * 300_000
    assert guess.max_runs(BASELINE_BYTES + 3_000_000) == 10
