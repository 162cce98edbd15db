"""Issue 38 (what a new user hits): each test failed on the code before its fix.

(d) numbers keyed by value; (e) Hydra's refusals with close names; (a) the compute column's
timing; (b) the kernels' compile message and the warm-up command; (c) your own filter; (f) re-running
a stored run into the artifacts tree."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.helpers.config import composed
from tests.helpers.processes import run_command, run_pipeline


# ---- (d) sensors.noise_std=20 and =20.0 are one cache key ---------------------------------------------

def _stage_keys(*overrides: str) -> dict[str, str]:
    """Every declared stage's cache key, as the runner computes it, for the default experiment."""
    from omegaconf import OmegaConf
    from pipeline.run.runner import build_fault_checks, prepare
    from pipeline.run.stages import declare
    from pipeline.storage.keys import stage_key

    cfg = composed("ao_vsimm_s1", "mc.runs=2", *overrides)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    stages, _ = declare(cfg, resolved, prepare(cfg), build_fault_checks(cfg))
    keys: dict[str, str] = {}
    for stage in stages:
        keys[stage.output] = stage_key(stage.cache, stage.config, tuple(keys[i] for i in stage.inputs),
                                       stage.producers)
    return keys


def test_an_integral_number_typed_as_int_or_float_gives_one_cache_key():
    """Before: noise_std=20 and 20.0 hashed their JSON text ('20' vs '20.0'): two keys, a recompute."""
    as_int, as_float = _stage_keys("sensors.noise_std=20"), _stage_keys("sensors.noise_std=20.0")
    assert as_int == as_float
    assert _stage_keys("sensors.noise_std=20.5")["detections"] != as_int["detections"]   # a value still counts


# ---- (e) a typo in a key or an option gets the close names, one paragraph -------------------------------

def _cli(tmp_path, *args: str):
    return run_pipeline(*args, artifacts=tmp_path)


@pytest.mark.parametrize("args, says", [
    (("sensors.noise_stdd=20",), "error: sensors.noise_stdd=20: 'sensors' has no key 'noise_stdd'. Did you mean "
                                 "'noise_std'?"),
    (("experiment=mie_loss",), "error: experiment=mie_loss: conf/experiment/ has no option 'mie_loss'. Did you "
                               "mean 'mie_los'?"),
    (("+filter@filters.x=fsim",), "conf/filter/ has no option 'fsim'. Did you mean 'fsimm'"),
    (("filterz.fsimm.name=x",), "the config's top level has no key 'filterz'. Did you mean 'filters'?"),
])
def test_a_typo_in_a_key_or_an_option_names_the_close_ones(tmp_path, args, says):
    """Before: Hydra's own text (``Key 'noise_stdd' is not in struct``, ``full_key``, ``object_type``, a
    list of every option) without the close names."""
    proc = _cli(tmp_path, *args)
    assert proc.returncode == 2, proc.stderr
    assert says in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and "object_type" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1              # one paragraph
    assert not (tmp_path / "runs").exists()


# ---- (a) the compute column: several passes in this process, cached times marked ------------------------

def test_timing_takes_turns_stops_at_the_passes_and_the_budget_and_marks_a_cached_time():
    """The invariants of pipeline.evaluation.timing.time_passes (not timing values: a fake clock)."""
    from pipeline.evaluation.timing import time_passes
    now, calls = [0.0], []

    def pass_of(name: str, seconds: float):
        def run() -> float:
            calls.append(name)
            now[0] += seconds
            return seconds
        return run

    timings = time_passes({"a": pass_of("a", 1.0), "b": pass_of("b", 0.5), "slow": pass_of("slow", 9.0),
                           "cached": pass_of("cached", 1.0)},
                          first={"a": 1.0, "b": None, "slow": None, "cached": None},
                          stored={"a": 1.0, "b": 0.5, "slow": 9.0, "cached": 1.0},
                          passes=4, budget_s=3.0, clock=lambda: now[0])
    assert timings["a"].passes == (1.0, 1.0, 1.0) and not timings["a"].cached        # 3 s budget: 3 passes
    assert timings["b"].count == 4 and not timings["b"].cached                         # at most `passes`
    assert timings["slow"].cached and timings["slow"].passes == (9.0,) and "slow" not in calls   # over budget
    assert not timings["cached"].cached                                                # re-timed here
    assert calls[:3] == ["a", "b", "cached"]                                           # the variants take turns


