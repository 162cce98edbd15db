"""A stored run keeps the class names of its day: a config.yaml written before issue 39's moves
(``pipeline.tables.SummaryTable``, ``pipeline.studies.mie_los.sensor.Radar3D``) is read under today's
names, and the report and recompute commands read such a folder."""

from __future__ import annotations

import shutil

from omegaconf import OmegaConf

from pipeline.run.stored import MOVED_MODULES, current_target, stored_config, upgrade_targets


def test_a_moved_name_maps_to_where_it_is_now_and_others_stay():
    assert current_target("pipeline.tables.SummaryTable") == "pipeline.views.tables.SummaryTable"
    assert current_target("pipeline.folders.OutputFolders") == "pipeline.launch.folders.OutputFolders"
    assert current_target("pipeline.studies.mie_los.sensor.Radar3D") == "pipeline.sensors.Radar3D"
    assert current_target("pipeline.tablesX.Y") == "pipeline.tablesX.Y"
    assert current_target("filters.imm.FSIMM") == "filters.imm.FSIMM"
    from hydra.utils import get_object
    for old, new in MOVED_MODULES.items():       # every entry names a module that exists
        assert get_object(new) is not None, (old, new)


def test_upgrade_rewrites_nested_targets_without_resolving_interpolations():
    cfg = OmegaConf.create({"report": {"tables": {"t": {"_target_": "pipeline.tables.BinnedTable", "n": "${x}"}}},
                            "x": 3, "list": [{"_target_": "pipeline.tables.SummaryTable"}]})
    changed = upgrade_targets(cfg)
    assert [c[0] for c in changed] == ["report.tables.t._target_", "list[0]._target_"]
    assert cfg.report.tables.t._target_ == "pipeline.views.tables.BinnedTable" and cfg.report.tables.t.n == 3
    assert cfg.list[0]._target_ == "pipeline.views.tables.SummaryTable"


def test_a_run_folder_from_before_the_moves_is_reported_and_recomputed(smoke_runs, tmp_path):
    from pipeline.results.recompute import recompute
    from pipeline.results.report import load_run
    _, ctx = smoke_runs("mie_los")
    old = tmp_path / "old_run"
    shutil.copytree(ctx.run_dir, old)
    text = (old / "config.yaml").read_text()
    assert "pipeline.sensors.Radar3D" in text
    (old / "config.yaml").write_text(text.replace("pipeline.sensors.Radar3D", "pipeline.studies.mie_los.sensor.Radar3D")
                                     .replace("pipeline.views.tables.", "pipeline.tables."))
    assert stored_config(old).sensors._target_ == "pipeline.sensors.Radar3D"
    load_run(old)
    metrics, summary = recompute(old)
    assert summary.height > 0
