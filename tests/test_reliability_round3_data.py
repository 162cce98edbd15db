"""Issue 37 (reliability, round 3), items 1-4, 17, 19 and 20: data a failure must not lose, and
refusals that must be one paragraph, each with the case that went wrong."""

from __future__ import annotations

import json
import os
from pathlib import Path

import polars as pl
import pytest

from tests.test_pipeline import cli


# ---- item 1: a refused run removes only what it created ---------------------------------------------

def test_a_refused_run_into_an_existing_folder_keeps_every_file_of_it(tmp_path):
    """Item 1: ``hydra.run.dir=<an existing folder> mc.runs=0`` removed the folder (rmtree), the
    user's files with it (a folder holding only ``*.log`` files passed for Hydra's own)."""
    mine = tmp_path / "mine"
    (mine / "sub").mkdir(parents=True)
    (mine / "important.log").write_text("the user's log\n")
    (mine / "sub" / "data.csv").write_text("1,2\n")
    logs = tmp_path / "logs_only"
    logs.mkdir()
    (logs / "server.log").write_text("kept\n")
    empty = tmp_path / "empty_but_mine"
    empty.mkdir()
    for folder in (mine, logs, empty):
        proc = cli(tmp_path, f"hydra.run.dir={folder}", "mc.runs=0")
        assert proc.returncode == 2 and "error: mc.runs: 0 is not allowed" in proc.stderr
        assert folder.is_dir()
    assert (mine / "important.log").read_text() == "the user's log\n"
    assert (mine / "sub" / "data.csv").read_text() == "1,2\n"
    # what the refused job made (Hydra's .hydra/ and its log) is gone again; the user's files stay
    assert sorted(p.relative_to(mine).as_posix() for p in mine.rglob("*")) == ["important.log", "sub", "sub/data.csv"]
    assert [p.name for p in logs.iterdir()] == ["server.log"] and (logs / "server.log").read_text() == "kept\n"
    assert list(empty.iterdir()) == []


def test_a_refused_run_into_a_finished_runs_folder_leaves_its_results(tmp_path):
    """Item 1: a refused rerun into a finished run's folder wrote its failure over that run's
    status.json and summary.parquet (the folder held a status.json, taken as 'this job started')."""
    run = tmp_path / "done"
    assert cli(tmp_path, f"hydra.run.dir={run}", "mc.runs=2", "scenario.steps=20",
               "record.enabled=false").returncode == 0
    before = {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()
              and ".hydra" not in p.parts and not p.name.endswith(".log")}
    proc = cli(tmp_path, f"hydra.run.dir={run}", "mc.runs=0")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    after = {p.relative_to(run).as_posix(): p.read_bytes() for p in run.rglob("*") if p.is_file()
             and ".hydra" not in p.parts and not p.name.endswith(".log")}
    assert after == before
    assert json.loads((run / "status.json").read_text())["status"] == "ok"