def test_a_ratio_with_a_cached_time_is_flagged_and_its_interval_holds_its_value():
    from pipeline.evaluation.timing import Timing, ratio_fields
    here, ref = Timing((1.0, 1.2, 0.9)), Timing((2.0, 2.5, 1.8))
    fields = ratio_fields(here, ref, False)
    assert fields["ci_low"] <= fields["value"] <= fields["ci_high"] and not fields["mixes_processes"]
    assert ratio_fields(here, Timing((2.0,), cached=True), False)["mixes_processes"]
    assert ratio_fields(ref, ref, True)["value"] == 100.0


def test_a_job_times_every_variant_several_times_in_its_process_and_marks_cached_times(tmp_path):
    """Before: compute_seconds was one pass, a cached variant's from whichever process computed it, and the
    summary said neither (no compute_passes / compute_cached / mixes_processes columns)."""
    import polars as pl
    from tests.helpers.runs import run_in_process
    first, _ = run_in_process(tmp_path, "first", "mc.runs=2", "scenario.steps=30", "timing.passes=3",
                              "timing.budget_s=30")
    timed = first.summary.filter(pl.col("series") == "compute_seconds")
    assert timed["compute_passes"].to_list() == [3, 3, 3] and not any(timed["compute_cached"])
    assert (timed["ci_low"] <= timed["value"]).all() and (timed["value"] <= timed["ci_high"]).all()
    ratios = first.summary.filter(pl.col("series") == "compute_pct_of_reference")
    assert ratios.height == 3 and not any(ratios["mixes_processes"])
    # all cached, none re-timed (budget 0): each keeps its stored pass, marked; every ratio is flagged
    again, _ = run_in_process(tmp_path, "again", "mc.runs=2", "scenario.steps=30", "timing.budget_s=0")
    cached = again.summary.filter(pl.col("series") == "compute_seconds")
    assert all(cached["compute_cached"]) and cached["ci_low"].null_count() == cached.height
    flagged = again.summary.filter((pl.col("series") == "compute_pct_of_reference") & (pl.col("variant_key") != "fsimm"))
    assert all(flagged["mixes_processes"])
    assert "(cached)" in again.table and "(mixed)" in again.table and "cost: `models %`" in again.table


# ---- (c) your own filter: the documented example verbatim, and a wrong layout named -----------------------

DOC = Path(__file__).resolve().parents[1] / "docs" / "your-own-filter.md"


