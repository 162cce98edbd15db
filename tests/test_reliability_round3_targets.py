"""Issue 37 (reliability, round 3), items 5-7: what a config, the command line and a stored run folder
may instantiate. Each case is one that ran code or truncated a file before."""

from __future__ import annotations

import re

import pytest
from omegaconf import OmegaConf

from pipeline.errors import ConfigError
from pipeline.run.config import check_targets


# ---- item 6: a class reached through an allowed module is checked where it is defined ----------------

MODULE_ATTRIBUTES = [("pipeline.run.runner.logging.FileHandler", "logging.FileHandler"),
                     ("pipeline.storage.store.np.memmap", "numpy.memmap"),
                     ("stonesoup.types.array.np.memmap", "numpy.memmap")]


@pytest.mark.parametrize("target, defined", MODULE_ATTRIBUTES)
def test_a_module_attribute_of_an_allowed_package_is_refused_where_it_is_defined(target, defined):
    """Item 6: these passed the check, the name's first part being an allowed package."""
    if target.startswith("stonesoup."):
        pytest.importorskip("stonesoup")
    cfg = OmegaConf.create({"filters": {"evil": {"_target_": target}}})
    with pytest.raises(ConfigError) as info:
        check_targets(cfg)
    message = str(info.value)
    assert message.startswith(f"filters.evil._target_: {target!r} is not allowed: it is {defined}, defined outside "
                              f"the allowed packages")
    assert "plugins.packages" in message and "\n" not in message


def test_a_module_attribute_builds_nothing_in_a_run(tmp_path):
    """Item 6: '+filters.evil={_target_: pipeline.run.runner.logging.FileHandler, ...}' truncated the file
    (the variant was built before its missing run() was noticed)."""
    from tests.test_pipeline import run_in_process
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    node = f"{{_target_: pipeline.run.runner.logging.FileHandler, filename: '{victim}', mode: w}}"
    with pytest.raises(ConfigError, match=re.escape("is logging.FileHandler, defined outside the allowed packages")):
        run_in_process(tmp_path, "bad", "mc.runs=2", f"+filters.evil={node}")
    assert victim.read_text() == "keep"


def test_a_class_of_the_project_that_is_no_component_is_refused(tmp_path):
    """Item 6, its contract half: pipeline.storage.store.TableStream is defined in the project, and building
    it made a temp file beside whatever path it was given."""
    beside = tmp_path / "elsewhere" / "x.parquet"
    beside.parent.mkdir()
    cfg = OmegaConf.create({"report": {"tables": {"evil": {"_target_": "pipeline.storage.store.TableStream",
                                                           "path": str(beside)}}}})
    with pytest.raises(ConfigError, match=r"report.tables.evil._target_: 'pipeline.storage.store.TableStream' is not "
                                          r"allowed: pipeline.storage.store.TableStream implements none of the "
                                          r"project's contracts; a _target_ must name a component: a study"):
        check_targets(cfg)
    assert list(beside.parent.iterdir()) == []


def test_every_target_in_conf_implements_a_contract():
    """The contract check keeps every class the shipped configs name (and Stone Soup's writer, when listed)."""
    import inspect
    from pathlib import Path

    from hydra.utils import get_object

    from pipeline.run.config import implemented_contract
    root = Path(__file__).resolve().parents[1] / "conf"
    targets = sorted({m.group(1) for p in root.rglob("*.yaml")
                      for m in re.finditer(r"_target_:\s*([A-Za-z0-9_.]+)", p.read_text())})
    assert len(targets) > 40
    for target in targets:
        if target.startswith("stonesoup.") and pytest.importorskip("stonesoup") is None:
            continue
        obj = get_object(target)
        cls = obj.__self__ if inspect.ismethod(obj) else obj
        assert implemented_contract(cls) is not None, target


# ---- item 5: what the config names for Hydra itself to build -----------------------------------------

def run_entry(monkeypatch, tmp_path, *args: str) -> int:
    """``python -m pipeline ARGS`` in this process (its exit code); cwd and artifacts in ``tmp_path``."""
    import sys

    from pipeline.__main__ import entry
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "argv", ["pipeline", *args, f"paths.artifacts={tmp_path / 'art'}"])
    with pytest.raises(SystemExit) as info:
        entry()
    return info.value.code


def evil_callback(victim) -> str:
    return f"{{_target_: logging.FileHandler, filename: '{victim}', mode: w}}"


