"""The cached stages of an experiment, declared: scenario -> measure -> track (one per variant).

A ``Stage`` names its output, the outputs of earlier stages it reads (``inputs``), the resolved
config subtree that parameterizes it and the modules that make it (both in its cache key, with its
inputs' keys: pipeline.storage.keys.stage_key), how it is computed from its inputs, and its table codec.
The runner (pipeline.run.runner) runs the list in order through the stage cache; evaluate and record
then read the outputs. Kedro's nodes in spirit: inputs are named outputs or declared values, never
a shared context.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

import polars as pl

from filters.base import TrackEstimate, layout_problems
from pipeline.errors import EstimateLayoutError
from pipeline.studies.single_target import SingleTargetStudy, filter_chunks, truth_runs, with_fault_flags

Codec = Callable[[Any, Mapping[str, Any]], tuple[pl.DataFrame, dict]]     # (value, the inputs) -> table
Decoder = Callable[[pl.DataFrame, dict[str, str]], Any]


@dataclass(frozen=True)
class Stage:
    cache: str                               # the cache folder: scenario | measure | track
    output: str                              # its name among the outputs: truth, detections, estimates/<variant>
    table: str                               # the table name its file's metadata carries
    inputs: tuple[str, ...]                  # outputs of earlier stages, passed to compute by name
    config: Mapping[str, Any]                # the resolved config that parameterizes it (in the key)
    producers: tuple[str, ...]               # modules whose import closure is in the key (beyond config _target_s)
    compute: Callable[..., Any]              # compute(**inputs) -> value
    to_frame: Codec                          # the table (a track table's fault column needs the truth)
    from_frame: Decoder
    describe: Callable[[Mapping[str, Any]], str]   # the log line's subject, from the inputs
    # optional: the table in chunks of runs, chunks(**inputs) -> iterator of (frame, metadata), streamed
    # to the file one at a time (mc.chunk_runs); the value is then decoded from the written table
    chunks: Callable[..., Iterator[tuple[pl.DataFrame, dict]]] | None = None

    @property
    def publish_as(self) -> Path:
        return Path(f"{self.output}.parquet")


def _data_fingerprint(scenario: Any) -> dict[str, str]:
    """``{"data": ...}`` for a scenario with ``data_fingerprint()`` (a hash of the files it reads), else {}."""
    fingerprint = getattr(scenario, "data_fingerprint", None)
    return {"data": str(fingerprint())} if callable(fingerprint) else {}


def declare(cfg: Any, resolved: Mapping[str, Any], prepared: Any, fault_checks: Any
            ) -> tuple[list[Stage], Callable[[Any, Any], Any]]:
    """The experiment's stages, in order, and the filters' view ``track_input(truth, detections)``
    (Study.track_input, made once per detections and shared by every variant and the recording);
    ``prepared``: pipeline.run.runner.Prepared; ``fault_checks``: pipeline.evaluation.faults.FaultChecks."""
    runs, seed = int(cfg.mc.runs), int(cfg.mc.seed)
    study, scenario, sensor = prepared.study, prepared.scenario, prepared.sensor
    chunk_runs = cfg.mc.get("chunk_runs")
    # the adapter's node is part of what the filters see (the default adapter has none)
    study_node = {"study": resolved["study"]} if cfg.get("study") is not None else {}
    made: list[tuple[Any, Any]] = []             # (detections, the filters' view of them)

    def track_input(truth, detections):          # one filters' view for all variants and the recording
        if not made or made[0][0] is not detections:
            made[:] = [(detections, study.track_input(truth, detections, sensor, seed))]
        return made[0][1]

    # the study's codecs of the truth and detections tables (pipeline.contract.Study; default schemas') are in
    # those stages' keys through the study's module
    codecs = ("pipeline.run.stages", "pipeline.storage.schemas", "pipeline.run.seeding", type(study).__module__)
    stages = [
        # a scenario read from a data file (a recorded flight) names its bytes: an edited file recomputes
        Stage("scenario", "truth", "truth", (), {"scenario": resolved["scenario"], "runs": runs, "seed": seed,
                                                  **_data_fingerprint(scenario)},
              codecs, lambda: scenario.generate(runs, seed),
              lambda truth, _: study.truth_to_frame(truth), study.truth_from_frame, lambda _: f"{runs} runs"),
        Stage("measure", "detections", "detections", ("truth",), {"sensors": resolved["sensors"], "seed": seed},
              codecs, lambda truth: sensor.measure(truth, seed),
              lambda detections, _: study.detections_to_frame(detections), study.detections_from_frame,
              lambda i: f"{runs} runs x {i['truth'].time.size} scans"),
    ]
    streamed = bool(chunk_runs) and chunk_runs < runs

    def track_chunks(truth, detections, estimator):
        """Each chunk of runs filtered, flagged and framed with its global run numbers."""
        view = track_input(truth, detections)
        for first, part in filter_chunks(estimator, view, chunk_runs):
            checked_layout(key_of[id(estimator)], estimator, part, truth, first)
            df, meta = with_fault_flags(study, part, truth_runs(truth, first, first + chunk_runs), fault_checks)
            yield df.with_columns(pl.col("run") + first), meta

    key_of = {id(prepared.estimators[v]): v for v in prepared.variants}

    def checked_layout(key: str, estimator: Any, estimate: Any, truth: Any, first: int) -> Any:
        """``estimate`` (of runs first.. of a single-target study) when its arrays have the truth's
        layout (filters.base.SingleTargetFilter); else an EstimateLayoutError naming the variant, the
        class and the shapes expected, before a raw numpy broadcast error in a metric."""
        if not isinstance(study, SingleTargetStudy) or not isinstance(estimate, TrackEstimate):
            return estimate
        runs_here = min(runs - first, chunk_runs or runs)
        names = tuple(truth.state_names)
        problems = layout_problems(estimate, runs_here, truth.time.size, names)
        if problems:
            raise EstimateLayoutError(
                f"filters.{key} ({type(estimator).__module__}.{type(estimator).__qualname__}): "
                + "; ".join(problems) + f". An estimate holds one value per run, scan and state component, "
                f"the components in the order of MeasurementSeries.state_names {list(names)} (NaN for one "
                f"the filter does not estimate): the layout contract of filters.base.SingleTargetFilter "
                f"(docs/your-own-filter.md).")
        return estimate

    for v in prepared.variants:
        estimator = prepared.estimators[v]
        name = getattr(estimator, "name", v)
        stages.append(Stage(
            "track", f"estimates/{v}", study.estimate_table, ("truth", "detections"),
            # the fault checks decide the table's fault column, so they are part of its key
            {"filter": resolved["filters"][v], **study_node, "faults": resolved.get("faults")},
            ("pipeline.run.stages", "pipeline.storage.schemas", "pipeline.studies.single_target"),
            lambda truth, detections, e=estimator, v=v: checked_layout(
                v, e, e.run(track_input(truth, detections)), truth, 0),                        # chunked: track_chunks
            lambda estimate, inputs: with_fault_flags(study, estimate, inputs["truth"], fault_checks),
            study.estimate_from_frame,
            lambda i, n=name: f"{n}: {runs} runs x {i['truth'].time.size} scans",
            (lambda truth, detections, e=estimator: track_chunks(truth, detections, e)) if streamed else None))
    return stages, track_input
