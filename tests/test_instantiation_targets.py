"""What a config, the command line and a stored run folder may instantiate (issue 37, items 5-7).
Each case is one that ran code or truncated a file before."""

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
    from tests.helpers.runs import run_in_process
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
    from tests.helpers.processes import run_pipeline
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (tmp_path / "extra" / "experiment").mkdir(parents=True)
    (tmp_path / "extra" / "experiment" / "evil.yaml").write_text(
        "# @package _global_\ndefaults:\n  - ao_vsimm_s1\n  - _self_\nexperiment_name: evil\nhydra:\n  callbacks:\n"
        f"    evil:\n      _target_: logging.FileHandler\n      filename: '{victim}'\n      mode: w\n")
    proc = run_pipeline(f"--config-dir={tmp_path / 'extra'}", "experiment=evil", "mc.runs=0", artifacts=tmp_path)
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


# ---- item 7: a stored run folder is input --------------------------------------------------------------

class MarkingTable:
    """A report table whose building leaves a mark: a class of a package the stored config lists."""

    def __init__(self, marker: str) -> None:
        from pathlib import Path
        Path(marker).write_text("built")

    def render(self, ctx) -> str:
        return ""


def stored_run(tmp_path, *, packages, tables, **values):
    """A run folder as python -m pipeline leaves one (config.yaml resolved, status ok), holding only
    what the checks before any stage read: the config the user may have edited, or got from elsewhere."""
    import json

    from tests.helpers.config import composed_config
    from omegaconf import open_dict
    cfg = composed_config(f"paths.artifacts={tmp_path}", "mc.runs=2", "record.enabled=false")
    with open_dict(cfg):
        cfg.plugins.packages = packages
        cfg.report.tables = tables
        for key, value in values.items():
            OmegaConf.update(cfg, key, value)
    run = tmp_path / "runs" / "ao_vsimm_s1" / "stored"
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    (run / "status.json").write_text(json.dumps({"status": "ok", "run_id": "stored"}))
    return run


def test_recompute_builds_nothing_a_stored_config_names_through_its_report_tables(tmp_path, capsys):
    """Item 7: 'report.tables.evil' in a run folder's config.yaml was built by python -m pipeline.recompute
    (pipeline.run.runner.logging.FileHandler truncated its file)."""
    from pipeline.results.recompute import main
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    run = stored_run(tmp_path, packages=[], tables={"evil": {"_target_": "pipeline.runner.logging.FileHandler",
                                                             "filename": str(victim), "mode": "w"}})
    assert main([str(run)]) == 2
    assert victim.read_text() == "keep"
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith("recompute: report.tables.evil._target_: 'pipeline.run.runner.logging.FileHandler' is "
                           "not allowed: it is logging.FileHandler, defined outside the allowed packages")


def test_a_stored_folders_own_plugins_packages_are_not_taken_on_its_word(tmp_path, capsys):
    """Item 7: a config.yaml listing a package (plugins.packages: [tests]) had any class of it built by
    python -m pipeline.recompute; now only a package the user names (--plugins) is."""
    from pipeline.results.recompute import main
    marker = tmp_path / "built.txt"
    run = stored_run(tmp_path, packages=["tests"], tables={"mark": {
        "_target_": "tests.test_instantiation_targets.MarkingTable", "marker": str(marker)}})
    assert main([str(run)]) == 2
    assert not marker.exists()
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"recompute: {run / 'config.yaml'}: plugins.packages: ['tests'] is not taken from a stored "
                           f"run folder") and line.endswith(f"python -m pipeline.recompute {run} --plugins tests.")
    # named by the user, the package is allowed: the table is built (the folder has no tables to read then)
    assert main([str(run), "--plugins", "tests"]) == 2
    assert marker.read_text() == "built" and "truth.parquet" in capsys.readouterr().err


def test_rerun_takes_a_stored_folders_plugins_packages_only_from_the_command_line(tmp_path, capsys):
    """Item 7: python -m pipeline.rerun built the classes of the packages a stored config listed."""
    from pipeline.results.rerun import main
    marker = tmp_path / "built.txt"
    # two variants of one display name: refused once the report tables are built, before any stage
    run = stored_run(tmp_path, packages=["tests"], tables={"mark": {
        "_target_": "tests.test_instantiation_targets.MarkingTable", "marker": str(marker)}},
        **{"filters.vsimm.name": "FSIMM"})
    assert main([str(run)]) == 2
    assert not marker.exists()
    err = capsys.readouterr().err
    assert "plugins.packages: ['tests'] is not taken from a stored run folder" in err
    assert f"python -m pipeline.rerun {run} plugins.packages=[tests]." in err
    assert main([str(run), "plugins.packages=[tests]"]) == 2
    assert marker.read_text() == "built" and "filters.vsimm.name: 'FSIMM' is also the display name" in capsys.readouterr().err
