"""Issue 38 (what a new user hits): each test failed on the code before its fix.

(d) numbers keyed by value; (e) Hydra's refusals with close names; (a) the compute column's
timing; (b) the kernels' compile message and the warm-up command; (c) your own filter; (f) re-running
a stored run into the artifacts tree."""

from __future__ import annotations

import pytest

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


# ---- (e) a typo in a key or an option gets the close names, one paragraph -------------------------------

def _cli(tmp_path, *args: str):
    import os
    import subprocess
    import sys
    from pathlib import Path
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    return subprocess.run([sys.executable, "-m", "pipeline", f"paths.artifacts={tmp_path}", *args], cwd=tmp_path,
                          capture_output=True, text=True, timeout=120, env=env)


@pytest.mark.parametrize("args, says", [
    (("sensors.noise_stdd=20",), "error: sensors.noise_stdd=20: 'sensors' has no key 'noise_stdd'. Did you mean "
                                 "'noise_std'?"),
    (("experiment=mie_loss",), "error: experiment=mie_loss: conf/experiment/ has no option 'mie_loss'. Did you "
                               "mean 'mie_los'?"),
    (("+filter@filters.x=fsim",), "conf/filter/ has no option 'fsim'. Did you mean 'fsimm'"),
    (("filterz.fsimm.name=x",), "the config's top level has no key 'filterz'. Did you mean 'filters'?"),
])
def test_a_typo_in_a_key_or_an_option_names_the_close_ones(tmp_path, args, says):
    """Before: Hydra's own text (``Key 'noise_stdd' is not in struct``, ``full_key``, ``object_type``, a
    list of every option) without the close names."""
    proc = _cli(tmp_path, *args)
    assert proc.returncode == 2, proc.stderr
    assert says in proc.stderr, proc.stderr
    assert "Traceback" not in proc.stderr and "object_type" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1              # one paragraph
    assert not (tmp_path / "runs").exists()
