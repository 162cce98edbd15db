"""Issue 19: a printed percentage names the variant it is relative to ("compute % of SIR-MM"), the
compute reference is chosen per study (``metrics.compute_reference``, by default the comparisons'
``metrics.reference_variant``), and a study without a sensible one prints compute seconds only."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from omegaconf import open_dict

from pipeline.run.config import compute_reference
from pipeline.errors import ConfigError
from pipeline.evaluation.evaluate import Window, summary_rows
from pipeline.run.runner import prepare
from pipeline.views.tables import format_summary
from tests.helpers.config import composed

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))


def _compose(experiment: str):
    cfg = composed(experiment)
    cfg.paths.artifacts = "/nonexistent-artifacts"
    return cfg


def _rows(**kwargs) -> pl.DataFrame:
    variants = {key: (display, {"models_evaluated": np.full(5, models)})
                for key, display, models in (("ekf", "EKF", 1.0), ("ammpf", "AMMPF", 4.0), ("sir_mm", "SIR-MM", 2.0))}
    compute_seconds = {"ekf": 0.01, "ammpf": 5.0, "sir_mm": 2.5}
    rows = summary_rows(variants, compute_seconds, [Window("all", 0, 4)], "ekf", 3, **kwargs)
    return pl.DataFrame([{k: v for k, v in r.items() if k != "statistic"} for r in rows])


def test_the_compute_reference_is_its_own_and_its_unit_names_it():
    df = _rows(compute_reference="sir_mm")
    pct = df.filter(pl.col("series") == "compute_pct_of_reference")
    assert dict(zip(pct["variant_key"], pct["value"])) == {"ekf": pytest.approx(0.4), "ammpf": 200.0, "sir_mm": 100.0}
    assert set(pct["unit"]) == {"% of SIR-MM"}
    models = df.filter(pl.col("series") == "models_pct_of_reference")          # still of the comparisons' reference
    assert dict(zip(models["variant_key"], models["value"])) == {"ekf": 100.0, "ammpf": 400.0, "sir_mm": 200.0}
    assert set(models["unit"]) == {"% of EKF"}
    # by default the comparisons' reference; None: seconds only
    assert set(_rows().filter(pl.col("series") == "compute_pct_of_reference")["unit"]) == {"% of EKF"}
    none = _rows(compute_reference=None)
    assert none.filter(pl.col("series") == "compute_pct_of_reference").height == 0
    assert none.filter(pl.col("series") == "compute_seconds").height == 3


def test_the_printed_header_names_the_reference_or_prints_seconds_only():
    text = format_summary(_rows(compute_reference="sir_mm"), "sonobuoy_case2", 3)
    header = next(line for line in text.splitlines() if line.startswith("variant"))
    assert [c.strip() for c in header.split("  ") if c.strip()] == [
        "variant", "models/step", "models % of EKF", "compute s", "compute % of SIR-MM"]
    assert "200.0" in text and "53719" not in text
    text = format_summary(_rows(compute_reference=None), "sonobuoy_case1b", 3)
    header = next(line for line in text.splitlines() if line.startswith("variant"))
    assert "compute s" in header and "compute %" not in header
    # a summary without units (an older table, a test's frame) keeps the bare label
    bare = format_summary(_rows(compute_reference="sir_mm").drop("unit"), "x", 3)
    assert "compute %" in bare and "compute % of" not in bare


def test_each_study_has_a_compute_reference_that_makes_sense():
    """Study 004's EKF is hundreds of times cheaper than the particle filters: the percentages are of a
    particle filter with the same particles (SIR-MM; the unregularised AMMPF in case 1), or none."""
    expected = {"sonobuoy_case1": "ammpf_nolw", "sonobuoy_case1b": None, "sonobuoy_case2": "sir_mm",
                "sonobuoy_case2b": "sir_mm", "mie_los": "a", "ao_vsimm_s1": "fsimm", "async_bias": "local",
                "sonar_case1": "only_mgekf", "adsb_jet": "kf_cv"}
    for experiment in EXPERIMENTS:
        cfg = _compose(experiment)
        ref = compute_reference(cfg)
        assert ref is None or ref in cfg.filters, (experiment, ref)
        if experiment in expected:
            assert ref == expected[experiment], experiment
        if experiment.startswith("sonobuoy"):
            assert cfg.metrics.reference_variant == "ekf"            # the comparisons stay with the EKF


def test_a_compute_reference_that_is_no_variant_is_refused():
    cfg = _compose("sonobuoy_case2")
    with open_dict(cfg):
        cfg.metrics.compute_reference = "sirmm"
    with pytest.raises(ConfigError, match="metrics.compute_reference: 'sirmm'.*sir_mm.*or null"):
        prepare(cfg)
    with open_dict(cfg):                       # absent: the comparisons' reference
        del cfg.metrics["compute_reference"]
    assert compute_reference(cfg) == "ekf"


def test_a_study_004_run_prints_compute_as_percent_of_sir_mm(tmp_path):
    from tests.helpers.runs import run_in_process
    out, _ = run_in_process(tmp_path, "case2", "experiment=sonobuoy_case2", "mc.runs=2", "scenario.duration=100",
                            "target_model.particles=100")
    assert "compute % of SIR-MM" in out.table and "compute % of EKF" not in out.table
    pct = out.summary.filter(pl.col("series") == "compute_pct_of_reference")
    assert dict(zip(pct["variant_key"], pct["value"]))["sir_mm"] == pytest.approx(100.0)
    assert set(pct["unit"]) == {"% of SIR-MM"}