def test_the_documented_own_filter_example_runs_verbatim_in_a_fresh_folder(tmp_path):
    """Before: no such page; the README pointed at docs/your-own-study.md, which had no example."""
    import re
    import sys
    text = DOC.read_text()
    files = re.findall(r"<!-- file: (\S+) -->\n```\w*\n(.*?)```", text, re.S)
    commands = re.findall(r"<!-- command -->\n```bash\n(.*?)```", text, re.S)
    assert {path for path, _ in files} >= {"mytrack/cv.py", "mytrack/conf/filter/differenced.yaml"}
    assert len(commands) == 2 and "hydra.searchpath" in commands[0] and "_target_" in commands[1]
    for path, body in files:
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(body)
    for i, command in enumerate(commands):
        assert command.startswith("python -m pipeline ")
        line = command.strip().replace("python -m", f"{sys.executable} -m", 1) + f" paths.artifacts=art{i}"
        proc = run_command(["bash", "-c", line], cwd=tmp_path, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
        assert "Differenced" in proc.stdout and "FSIMM" in proc.stdout
        (written,) = (tmp_path / f"art{i}" / "runs" / "ao_vsimm_s1").glob("*/estimates/mine.parquet")


class TwoComponents:
    """A filter that breaks the layout contract: it writes (x, y) only, not the truth's four components."""
    name = "Two"

    def run(self, measurements):
        from filters.base import TrackEstimate
        R, K = measurements.runs, measurements.scans
        return TrackEstimate(measurements.time, np.nan_to_num(measurements.z), np.tile(np.eye(2), (R, K, 1, 1)), {}, 0.0)


def test_an_estimate_of_the_wrong_layout_is_refused_naming_the_variant_and_the_shape(tmp_path):
    """Before: ValueError 'operands could not be broadcast together with shapes (2,31,2) (2,31,4)'."""
    from pipeline.errors import EstimateLayoutError
    from tests.helpers.runs import run_in_process
    with pytest.raises(EstimateLayoutError) as info:
        run_in_process(tmp_path, "bad", "mc.runs=2", "scenario.steps=30", "plugins.packages=[tests]",
                       "+filters.two={_target_: tests.test_users_round.TwoComponents}")
    message = str(info.value)
    assert message.startswith("filters.two (tests.test_users_round.TwoComponents): its state has shape (2, 31, 2), "
                              "expected (2, 31, 4)")
    assert "['x', 'vx', 'y', 'vy']" in message and "docs/your-own-filter.md" in message


def test_the_base_class_gives_the_layout_of_state_names():
    from filters.base import MeasurementSeries, SingleTargetFilter
    series = MeasurementSeries(np.arange(3.0), np.zeros((2, 3, 2)), np.eye(2), np.ones((2, 3), bool), np.zeros(3, int),
                               state_names=("x", "vx", "y", "vy"))
    state, covariance = SingleTargetFilter.empty_estimate(series)
    assert state.shape == (2, 3, 4) and covariance.shape == (2, 3, 4, 4) and np.isnan(state).all()
    with pytest.raises(TypeError):
        SingleTargetFilter()                      # run is abstract


# ---- (f) a stored run re-run with its config, into the artifacts tree ---------------------------------------

def test_a_stored_run_reruns_into_the_artifacts_tree_with_its_config_and_the_overrides(tmp_path, capsys):
    """Before: no such command; Hydra's --config-path <run>/.hydra wrote to outputs/, which no query reads."""
    import json
    from pipeline.results.query import main as query
    from pipeline.results.rerun import RerunError, rerun
    from tests.helpers.runs import run_in_process
    _, stored = run_in_process(tmp_path, "ao_vsimm_s1/stored", "mc.runs=2", "scenario.steps=30")
    outcome, ctx = rerun(stored.run_dir, ["mc.runs=3", "filters.vsimm.t1_mu=0.85"])
    assert ctx.run_dir.parent == tmp_path / "runs" / "ao_vsimm_s1" and ctx.run_dir != stored.run_dir
    status = json.loads((ctx.run_dir / "status.json").read_text())
    assert status["status"] == "ok" and status["runs"] == 3
    assert status["overrides"][-2:] == ["mc.runs=3", "filters.vsimm.t1_mu=0.85"]
    assert outcome.summary["filters.vsimm.t1_mu"][0] == 0.85 and outcome.summary["scenario.steps"][0] == 30
    assert query(["list", "--root", str(tmp_path), "--format", "csv"]) == 0
    listed = capsys.readouterr().out
    assert ctx.run_id in listed and "runs/ao_vsimm_s1/stored" in listed        # the query sees both
    with pytest.raises(RerunError, match="did you mean 'mc.runs'"):
        rerun(stored.run_dir, ["mc.runz=3"])
    with pytest.raises(RerunError, match="composes a new config"):
        rerun(stored.run_dir, ["scenario=ao_vsimm_s2"])


# ---- (b) first use: the compile is announced; a warm-up command compiles up front ---------------------------

def test_a_slow_kernel_load_says_once_that_it_compiles_and_how_long_it_took(caplog):
    """Before: the first job compiled for 21.5 s without a word."""
    import logging
    import time as clock
    from filters.compiling import compiling
    with caplog.at_level(logging.INFO, logger="filters.compiling"):
        with compiling("filters.example.kernel", notice_after_s=0.05):
            clock.sleep(0.3)
        with compiling("filters.example.kernel", notice_after_s=5.0):
            pass                                              # a cached load: nothing said
    lines = [r.getMessage() for r in caplog.records if r.name == "filters.compiling"]
    assert len(lines) == 2 and lines[0].startswith("compiling the numba kernels of filters.example.kernel: once per "
                                                   "install") and "python -m pipeline.run.warmup" in lines[0]
    assert lines[1].startswith("compiled the numba kernels of filters.example.kernel in ")


def test_every_kernel_warm_up_is_announced():
    import re
    root = Path(__file__).resolve().parents[1]
    sites = 0
    for path in sorted((root / "filters").glob("*/reference.py")):
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            if re.search(r"\w+_kernel\.warm_up\(\)", line):
                sites += 1
                assert "with compiling(" in lines[i - 1], f"{path}:{i + 1}"
    assert sites >= 6


def test_the_warm_up_command_runs_a_study_and_the_readme_names_it(capsys):
    from pipeline.run.warmup import main
    assert main(["--experiments", "ao_vsimm_s1"]) == 0
    assert capsys.readouterr().out.startswith("ao_vsimm_s1: ")
    assert "python -m pipeline.run.warmup" in (Path(__file__).resolve().parents[1] / "README.md").read_text()
