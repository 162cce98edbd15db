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