@pytest.mark.parametrize("sweep", [False, True])
def test_a_callback_outside_the_allow_list_is_refused_before_hydra_builds_it(tmp_path, monkeypatch, capsys, sweep):
    """Item 5: '+hydra.callbacks.evil={_target_: logging.FileHandler, filename: F, mode: w}' truncated F
    (Hydra builds its callbacks before the task function checks anything), in a run and in a sweep."""
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    args = ["-m", "mc.seed=1,2"] if sweep else []
    code = run_entry(monkeypatch, tmp_path, *args, "mc.runs=0", f"+hydra.callbacks.evil={evil_callback(victim)}")
    assert victim.read_text() == "keep"
    assert code == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("error: hydra.callbacks.evil._target_: 'logging.FileHandler' is not allowed (nothing was "
                           "imported)") and "plugins.packages" in line
    assert not (tmp_path / "art").exists()             # before any work: no run or sweep folder


def test_a_callback_set_by_an_experiment_file_is_refused(tmp_path):
    """Item 5: an experiment YAML can set hydra.callbacks too (a callback chain there ran a command)."""
    from tests.test_pipeline import cli
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / "extra" / "experiment").mkdir(parents=True)
    (tmp_path / "extra" / "experiment" / "evil.yaml").write_text(
        "# @package _global_\ndefaults:\n  - ao_vsimm_s1\n  - _self_\nexperiment_name: evil\nhydra:\n  callbacks:\n"
        f"    evil:\n      _target_: logging.FileHandler\n      filename: '{victim}'\n      mode: w\n")
    proc = cli(tmp_path, f"--config-dir={tmp_path / 'extra'}", "experiment=evil", "mc.runs=0")
    assert victim.read_text() == "keep" and proc.returncode == 2
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith("error: hydra.callbacks.evil._target_: 'logging.FileHandler' is not allowed")
    assert not (tmp_path / "runs").exists()


def test_a_callback_must_be_a_hydra_callback_defined_where_allowed():
    """Item 5: a callback node is checked as every _target_ is (item 6 included), and must be a Callback."""
    from pipeline.run.config import check_hydra_targets

    def hydra(callbacks=None, **parts):
        return OmegaConf.create({"plugins": {"packages": []}, "hydra": {"callbacks": callbacks or {}, **parts}})

    check_hydra_targets(hydra({"output_folders": {"_target_": "pipeline.launch.folders.OutputFolders"}}))
    for node, says in [({"_target_": "pipeline.views.tables.SummaryTable"}, "a callback must be a Hydra callback"),
                       ({"_target_": "pipeline.run.runner.logging.FileHandler"}, "is logging.FileHandler, defined outside"),
                       ({"_target_": "pipeline.launch.folders.OutputFolders", "x": {"_target_": "builtins.open"}},
                        "hydra.callbacks.evil.x._target_: 'builtins.open' is not allowed"),
                       ("oops", "a callback is a node whose _target_ names a Hydra callback class")]:
        with pytest.raises(ConfigError, match=re.escape(says)):
            check_hydra_targets(hydra({"evil": node}))
    with pytest.raises(ConfigError, match=re.escape("hydra.launcher._target_: 'logging.FileHandler' is not allowed "
                                                    "(nothing was imported); a launcher must be a Hydra plugin")):
        check_hydra_targets(hydra(launcher={"_target_": "logging.FileHandler", "filename": "x"}))
    with pytest.raises(ConfigError, match=re.escape("hydra.sweeper.sampler._target_: 'logging.FileHandler' is not "
                                                    "allowed (nothing was imported)")):
        check_hydra_targets(hydra(sweeper={"_target_": "hydra_plugins.hydra_optuna_sweeper.optuna_sweeper.OptunaSweeper",
                                           "sampler": {"_target_": "logging.FileHandler"}}))


@pytest.mark.parametrize("args", [["mc.runs=2"], ["-m", "mc.seed=1,2", "hydra/launcher=isolated"],
                                  ["-m", "hydra/launcher=slurm"], ["-m", "hydra/launcher=ray_local"],
                                  ["-m", "experiment=ao_vsimm_s2", "tune=vsimm_thresholds"]])
def test_the_shipped_callbacks_launchers_and_sweepers_pass(args):
    """The check composes the config as Hydra will and keeps what the project ships."""
    from pipeline.__main__ import register_isolated_launcher
    from pipeline.launch.hydra_targets import check_command, composed
    if "tune=vsimm_thresholds" in args:
        pytest.importorskip("optuna")
    register_isolated_launcher()
    cfg = composed(args)
    assert cfg is not None and "output_folders" in cfg.hydra.callbacks
    check_command(args)
