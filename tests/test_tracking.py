"""Experiment tracking (issue 42): provenance in every run, `mtt-query runs/diff/tag/note/rm/gc`.

The provenance tests work on throw-away git checkouts; the end-to-end test edits a filter in one
(uncommitted) between two runs of study 001 and checks that `runs` shows the dirty flag, that
`diff` names the edited file and that its paired interval is the bootstrap interval of the
resampled differences, recomputed here by hand.
"""

from __future__ import annotations

import importlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from scipy import stats

from pipeline.results import diff as run_diff
from pipeline.results import gc, tracking
from pipeline.results.cli import main as query_main
from pipeline.run import provenance
from pipeline.run.process import identity
from pipeline.storage import fingerprint
from tests.helpers.runs import run_in_process

GIT = shutil.which("git")
pytestmark = pytest.mark.skipif(GIT is None, reason="git is not installed")


def git(where: Path, *args: str) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@example.org", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@example.org"}
    return subprocess.run(["git", "-C", str(where), *args], check=True, capture_output=True, text=True,
                          env=env).stdout.strip()


def new_repo(where: Path, files: dict[str, str]) -> Path:
    where.mkdir(parents=True, exist_ok=True)
    git(where, "init", "-q", "-b", "main")
    for name, text in files.items():
        (where / name).parent.mkdir(parents=True, exist_ok=True)
        (where / name).write_text(text)
    git(where, "add", "-A")
    git(where, "commit", "-q", "-m", "first")
    return where


def query(*args: str, capsys) -> tuple[int, str, str]:
    code = query_main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


# ---- provenance -------------------------------------------------------------------------------
def test_a_clean_checkout_is_recorded_with_its_commit_and_no_diff(tmp_path):
    repo = new_repo(tmp_path / "repo", {"a.py": "x = 1\n"})
    record, diff = provenance.git_state(repo)
    assert record["available"] and record["commit"] == git(repo, "rev-parse", "HEAD")
    assert record["branch"] == "main" and record["dirty"] is False and diff == b""


def test_the_dirty_diff_recreates_the_work_tree_untracked_files_included(tmp_path):
    repo = new_repo(tmp_path / "repo", {"a.py": "x = 1\ny = 2\n", "pkg/b.py": "z = 3\n"})
    (repo / "a.py").write_text("x = 1\ny = 20\n")             # an edit
    (repo / "pkg" / "new.py").write_text("w = 4\nv = 5")     # untracked, no final newline
    (repo / "pkg" / "b.py").unlink()                         # a deletion
    record, diff = provenance.git_state(repo)
    assert record["dirty"] and record["untracked_files"] == 1
    # the recorded diff applied to a clean clone of the commit gives the dirty tree back, byte for byte
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "-q", str(repo), str(clone)], check=True)
    (tmp_path / "code.diff").write_bytes(diff)
    git(clone, "apply", str(tmp_path / "code.diff"))
    for name in ("a.py", "pkg/new.py"):
        assert (clone / name).read_bytes() == (repo / name).read_bytes()
    assert not (clone / "pkg" / "b.py").exists()


def test_outside_a_git_checkout_provenance_says_so_and_the_run_goes_on(tmp_path, monkeypatch):
    record, diff = provenance.git_state(tmp_path)
    assert record["available"] is False and "not in a git checkout" in record["reason"] and diff == b""
    monkeypatch.setenv("PATH", str(tmp_path))                # no git command at all
    record, _ = provenance.git_state(tmp_path)
    assert record == {"available": False, "reason": f"{tmp_path} is not in a git checkout (no git command on PATH)"}
    monkeypatch.setattr(provenance, "ROOT", tmp_path)
    made = provenance.record(tmp_path, {"mc": {"seed": 3}}, ["mc.seed=3"], [])
    assert made["git"]["available"] is False and made["seed"] == 3 and made["code"]
    assert provenance.table_metadata(made)["mtt.git"] == "unavailable"


