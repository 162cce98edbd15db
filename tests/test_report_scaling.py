"""Issue 19: study 000's detection figure drew a 5-run count against the paper's 100-run circles. Its
query (conf/report/mie_los.yaml) scales our count to the paper's run count with the run's n_runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pipeline.results.report import ReportSpec

ROOT = Path(__file__).resolve().parents[1]


def _figure(experiment: str, name: str):
    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base=None):
        cfg = compose("config", overrides=[f"experiment={experiment}", "paths.artifacts=/nonexistent-artifacts"])
    resolved = OmegaConf.to_container(cfg, resolve=True)          # as the run's config.yaml holds it
    spec = ReportSpec.from_config(resolved["report"])
    return resolved, next(f for f in spec.figures if f.name == name)


def _metrics(n_runs: int) -> pl.DataFrame:
    rows = []
    for key, display in (("a", "A"), ("b", "B"), ("c", "C")):
        for step in range(101):
            rows.append({"variant": display, "variant_key": key, "series": "detections", "step": step,
                         "time": float(step), "value": float(n_runs if step == 43 else step % 2), "n_runs": n_runs})
    return pl.DataFrame(rows, schema_overrides={"n_runs": pl.Int32})


def test_the_detection_figure_is_per_paper_runs_whatever_our_run_count():
    cfg, figure = _figure("mie_los", "detections")
    paper = cfg["paper_runs"]
    assert paper == 100 and f"per {paper} runs" in figure.title and f"per {paper} runs" in figure.ylabel
    for n_runs in (5, 20, 100):
        df = pl.SQLContext(frames={"metrics": _metrics(n_runs)}).execute(figure.query, eager=True)
        assert set(df[figure.series]) == {f"A (ours: {n_runs} runs x 100/{n_runs})",
                                          f"B (ours: {n_runs} runs x 100/{n_runs})"}
        a = df.filter(pl.col(figure.series).str.starts_with("A")).sort("time")
        assert a["time"].to_list() == [float(t) for t in range(30, 81)]
        # every run detecting at t = 43 reads 100 detections per 100 runs, as the paper's scale
        assert a.filter(pl.col("time") == 43.0)[figure.y].item() == 100.0
        odd = a.filter(pl.col("time") == 45.0)[figure.y].item()
        assert np.isclose(odd, 100.0 / n_runs)
    # the paper's circles are its Table 1 as printed (100 runs)
    labels = [r["label"] for r in figure.reference]
    assert labels == ["paper A", "paper B"] and figure.reference[0]["y"][2] == 73
