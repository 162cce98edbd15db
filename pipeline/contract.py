"""What a study promises the runner: one abstract base, every hook listed here, none probed.

A study is the glue between a scenario, a sensor and the filters of one experiment family. The
runner (pipeline.run.runner) calls exactly these hooks, in this order:

1. ``check(scenario, sensor, estimators)``: cross-node consistency, before any stage; raise
   ``pipeline.errors.ConfigError`` naming the key.
   The scenario and measure stages' tables come from ``truth_to_frame`` / ``detections_to_frame`` (and back
   from ``truth_from_frame`` / ``detections_from_frame``); the defaults are pipeline.storage.schemas'.
2. ``track_input(truth, detections, sensor, seed)``: the filters' view of the detections (a
   ``filters.base.MeasurementSeries``, or the study's own report type). Randomness here (a drawn
   track start) comes from ``pipeline.run.seeding.run_generators(seed, <stage>, R)``.
3. per variant, ``estimate_to_frame(estimate, truth)`` and ``fault_flags(estimate, truth, checks)``:
   the track stage's table (named ``estimate_table``) and its ``fault`` column;
   ``estimate_from_frame(df, metadata)`` reads it back (a cached stage, and later stages, see
   exactly what the table holds).
4. per variant as soon as its track stage ends, ``per_step_metrics(truth, estimate, sensor)`` and
   ``variant_summary(VariantInputs)`` (its own summary rows beyond the per-window means); the estimate is then
   let go (a job holds one at a time: pipeline.storage.estimates). Once every variant is in,
   ``extra_summary(JobInputs)`` for rows across variants. A Monte Carlo metric is returned per run
   (``pipeline.evaluation.uncertainty.RunValues``): its value over the runs per step, the summary's interval
   across runs, the paired comparisons and the per-run table all come from it; a plain (K,) array
   is a fixed value (a bound, a chi-square band) without an interval. Every metric name is in the
   registry (``pipeline.evaluation.metrics``: unit, aggregation, label, printed digits, dof); a study
   registers its own names when its module is imported.
5. ``record(path, inputs)``: the Rerun recording of the runs in ``inputs.record_runs``.

A study is a config node (``study: {_target_: ...}``); an experiment without one gets
``pipeline.studies.single_target.SingleTargetStudy``. Scenarios and sensors are plain config nodes with
``generate(runs, seed) -> Truth`` and ``measure(truth, seed) -> Detections``; a sensor declares the
measurement kind it ``produces`` and a filter the kinds it ``accepts`` (filters.base.MEASUREMENT_KINDS).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, Protocol, Sequence

import numpy as np

if TYPE_CHECKING:
    import polars as pl

    from pipeline.data import Detections, Truth
    from pipeline.evaluation.faults import FaultChecks


class Scenario(Protocol):
    """A truth generator: every Monte Carlo run at once, run r's randomness from (seed, "scenario", r).

    A scenario that reads data files (a recorded flight) also offers ``data_fingerprint() -> str``, a
    hash of those files, which joins the scenario stage's cache key (pipeline.run.stages): the config
    names a file, the fingerprint says which bytes it held. It may offer ``describe() -> str`` too: one
    line on what it is (the flight file that ran), which heads report.txt and the report (status.json
    ``scenario``)."""

    def generate(self, runs: int, seed: int) -> "Truth": ...


class Sensor(Protocol):
    """Measurement synthesis; ``produces`` names its measurement kind (filters.base.MEASUREMENT_KINDS)."""

    produces: ClassVar[str]

    def measure(self, truth: "Truth", seed: int) -> "Detections": ...


@dataclass(frozen=True)
class RecordingInputs:
    """Everything a study's recording may draw: the stages' outputs, the built nodes, the config."""

    experiment: str
    truth: "Truth"
    detections: "Detections"
    estimates: Mapping[str, Any]              # variant key -> estimate, in display order: the recorded
    #                                           runs' rows only (pipeline.storage.estimates.RecordedRuns; index by run)
    display_names: Mapping[str, str]
    metrics: "pl.DataFrame"
    record_runs: Sequence[int]
    sensor: Any
    estimators: Mapping[str, Any]             # variant key -> the built filter
    track_input: Any                          # what the filters were given
    seed: int
    config_text: str = ""
    description: str = ""
    options: Mapping[str, Any] = field(default_factory=dict)

    def common(self) -> dict[str, Any]:
        """The keyword arguments every recording writer takes."""
        return {"experiment": self.experiment, "truth": self.truth, "detections": self.detections,
                "estimates": self.estimates, "display_names": self.display_names, "metrics": self.metrics,
                "record_runs": self.record_runs, "config_text": self.config_text, "description": self.description}


@dataclass(frozen=True)
class VariantInputs:
    """What ``Study.variant_summary`` gets: one variant's estimate, while it is in memory."""

    truth: "Truth"
    key: str                                  # the variant's config key (filters.<key>)
    display: str                              # its display name
    estimate: Any
    runs: int
    sensor: Any
    metrics: Mapping[str, Any]                # its per_step_metrics