def test_a_user_package_outside_the_checkout_is_hashed_and_an_edit_changes_the_hash(tmp_path, monkeypatch):
    (tmp_path / "provpkg").mkdir()
    (tmp_path / "provpkg" / "__init__.py").write_text("")
    (tmp_path / "provpkg" / "cv.py").write_text("GAIN = 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.invalidate_caches()
    fingerprint._location.cache_clear()
    before = provenance.user_packages(["provpkg.cv"], inside=provenance.ROOT)
    assert set(before) == {"provpkg"} and before["provpkg"]["modules"] == 2 and before["provpkg"]["git"] is None
    (tmp_path / "provpkg" / "cv.py").write_text("GAIN = 2.0\n")
    after = provenance.user_packages(["provpkg.cv"], inside=provenance.ROOT)
    assert after["provpkg"]["sha256"] != before["provpkg"]["sha256"]
    # the project's own modules are in the checkout: never listed as user packages
    assert "pipeline" not in provenance.user_packages(["pipeline.run.runner"], inside=provenance.ROOT)
    fingerprint._location.cache_clear()        # provpkg's files are this test's: no later test may see them


# ---- a dirty edit of a filter, end to end -----------------------------------------------------
FILTER = '''"""A VSIMM whose activation threshold is scaled in code (the edit under test)."""
from filters.imm import VSIMM

SCALE = {scale}


class ScaledVSIMM(VSIMM):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.activation_threshold *= SCALE
'''

RUN = ("experiment=ao_vsimm_s1", "mc.runs=6", "scenario.steps=120", "variants=[fsimm,vsimm]",
       "plugins.packages=[scaledpkg]", "filters.vsimm._target_=scaledpkg.filters.ScaledVSIMM")


@pytest.fixture
def edited_runs(tmp_path, monkeypatch):
    """Two runs of study 001 in a checkout: the first at a commit, the second after an uncommitted
    edit of a filter's code. The checkout is a throw-away repository holding the filter package,
    standing in for the project's (provenance.ROOT)."""
    repo = new_repo(tmp_path / "checkout", {"scaledpkg/__init__.py": "", "scaledpkg/filters.py":
                                            FILTER.format(scale="1.0")})
    monkeypatch.setattr(provenance, "ROOT", repo)
    monkeypatch.syspath_prepend(str(repo))
    importlib.invalidate_caches()
    fingerprint._location.cache_clear()        # a module's file is cached by name: another test's scaledpkg
    root = tmp_path / "artifacts"
    _, ctx_a = run_in_process(root, "ao_vsimm_s1/a", *RUN)
    (repo / "scaledpkg" / "filters.py").write_text(FILTER.format(scale="0.5"))
    for name in ("scaledpkg.filters", "scaledpkg"):          # the edited module, imported afresh
        sys.modules.pop(name, None)
    _, ctx_b = run_in_process(root, "ao_vsimm_s1/b", *RUN)
    yield root, ctx_a.run_dir, ctx_b.run_dir, repo
    sys.modules.pop("scaledpkg.filters", None)
    sys.modules.pop("scaledpkg", None)
    fingerprint._location.cache_clear()


def test_runs_lists_both_runs_with_their_commit_and_dirty_flag(edited_runs, capsys):
    root, a, b, repo = edited_runs
    code, out, _ = query("runs", "--root", str(root), "--format", "json", capsys=capsys)
    assert code == 0
    rows = {r["run_id"]: r for r in json.loads(out)["rows"]}
    commit = git(repo, "rev-parse", "HEAD")[:10]
    ra, rb = rows["runs/ao_vsimm_s1/a"], rows["runs/ao_vsimm_s1/b"]
    assert ra["commit"] == rb["commit"] == commit and ra["dirty"] is False and rb["dirty"] is True
    assert ra["code"] != rb["code"]
    # the diff is stored once, in the run folder, and its hash is in every table's metadata
    status = json.loads((b / "status.json").read_text())
    assert (b / "provenance" / "code.diff").read_text().count("+SCALE = 0.5") == 1
    assert pl.read_parquet_metadata(b / "summary.parquet")["mtt.code"] == status["provenance"]["code"]
    assert set(status["stage_keys"]) == {"truth.parquet", "detections.parquet", "estimates/fsimm.parquet",
                                         "estimates/vsimm.parquet"}
    # --only-changed: the provenance fields that differ, and no config key (none differs)
    code, out, _ = query("runs", "--root", str(root), "--only-changed", "--format", "json", capsys=capsys)
    changed = json.loads(out)["rows"][0]
    assert {"dirty", "code", "diff"} <= set(changed) and "commit" not in changed and "mc.runs" not in changed


def test_diff_shows_the_code_change_and_a_paired_difference_with_its_interval(edited_runs, capsys):
    root, a, b, _ = edited_runs
    comparison = run_diff.compare(root, str(a), str(b))
    pair = comparison.pairs[0]
    assert pair.config == []
    assert [row["file"] for row in pair.code["uncommitted"]] == ["scaledpkg/filters.py"]
    assert pair.pairing.startswith("paired by run")
    # FSIMM's estimates are the same table in both (same key): identical, left out
    assert pair.left_out > 0 and set(pair.metrics["variant"]) == {"VSIMM"}
    row = pair.metrics.filter((pl.col("series") == "position_rmse") & (pl.col("window") == "all")).row(0, named=True)
    assert row["pairing"] == run_diff.PAIRED
    # by hand: the 2.5 / 97.5 % quantiles of B's minus A's statistic on the same bootstrap resamples
    ra, rb = (pl.read_parquet(d / "resamples.parquet").filter(
        (pl.col("variant_key") == "vsimm") & (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
        .sort("resample")["value"].to_numpy() for d in (a, b))
    assert row["ci_low"] == pytest.approx(np.quantile(rb - ra, 0.025), abs=1e-12)
    assert row["ci_high"] == pytest.approx(np.quantile(rb - ra, 0.975), abs=1e-12)
    summary = [pl.read_parquet(d / "summary.parquet").filter(
        (pl.col("variant_key") == "vsimm") & (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
        ["value"].item() for d in (a, b)]
    assert row["difference"] == pytest.approx(summary[1] - summary[0], abs=1e-12) and row["difference"] != 0
    code, out, _ = query("diff", "--root", str(root), str(a), str(b), "--patch", capsys=capsys)
    assert code == 0 and "scaledpkg/filters.py" in out and "+SCALE = 0.5" in out and "paired by run" in out


def test_diff_is_unpaired_and_says_why_when_the_measurements_differ(edited_runs):
    root, a, _, _ = edited_runs
    _, ctx_c = run_in_process(root, "ao_vsimm_s1/c", *RUN, "sensors.noise_std=30")
    pair = run_diff.compare(root, str(a), str(ctx_c.run_dir)).pairs[0]
    assert pair.pairing.startswith("unpaired") and "measurements differ" in pair.pairing
    assert [r["key"] for r in pair.config] == ["sensors.noise_std"]
    row = pair.metrics.filter((pl.col("variant") == "FSIMM") & (pl.col("series") == "position_rmse")
                              & (pl.col("window") == "all")).row(0, named=True)
    se = [pl.read_parquet(d / "summary.parquet").filter(
        (pl.col("variant_key") == "fsimm") & (pl.col("series") == "position_rmse") & (pl.col("window") == "all"))
        ["standard_error"].item() for d in (a, ctx_c.run_dir)]
    half = stats.norm.ppf(0.975) * np.hypot(*se)
    assert row["pairing"] == run_diff.UNPAIRED
    assert row["ci_high"] - row["difference"] == pytest.approx(half, rel=1e-9)


# ---- tags, notes, rm, filters on synthetic run folders ----------------------------------------
def fake_run(root: Path, run_id: str, *, experiment: str = "exp", status: str = "ok", started: str = "2026-12-01T10:00:00",
             keys: dict[str, str] | None = None, process: dict | None = None, seed: int = 1) -> Path:
    folder = root / run_id
    folder.mkdir(parents=True)
    (folder / "status.json").write_text(json.dumps({
        "run_id": run_id, "experiment": experiment, "status": status, "started_at": started, "runs": 4,
        "overrides": [], "stage_keys": keys or {}, "process": process,
        "provenance": {"code": f"code-{seed}", "seed": seed, "git": {"available": True, "commit": "c" * 40,
                                                                     "branch": "main", "dirty": False}}}))
    (folder / "config.yaml").write_text(f"mc:\n  runs: 4\n  seed: {seed}\npaths:\n  artifacts: {root}\n")
    return folder


def test_tags_notes_and_rm_are_kept_in_the_run_folder_and_filter_the_listing(tmp_path, capsys):
    fake_run(tmp_path, "runs/exp/one", started="2026-12-01T10:00:00", seed=1)
    fake_run(tmp_path, "runs/exp/two", started="2026-12-02T10:00:00", seed=2)
    fake_run(tmp_path, "runs/other/three", experiment="other", status="failed", started="2026-12-03T10:00:00")
    root = str(tmp_path)
    assert query("tag", "--root", root, "runs/exp/one", "baseline", "paper", capsys=capsys)[0] == 0
    assert query("tag", "--root", root, "runs/exp/one", "paper", "--remove", capsys=capsys)[0] == 0
    assert query("note", "--root", root, "runs/exp/two", "after the fix", capsys=capsys)[0] == 0
    notes = json.loads((tmp_path / "runs/exp/one/annotations.json").read_text())
    assert notes["tags"] == ["baseline"]

    def ids(*args: str) -> list[str]:
        code, out, err = query("runs", "--root", root, "--format", "json", *args, capsys=capsys)
        assert code == 0, err
        return [r["run_id"] for r in json.loads(out)["rows"]]

    assert ids() == ["runs/exp/one", "runs/exp/two", "runs/other/three"]
    assert ids("--experiment", "exp") == ["runs/exp/one", "runs/exp/two"]
    assert ids("--status", "failed") == ["runs/other/three"]
    assert ids("--tag", "baseline") == ["runs/exp/one"]
    assert ids("--since", "2026-12-02") == ["runs/exp/two", "runs/other/three"]
    assert ids("--until", "2026-12-01T23:00") == ["runs/exp/one"]
    assert query("rm", "--root", root, "runs/exp/two", capsys=capsys)[0] == 0
    assert ids() == ["runs/exp/one", "runs/other/three"]
    assert ids("--include-deleted", "--experiment", "exp") == ["runs/exp/one", "runs/exp/two"]
    code, out, _ = query("runs", "--root", root, "--experiment", "exp", "--include-deleted", "--only-changed",
                         "--format", "json", capsys=capsys)
    rows = json.loads(out)["rows"]
    assert [r["note"] for r in rows] == [None, "after the fix"] and [r["mc.seed"] for r in rows] == ["1", "2"]
    assert "experiment" not in rows[0] and "paths.artifacts" not in rows[0]      # same in both / where it wrote
    assert query("rm", "--root", root, "runs/exp/two", "--undo", capsys=capsys)[0] == 0
    assert ids("--experiment", "exp") == ["runs/exp/one", "runs/exp/two"]


@pytest.mark.parametrize("args, says", [
    (("diff", "runs/exp/one", "runs/nope"), "RUN_B 'runs/nope': no such folder"),
    (("runs", "--since", "yesterday"), "--since 'yesterday': give a date or a time as ISO 8601"),
    (("tag", "runs/exp/one", "two words"), "a tag is one word"),
    (("export-mlflow", "runs/exp/one", "--store", "http://example.org"), "give an SQLite store"),
    (("rm", "/"), "is not inside the artifacts root"),
])
def test_bad_arguments_get_one_paragraph_and_exit_2(tmp_path, capsys, args, says):
    fake_run(tmp_path, "runs/exp/one")
    code, out, err = query(args[0], "--root", str(tmp_path), *args[1:], capsys=capsys)
    assert code == 2 and says in err and "Traceback" not in err and err.count("\n") == 1


# ---- gc ---------------------------------------------------------------------------------------
def _entry(root: Path, stage: str, key: str, age_s: float) -> Path:
    path = root / "cache" / stage / f"{key}.parquet"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"x" * 100)
    stamp = time.time() - age_s
    os.utime(path, (stamp, stamp))
    return path


def test_gc_on_300_runs_lists_exactly_the_unreferenced_entries_and_the_deleted_runs(tmp_path):
    hour = 3600.0
    kept_keys, deleted_keys, unreferenced, recent = set(), set(), set(), set()
    for i in range(300):
        keys = {"truth.parquet": f"t{i % 10:014d}", "detections.parquet": f"d{i % 10:014d}",
                "estimates/a.parquet": f"a{i:014d}"}
        folder = fake_run(tmp_path, f"runs/exp/{i:03d}", keys=keys)
        if i % 30 == 0:                                   # 10 runs marked deleted
            (folder / "annotations.json").write_text(json.dumps({"deleted": True}))
            deleted_keys.add(keys["estimates/a.parquet"])
        else:
            kept_keys |= set(keys.values())
    for key in kept_keys | deleted_keys:
        _entry(tmp_path, "scenario" if key[0] == "t" else "measure" if key[0] == "d" else "track", key, 5 * hour)
    for i in range(50):
        unreferenced.add(_entry(tmp_path, "track", f"u{i:014d}", 5 * hour))
    for i in range(5):
        recent.add(_entry(tmp_path, "track", f"r{i:014d}", 60.0))          # inside the grace: kept
    # a job still running, started an hour ago: an unreferenced entry written since is its, kept
    fake_run(tmp_path, "runs/exp/live", status="running", started=time.strftime("%Y-%m-%dT%H:%M:%S",
             time.localtime(time.time() - hour)), process=identity())
    since_live = _entry(tmp_path, "track", "l00000000000000", 0.5 * hour)
    (tmp_path / "cache" / "track" / "x.parquet.20261201-000000.abc123.rejected").write_bytes(b"kept")
    started = time.perf_counter()
    planned = gc.plan(tmp_path, grace_s=600)
    took = time.perf_counter() - started
    listed_cache = {e.path for e in planned.entries if e.kind == "cache"}
    expected = unreferenced | {tmp_path / "cache" / "track" / f"{k}.parquet" for k in deleted_keys}
    assert listed_cache == expected
    assert {e.path.name for e in planned.entries if e.kind == "run"} == {f"{i:03d}" for i in range(0, 300, 30)}
    assert planned.live_jobs == 1 and planned.bytes == 100 * len(expected) + sum(
        e.bytes for e in planned.entries if e.kind == "run")
    # a dry run removed nothing; --apply removes exactly what was listed
    assert all(p.exists() for p in expected)
    gc.apply(planned)
    assert not any(p.exists() for p in expected) and all(e.removed for e in planned.entries)
    assert all(p.exists() for p in recent) and since_live.exists()
    assert all((tmp_path / "cache" / s).glob("*.parquet") for s in ("scenario", "measure"))
    assert len(list((tmp_path / "cache" / "track").glob("a*.parquet"))) == 290
    assert (tmp_path / "cache" / "track" / "x.parquet.20261201-000000.abc123.rejected").exists()
    print(f"gc plan over 300 runs and {len(kept_keys) + len(expected) + 6} cache entries: {took:.3f} s")


def test_gc_keeps_an_entry_that_a_store_renamed_onto_the_name_after_the_listing(tmp_path):
    path = _entry(tmp_path, "track", "k00000000000000", 3600.0)
    planned = gc.plan(tmp_path, grace_s=0)
    assert [e.path for e in planned.entries] == [path]
    replacement = path.with_name(".new.tmp")
    replacement.write_bytes(b"y" * 100)
    os.replace(replacement, path)                       # a job stored the same key meanwhile
    gc.apply(planned)
    assert path.read_bytes() == b"y" * 100 and planned.entries[0].removed is False


@pytest.mark.full
def test_gc_while_a_job_runs_loses_nothing(tmp_path):
    """A job writes its stages while gc --apply runs in a loop: the job ends ok, every table it
    published reads with its checksum, and every cache entry it refers to is there."""
    from tests.helpers.processes import start_pipeline
    old = _entry(tmp_path, "track", "o00000000000000", 7200.0)     # unreferenced and old: gc's work
    job = start_pipeline("mc.runs=40", "record.enabled=false", artifacts=tmp_path, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT)
    passes = 0
    while job.poll() is None:
        gc.apply(gc.plan(tmp_path, grace_s=0))
        passes += 1
    out = job.stdout.read().decode()
    assert job.returncode == 0, out[-2000:]
    assert passes > 1 and not old.exists()
    (run,) = [r for r in tracking.load_runs(tmp_path)]
    assert run.status["status"] == "ok"
    for output, key in run.stage_keys().items():
        assert list((tmp_path / "cache").glob(f"*/{key}.parquet")), output
    from pipeline.storage.store import read_table
    for table in ["summary.parquet", "truth.parquet", *[f"estimates/{p.name}" for p in (run.path / "estimates").iterdir()]]:
        read_table(run.path / table)
    # and a later gc still keeps what the finished run refers to
    assert gc.plan(tmp_path, grace_s=0).entries == []


def test_two_sweeps_are_diffed_job_by_job_paired_by_their_swept_values(edited_runs, capsys):
    root, a, b, _ = edited_runs
    for sweep, source, swept in (("A", a, ("x=1", "x=2")), ("B", b, ("x=2", "x=1", "x=3"))):
        for job, value in enumerate(swept):
            folder = root / "multirun" / sweep / str(job)
            shutil.copytree(source, folder)
            status = json.loads((folder / "status.json").read_text())
            status["overrides"] = ["mc.runs=6", value]          # mc.runs: the same in every job, not swept
            (folder / "status.json").write_text(json.dumps(status))
    comparison = run_diff.compare(root, "multirun/A", "multirun/B")
    assert [p.job for p in comparison.pairs] == ["x=1", "x=2"]
    assert [(p.a.run_id, p.b.run_id) for p in comparison.pairs] == [("multirun/A/0", "multirun/B/1"),
                                                                    ("multirun/A/1", "multirun/B/0")]
    assert comparison.unmatched == {"a": [], "b": ["x=3"]}
    assert all(p.pairing.startswith("paired by run") and p.metrics.height for p in comparison.pairs)
    code, out, _ = query("diff", "--root", str(root), "multirun/A", "multirun/B", "--format", "csv", capsys=capsys)
    table = pl.read_csv(out.encode())
    assert code == 0 and set(table["job"]) == {"x=1", "x=2"} and run_diff.PAIRED in set(table["pairing"])
    assert all(kind.startswith(run_diff.PAIRED) for kind in table["pairing"])
