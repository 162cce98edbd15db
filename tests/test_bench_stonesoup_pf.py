"""benchmarks/bench_stonesoup_pf.py still runs, and its checks hold on a small job: Stone Soup's
particle filter and ours weigh a cloud alike and agree on the position RMSE within Monte Carlo noise."""

from __future__ import annotations

import pytest

from tests.helpers.extras import require_extra

require_extra("stonesoup", "stonesoup")

from benchmarks import bench_stonesoup_pf  # noqa: E402

# full tier (tests/helpers/tiers.py): a benchmark run
pytestmark = pytest.mark.full


def test_the_benchmark_runs_and_its_checks_pass(capsys, tmp_path):
    # its results file goes to tmp_path: benchmarks/results/ holds the committed record
    assert bench_stonesoup_pf.main(["--particles", "300", "--repeats", "1", "--runs", "8",
                                    "--results-dir", str(tmp_path)]) == 0
    assert (tmp_path / "stonesoup_pf.md").is_file()
    out = capsys.readouterr().out
    assert "Stone Soup / ours, numba" in out and "OK" in out
