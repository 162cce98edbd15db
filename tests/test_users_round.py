"""Issue 38 (what a new user hits): each test failed on the code before its fix.

(d) numbers keyed by value; (e) Hydra's refusals with close names; (a) the compute column's
timing; (b) the kernels' compile message and the warm-up command; (c) your own filter; (f) re-running
a stored run into the artifacts tree."""

from __future__ import annotations

from tests.conftest import composed


# ---- (d) sensors.noise_std=20 and =20.0 are one cache key ---------------------------------------------

def _stage_keys(*overrides: str) -> dict[str, str]:
    """Every declared stage's cache key, as the runner computes it, for the default experiment."""
    from omegaconf import OmegaConf
    from pipeline.run.runner import build_fault_checks, prepare
    from pipeline.run.stages import declare
    from pipeline.storage.keys import stage_key

    cfg = composed("ao_vsimm_s1", "mc.runs=2", *overrides)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    stages, _ = declare(cfg, resolved, prepare(cfg), build_fault_checks(cfg))
    keys: dict[str, str] = {}
    for stage in stages:
        keys[stage.output] = stage_key(stage.cache, stage.config, tuple(keys[i] for i in stage.inputs),
                                       stage.producers)
    return keys


def test_an_integral_number_typed_as_int_or_float_gives_one_cache_key():
    """Before: noise_std=20 and 20.0 hashed their JSON text ('20' vs '20.0'): two keys, a recompute."""
    as_int, as_float = _stage_keys("sensors.noise_std=20"), _stage_keys("sensors.noise_std=20.0")
    assert as_int == as_float
    assert _stage_keys("sensors.noise_std=20.5")["detections"] != as_int["detections"]   # a value still counts
