"""Issue 16 (reliability, round 2): the items fixed so far, each with the case that went wrong."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.errors import ConfigError
from pipeline.faults import FAULTS, fault_flags, fault_summary
from pipeline.store import inside
from tests.test_pipeline import cli, run_in_process


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
    proc = cli(tmp_path, f"--config-dir={tmp_path / 'conf_extra'}", "experiment=escape", "mc.runs=2",
               "scenario.steps=20", "record.enabled=false")
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
    from pipeline.query import QueryError, query
    from pipeline.report import TargetSpec, evaluate_target, load_run
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
