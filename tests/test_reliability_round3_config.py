"""Issue 37 (reliability, round 3), items 20, 8, 14 and 19: a config the job would misread is refused
before any work, a stored config edited after its run is not certified, a singular bound is NaN."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.errors import ConfigError


def _job(tmp_path: Path, name: str, *overrides: str):
    """(cfg, ctx) of an in-process single run ``runs/<name>`` (record off), as ``python -m pipeline`` makes them."""
    from pipeline.run.runner import RunContext
    from tests.helpers.config import composed_config
    cfg = composed_config(f"paths.artifacts={tmp_path}", "record.enabled=false", *overrides)
    return cfg, RunContext(tmp_path / "runs" / name, tmp_path, list(overrides))


# ---- item 20: a '+' key that nothing reads is refused ----------------------------------------------

@pytest.mark.parametrize("override, message", [
    ("+mc.rnus=5", "+mc.rnus=5: 'mc' has no key 'rnus' that anything reads, so the job would run with it ignored. "
                   "Did you mean 'mc.runs'? Its keys are: runs, seed, chunk_runs, max_memory_gb. Set one of them "
                   "without the '+' (mc.runs=5)."),
    ("+record.enable=false", "+record.enable=false: 'record' has no key 'enable' that anything reads, so the job "
                             "would run with it ignored. Did you mean 'record.enabled'? Its keys are: enabled, runs. "
                             "Set one of them without the '+' (record.enabled=false)."),
    ("++mc.rnus=5", "++mc.rnus=5: 'mc' has no key 'rnus' that anything reads"),
    ("+uncertainty.confidance=0.9", "Did you mean 'uncertainty.confidence'?"),
    ("+timing.pases=2", "Did you mean 'timing.passes'?"),
    ("+mc.sub.x=1", "+mc.sub.x=1: 'mc' has no key 'sub' that anything reads"),
    ("+sead=3", "+sead=3: the config's top level has no key 'sead' that anything reads"),
])
def test_a_plus_key_that_nothing_reads_is_refused_with_the_close_names(tmp_path, override, message):
    """Item 20: ``+mc.rnus=5`` and ``+record.enable=false`` (Hydra's own suggestion for a typo) ran with
    the key ignored. Before: the job ran (no ConfigError); after: one paragraph, before any work."""
    from pipeline.run.runner import run_experiment
    with pytest.raises(ConfigError) as info:
        run_experiment(*_job(tmp_path, "bad", "mc.runs=2", override))
    assert message in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / "cache").exists() and not (tmp_path / "runs").exists()


def test_a_plus_key_is_refused_on_the_command_line_with_exit_2(tmp_path):
    """Item 20 as the user meets it: exit 2, one paragraph, no traceback, no run folder left."""
    from tests.helpers.processes import run_pipeline
    proc = run_pipeline("+mc.rnus=5", "record.enabled=false", artifacts=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert "error: +mc.rnus=5: 'mc' has no key 'rnus' that anything reads" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("*.parquet"))


def _explained(override: str) -> str:
    """pipeline.launch.refusals' paragraph for Hydra's refusal of ``override``."""
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException

    from pipeline.launch.refusals import explain
    from tests.helpers.config import CONF
    with initialize_config_dir(version_base="1.3", config_dir=str(CONF)):
        with pytest.raises(HydraException) as info:
            compose("config", overrides=[override])
    return explain(info.value, [override])


def test_hydras_refusal_of_a_fixed_node_key_does_not_suggest_the_plus():
    """The paragraph for ``mc.rnus=5`` (no '+') suggested ``+mc.rnus=5``, the override item 20 refuses;
    under a ``_target_`` node ('sensors') the '+' adds a constructor parameter and is still suggested."""
    fixed = _explained("mc.rnus=5")
    assert "Did you mean 'runs'?" in fixed and "+mc.rnus" not in fixed
    assert "Its keys are fixed (a '+' key there is read by nothing)" in fixed
    assert "To add a new key, write +sensors.noise_stdd=5" in _explained("sensors.noise_stdd=5")


@pytest.mark.parametrize("override", ["+filters.fsimm.foo=1", "+scenario.foo=1"])
def test_a_plus_key_under_a_target_node_is_left_to_its_constructor(tmp_path, override):
    from pipeline.run.runner import run_experiment
    with pytest.raises(ConfigError, match=r"foo: 1 is not a parameter of"):
        run_experiment(*_job(tmp_path, "bad", "mc.runs=2", override))


def test_plus_keys_that_are_read_still_run(tmp_path):
    """An interpolated '+' key, a new filter variant from its config group and a key under a user-named
    mapping are read: they run."""
    from pipeline.run.runner import run_experiment
    out = run_experiment(*_job(tmp_path, "ok", "mc.runs=2", "scenario.steps=20", "+my_noise=15",
                               "sensors.noise_std=${my_noise}", "+filter@filters.extra=fsimm",
                               "filters.extra.name=FSIMM-2", "+metrics.windows.early=[0,10]"))
    assert "FSIMM-2" in set(out.summary["variant"]) and "early" in set(out.summary["window"])
    assert out.summary["sensors.noise_std"].unique().to_list() == [15]


def test_the_fixed_keys_are_conf_config_yamls_and_every_experiments_top_level():
    """FIXED_KEYS must follow conf/config.yaml (a key added there is read, one removed is not), and the
    top level must hold every top-level key of every experiment."""
    from omegaconf import OmegaConf

    from pipeline.launch.refusals import FIXED_KEYS
    from tests.helpers.config import composed, CONF
    base = OmegaConf.load(CONF / "config.yaml")
    for node, keys in FIXED_KEYS.items():
        if node:
            assert list(base[node].keys()) == list(keys), node
    assert set(base.keys()) - {"defaults", "hydra"} <= set(FIXED_KEYS[""])
    for path in sorted((CONF / "experiment").glob("*.yaml")):
        cfg = composed(path.stem)
        assert set(cfg.keys()) - {"hydra"} <= set(FIXED_KEYS[""]), path.stem


# ---- item 8: a run folder stays where it belongs and writes over nothing -----------------------------

@pytest.mark.parametrize("name, why", [
    ("../../escaped", "a '/' or '..' places the run folder outside paths.artifacts"),
    ("", "'' leaves the run unlabelled"),
    ("a/b", "a '/' or '..'"),
    ("..", "a '/' or '..'"),
])
def test_an_experiment_name_that_is_not_a_name_is_refused_in_process(tmp_path, name, why):
    """Item 8, in process (validate; pipeline.results.rerun and the tests run jobs so). Before: the
    job ran (runs/'' and runs/../../escaped)."""
    from omegaconf import OmegaConf

    from pipeline.run.runner import run_experiment
    cfg, ctx = _job(tmp_path, "bad", "mc.runs=2")
    OmegaConf.update(cfg, "experiment_name", name)
    with pytest.raises(ConfigError) as info:
        run_experiment(cfg, ctx)
    text = str(info.value)
    assert text.startswith(f"experiment_name: {name!r} is not allowed ({why}") and "1-64 letters" in text
    assert not (tmp_path / "runs").exists() and not (tmp_path / "cache").exists()


def test_an_experiment_name_that_escapes_or_is_empty_is_refused_before_hydra_makes_a_folder(tmp_path):
    """Item 8 on the command line: ``experiment_name=../../escaped`` wrote its run folder two levels
    above paths.artifacts/runs, ``experiment_name=''`` ran unlabelled. Before: exit 0 and the folders;
    after: exit 2, one paragraph, no folder anywhere."""
    from tests.helpers.processes import run_pipeline
    artifacts = tmp_path / "a" / "b"
    for name, folder in (("../../escaped", tmp_path / "a" / "escaped"), ("''", artifacts / "runs")):
        proc = run_pipeline(f"paths.artifacts={artifacts}", f"experiment_name={name}", "mc.runs=2",
                            "scenario.steps=20", "record.enabled=false", artifacts=tmp_path)
        assert proc.returncode == 2, proc.stderr
        assert "error: experiment_name: " in proc.stderr and "Traceback" not in proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert not folder.exists()
    assert not (tmp_path / "a" / "escaped").exists() and not (artifacts / "cache").exists()


def test_a_run_folder_that_holds_another_folders_files_is_refused_and_untouched(tmp_path):
    """Item 8: ``hydra.run.dir=../..`` wrote its config.yaml (and the rest) over another folder's. Before:
    exit 0 and config.yaml replaced; after: exit 2 naming the files, every byte there as it was. A new
    folder and an earlier run's folder (run into again, as after a kill) still run, and what a run writes
    is RUN_FILES (besides its log)."""
    from tests.helpers.processes import run_pipeline
    other = tmp_path / "project"
    (other / "conf").mkdir(parents=True)
    (other / "config.yaml").write_text("theirs: 1\n")
    (other / "summary.parquet").write_bytes(b"not ours")
    (other / "conf" / "x.yaml").write_text("x: 1\n")
    before = {p: p.read_bytes() for p in other.rglob("*") if p.is_file()}
    proc = run_pipeline(f"hydra.run.dir={other}", "mc.runs=2", "scenario.steps=20", artifacts=tmp_path)
    assert proc.returncode == 2, proc.stderr
    assert (f"error: hydra.run.dir={other}: {other} already holds config.yaml, summary.parquet, which a run writes "
            f"there, and it is not an earlier run's folder") in proc.stderr
    assert "Traceback" not in proc.stderr and len(proc.stderr.strip().splitlines()) == 1
    assert {p: p.read_bytes() for p in other.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in other.iterdir()) == ["conf", "config.yaml", "summary.parquet"]

    run = tmp_path / "new" / "run"
    for _ in range(2):                        # a new folder, then the same folder again: an earlier run's
        proc = run_pipeline(f"hydra.run.dir={run}", "mc.runs=2", "scenario.steps=20", artifacts=tmp_path)
        assert proc.returncode == 0, proc.stderr
    from pipeline.launch.folders import RUN_FILES
    written = {p.name for p in run.iterdir() if not p.name.endswith(".log")}
    assert "recording.rrd" in written and written <= RUN_FILES, written - RUN_FILES


# ---- item 14: recompute holds config.yaml to the hash the run recorded ------------------------------

def test_recompute_refuses_a_config_edited_after_the_run(smoke_runs, tmp_path, capsys):
    """Item 14: a run folder whose config.yaml was edited after the run (here its description, a
    value the recomputed metrics do not read) was certified "equal to
    the stored table bit for bit". Before: exit 0 and that line; after: exit 2 naming both hashes, nothing
    recomputed. The folder as the run wrote it says its hash is the one recorded."""
    import json
    import shutil

    from omegaconf import OmegaConf

    from pipeline.results.recompute import main
    _, ctx = smoke_runs("ao_vsimm_s1")
    run = tmp_path / "run"
    shutil.copytree(ctx.run_dir, run)
    recorded = json.loads((run / "status.json").read_text())["config_hash"]
    as_written = (run / "config.yaml").read_bytes()
    edited = OmegaConf.load(run / "config.yaml")
    edited.description = f"{edited.description} (edited)"
    OmegaConf.save(edited, run / "config.yaml")
    assert main([str(run)]) == 2
    captured = capsys.readouterr()
    assert "bit for bit" not in captured.out
    assert "config.yaml: edited after the run: its config hash is " in captured.err
    assert f"but the run recorded {recorded} (status.json's config_hash)" in captured.err
    assert "nothing was recomputed" in captured.err and len(captured.err.strip().splitlines()) == 1

    (run / "config.yaml").write_bytes(as_written)
    assert main([str(run)]) == 0
    out = capsys.readouterr().out
    assert f"config.yaml: config hash {recorded}, the one the run recorded (status.json's config_hash)" in out
    assert out.count("equal to the stored table bit for bit") == 2


# ---- item 19: study 000's bound at a noise-free or near noise-free range ----------------------------

@pytest.mark.parametrize("range_std", ["1e-9", "0"])
def test_study_000s_bound_is_nan_with_one_warning_at_a_singular_range_noise(tmp_path, caplog, range_std):
    """Item 19: ``experiment=mie_los sensors.range_std=1e-9`` (or 0, the sensor's noise-free channel)
    ended the job with ``LinAlgError: Singular matrix`` in the bound's information (the converted
    covariance R_I inverted). Before: LinAlgError; after: the job writes every table, position_bound and
    position_bound_model are NaN with one warning each, the other metrics are numbers."""
    import logging

    import polars as pl

    from pipeline.run.runner import run_experiment
    with caplog.at_level(logging.WARNING, logger="pipeline"):
        out = run_experiment(*_job(tmp_path, "run", "experiment=mie_los", "mc.runs=2",
                                   f"sensors.range_std={range_std}"))
    singular = [r.getMessage() for r in caplog.records if "PCRLB is singular" in r.getMessage()]
    assert len(singular) == 1, singular                     # both bounds meet it: said once
    assert "scan 0" in singular[0] and "position_bound and its ratios are NaN there" in singular[0]
    summary = out.summary
    bound = summary.filter(pl.col("series").is_in(["position_bound", "position_bound_model"]))
    assert bound.height > 0 and bound["value"].is_nan().fill_null(True).all()
    rmse = summary.filter(pl.col("series") == "position_rmse")["value"]
    assert rmse.len() > 0 and rmse.is_finite().all()


def test_study_000s_bound_is_a_number_at_small_but_regular_range_noise():
    """The NaN is for a singular R_I only: at range_std=1e-3 m the bound is a number every scan after the
    first, below its value at the paper's 10 m."""
    import warnings

    import numpy as np
    from hydra.utils import instantiate

    from tests.helpers.config import composed
    values = {}
    for std in (1e-3, 10.0):
        cfg = composed("mie_los", f"sensors.range_std={std}")
        truth = instantiate(cfg.scenario).generate(2, 1)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            values[std] = instantiate(cfg.bound).position_bound(truth, instantiate(cfg.sensors))
        assert np.isnan(values[std][0]) and np.isfinite(values[std][1:]).all()
    assert (values[1e-3][1:] < values[10.0][1:]).all()