@dataclass(frozen=True)
class JobInputs:
    """What ``Study.extra_summary`` gets: every variant, after each one's ``variant_summary``."""

    truth: "Truth"
    estimates: Mapping[str, Any]              # variant key -> estimate, read again from its table when asked
    #                                           (pipeline.storage.estimates.StoredEstimates: keeps the last one read)
    display: Mapping[str, str]                # variant key -> display name, in display order
    runs: int
    reference: str | None                     # the reference variant's key (metrics.reference_variant), if it ran
    sensor: Any
    per_variant: Mapping[str, tuple[str, dict[str, np.ndarray]]]   # key -> (display, per-step values over the runs)


class Study(ABC):
    """The hooks of a study (see the module docstring for when each is called).

    ``estimate_table`` names the track stage's table (in its metadata and the cache's checks).
    """

    estimate_table: ClassVar[str] = "estimates"

    def check(self, scenario: Any, sensor: Any, estimators: Mapping[str, Any]) -> None:
        """Cross-node consistency the nodes cannot check alone (default: nothing to check)."""

    @abstractmethod
    def track_input(self, truth: "Truth", detections: "Detections", sensor: Any, seed: int) -> Any:
        """What every variant's ``run`` is given; the same object for all variants."""

    @abstractmethod
    def estimate_to_frame(self, estimate: Any, truth: "Truth") -> tuple["pl.DataFrame", dict[str, str]]:
        """The track stage's table (one row per run x step x object) and its metadata."""

    def truth_to_frame(self, truth: "Truth") -> tuple["pl.DataFrame", dict[str, str]]:
        """The scenario stage's table (default: pipeline.storage.schemas' full run x step x target grid). A study
        whose targets come and go stores only the rows of the targets that exist."""
        from pipeline.storage.schemas import truth_to_frame
        return truth_to_frame(truth)

    def truth_from_frame(self, df: "pl.DataFrame", metadata: Mapping[str, str]) -> "Truth":
        """The truth back from its table (default: pipeline.storage.schemas')."""
        from pipeline.storage.schemas import truth_from_frame
        return truth_from_frame(df, metadata)

    def detections_to_frame(self, detections: "Detections") -> tuple["pl.DataFrame", dict[str, str]]:
        """The measure stage's table (default: pipeline.storage.schemas' full run x step x slot grid). A study with
        a variable number of detections per scan stores only the filled slots."""
        from pipeline.storage.schemas import detections_to_frame
        return detections_to_frame(detections)

    def detections_from_frame(self, df: "pl.DataFrame", metadata: Mapping[str, str]) -> "Detections":
        """The detections back from their table (default: pipeline.storage.schemas')."""
        from pipeline.storage.schemas import detections_from_frame
        return detections_from_frame(df, metadata)

    def estimate_from_frame(self, df: "pl.DataFrame", metadata: Mapping[str, str]) -> Any:
        """The estimate back from its table (default: pipeline.storage.schemas' TrackEstimate codec)."""
        from pipeline.storage.schemas import estimate_from_frame

        return estimate_from_frame(df, metadata)

    def fault_flags(self, estimate: Any, truth: "Truth", checks: "FaultChecks") -> np.ndarray:
        """(R, K) uint8 bit masks of pipeline.evaluation.faults per run and step. Default: the estimate's state and
        covariance alone (no comparison with the truth, so no NEES test)."""
        from pipeline.evaluation.faults import fault_flags

        if not (hasattr(estimate, "state") and hasattr(estimate, "covariance")):
            raise TypeError(f"{type(self).__name__} returns {type(estimate).__name__} estimates without state and "
                            f"covariance: override Study.fault_flags")
        extras = getattr(estimate, "extras", {}) or {}
        return fault_flags(estimate.state, estimate.covariance, checks, None, extras.get("weights_underflow"))

    @abstractmethod
    def per_step_metrics(self, truth: "Truth", estimate: Any, sensor: Any) -> dict[str, Any]:
        """metric name -> ``RunValues`` (R, K): each run's contribution per step and how runs combine
        (rms, mean, sum, median), or a fixed (K,) array over the truth's steps."""

    def variant_summary(self, inputs: VariantInputs) -> list[dict]:
        """One variant's summary rows beyond the per-window means (``pipeline.evaluation.evaluate.summary_row``;
        with a ``statistic``, a ``pipeline.evaluation.uncertainty.WindowStatistic``, the row gets its interval and
        paired comparison), computed while its ``inputs.estimate`` is in memory; ``inputs.metrics``: its
        ``per_step_metrics``. Default none."""
        return []

    def extra_summary(self, inputs: JobInputs) -> list[dict]:
        """Summary rows across variants (e.g. a ratio to the ``inputs.reference`` variant), rows as in
        ``variant_summary``, after every variant's; ``inputs.per_variant`` holds each variant's per-step
        values. ``inputs.estimates`` reads each variant's table again when asked and keeps only the last
        one read (``pipeline.storage.estimates.StoredEstimates``): go through them once, or keep what these
        rows need from ``variant_summary`` instead of reading them again. Default none."""
        return []

    @abstractmethod
    def record(self, path: Path, inputs: RecordingInputs) -> None:
        """Write the ``.rrd`` recording at ``path``."""
