"""pipeline.contract: the hooks a study fills in (issue 39: one inputs object, not 7 positional arguments)."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil

import pipeline.studies
from pipeline.contract import JobInputs, Study, VariantInputs


def _project_studies() -> list[type[Study]]:
    for info in pkgutil.walk_packages(pipeline.studies.__path__, "pipeline.studies."):
        importlib.import_module(info.name)

    def below(cls):
        for sub in cls.__subclasses__():
            yield sub
            yield from below(sub)
    return sorted({c for c in below(Study) if c.__module__.startswith("pipeline.")}, key=lambda c: c.__qualname__)


def test_every_study_takes_its_summary_inputs_as_one_object():
    studies = _project_studies()
    assert len(studies) >= 6                      # single target, ADS-B, bias, sonar, sonobuoy, multi-target
    for cls in studies:
        for hook in ("variant_summary", "extra_summary"):
            assert list(inspect.signature(getattr(cls, hook)).parameters) == ["self", "inputs"], (cls, hook)


def test_the_inputs_objects_name_every_field_a_study_reads():
    assert [f.name for f in dataclasses.fields(VariantInputs)] == [
        "truth", "key", "display", "estimate", "runs", "sensor", "metrics"]
    assert [f.name for f in dataclasses.fields(JobInputs)] == [
        "truth", "estimates", "display", "runs", "reference", "sensor", "per_variant"]
    inputs = VariantInputs(None, "kf", "KF", None, 3, None, {})
    assert Study.variant_summary(None, inputs) == [] and inputs.runs == 3
