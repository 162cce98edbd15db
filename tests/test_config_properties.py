"""Property tests: generated invalid values for the typed keys of every experiment's config groups
are refused before any stage runs, with a message that names the key and what is allowed.

Each test draws (experiment, key) pairs from every composed experiment in conf/experiment and a
bad value of one kind (wrong type, negative spread, probability outside [0, 1], zero or negative
count or duration, wrong vector or matrix shape, transition rows not summing to 1, unknown
variant names). ``pipeline.run.runner.prepare`` is what the runner calls before its first stage: it
validates, builds every node and cross-checks them without reading or writing a file.
``pytest --hypothesis-show-statistics tests/test_config_properties.py`` prints how many cases ran.
"""

from __future__ import annotations

import copy
import functools
import math
import re
from pathlib import Path

import pytest
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict

from hypothesis import HealthCheck, given, settings, strategies as st

from pipeline.errors import ConfigError
from pipeline.run.runner import prepare
from tests.helpers.config import composed

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = sorted(p.stem for p in (ROOT / "conf" / "experiment").glob("*.yaml"))
# groups whose leaves are typed constructor arguments or checked run settings
GROUPS = ("mc", "scenario", "sensors", "filters", "study", "models", "target_model")
SKIP = re.compile(r"(^|\.)(_target_|name|description)$|^filters\.[^.]+\.models(\.|$)|^record\.|^metrics\.")
EXAMPLES = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@functools.cache
def _composed(experiment: str) -> DictConfig:
    # unresolved: a bad target_model.X reaches the filters through ${...}
    cfg = composed(experiment)
    cfg.paths.artifacts = "/nonexistent-artifacts"
    return cfg


def _leaves(node, prefix: str = ""):
    if isinstance(node, DictConfig):
        for key in node.keys():
            yield from _leaves(node.get(key), f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, node


def _keys(predicate) -> list[tuple[str, str]]:
    """(experiment, dotted key) of every leaf in GROUPS whose value satisfies predicate(key, value)."""
    out = []
    for experiment in EXPERIMENTS:
        cfg = _composed(experiment)
        for group in GROUPS:
            if cfg.get(group) is None:
                continue
            for key, value in _leaves(cfg.get(group), group):
                if not SKIP.search(key) and predicate(key, value):
                    out.append((experiment, key))
    return out


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _numbers(value) -> bool:
    return isinstance(value, ListConfig) and len(value) > 0 and all(_is_number(v) for v in value)


def _matrix(value) -> bool:
    return (isinstance(value, ListConfig) and len(value) > 1 and all(isinstance(r, ListConfig) for r in value)
            and len({len(r) for r in value}) == 1)


def _with(experiment: str, key: str, value) -> DictConfig:
    cfg = copy.deepcopy(_composed(experiment))
    with open_dict(cfg):
        OmegaConf.update(cfg, key, value, force_add=True)
    return cfg


def _assert_refused(cfg: DictConfig, key: str, value) -> None:
    with pytest.raises(ConfigError) as info:
        prepare(cfg)
    message = str(info.value)
    leaf = key.rsplit(".", 1)[-1]
    assert leaf in message, f"{key}={value!r}: the message does not name '{leaf}': {message}"
    assert len(message.splitlines()) == 1, message
    assert re.search(r"must|allowed|one of|not a |takes|expected|sum|need", message), message


SPREAD = re.compile(r"(_std|std_|^std$|sigma|variance|noise_density|process_noise_std)")
PROBABILITY = re.compile(r"(probability$|activation_threshold$)")
POSITIVE = re.compile(r"(^mc\.runs$|particles$|\.window$|min_samples$|\.steps$|\.duration$|\.dt$|\.tau$|bound_tau$)")
STOCHASTIC = re.compile(r"(transition_matrix$|\.tpm$)")

NUMBER_KEYS = _keys(lambda k, v: _is_number(v))
BOOL_KEYS = _keys(lambda k, v: isinstance(v, bool))
SPREAD_KEYS = _keys(lambda k, v: SPREAD.search(k.rsplit(".", 1)[-1]) and (_is_number(v) or _numbers(v)))
PROBABILITY_KEYS = _keys(lambda k, v: PROBABILITY.search(k) and _is_number(v))
POSITIVE_KEYS = _keys(lambda k, v: POSITIVE.search(k) and _is_number(v))
STOCHASTIC_KEYS = _keys(lambda k, v: STOCHASTIC.search(k) and _matrix(v))
VECTOR_KEYS = _keys(lambda k, v: re.search(r"(initial_position|initial_velocity|^sensors\.position|initial_state|"
                                           r"target_start|target_velocity|observer_position|buoy_drift)$", k)
                    and _numbers(v))


def test_the_rules_reach_every_experiment():
    """Guard against a rule that silently matches nothing after a rename."""
    for keys in (NUMBER_KEYS, BOOL_KEYS, SPREAD_KEYS, PROBABILITY_KEYS, POSITIVE_KEYS, STOCHASTIC_KEYS, VECTOR_KEYS):
        assert keys
    assert {e for e, _ in NUMBER_KEYS} == set(EXPERIMENTS)
    assert {e for e, _ in SPREAD_KEYS} == set(EXPERIMENTS)


not_a_number = st.one_of(st.text(min_size=1, max_size=8).filter(lambda s: not _parses_as_number(s)),
                         st.lists(st.integers(), min_size=1, max_size=3), st.booleans())


def _parses_as_number(text: str) -> bool:
    try:
        float(text)
        return True
    except ValueError:
        return False


@EXAMPLES
@given(case=st.sampled_from(NUMBER_KEYS), value=not_a_number)
def test_a_number_of_the_wrong_type_is_refused(case, value):
    experiment, key = case
    _assert_refused(_with(experiment, key, value), key, value)


@EXAMPLES
@given(case=st.sampled_from(BOOL_KEYS), value=st.one_of(st.text(max_size=6), st.integers(), st.floats()))
def test_a_switch_that_is_not_true_or_false_is_refused(case, value):
    experiment, key = case
    _assert_refused(_with(experiment, key, value), key, value)


@EXAMPLES
@given(case=st.sampled_from(SPREAD_KEYS), magnitude=st.one_of(st.floats(1e-9, 1e9), st.just(math.inf)),
       where=st.integers(0, 100))
def test_a_negative_or_infinite_spread_is_refused(case, magnitude, where):
    experiment, key = case
    current = OmegaConf.select(_composed(experiment), key)
    bad = -magnitude if math.isfinite(magnitude) else math.nan
    if isinstance(current, ListConfig):
        value = list(current)
        value[where % len(value)] = bad
    else:
        value = bad
    _assert_refused(_with(experiment, key, value), key, value)


@EXAMPLES
@given(case=st.sampled_from(PROBABILITY_KEYS),
       value=st.one_of(st.floats(max_value=-1e-6, allow_nan=False), st.floats(min_value=1.000001, allow_nan=False)))
def test_a_probability_outside_zero_one_is_refused(case, value):
    experiment, key = case
    _assert_refused(_with(experiment, key, value), key, value)


@EXAMPLES
@given(case=st.sampled_from(POSITIVE_KEYS), value=st.integers(-10**6, 0))
def test_a_zero_or_negative_count_or_duration_is_refused(case, value):
    experiment, key = case
    _assert_refused(_with(experiment, key, value), key, value)


@EXAMPLES
@given(case=st.sampled_from(STOCHASTIC_KEYS), row=st.integers(0, 100), column=st.integers(0, 100),
       shift=st.floats(1e-3, 0.5), reshape=st.sampled_from(["perturb", "drop_row", "drop_column"]))
def test_a_transition_matrix_of_the_wrong_shape_or_with_rows_not_summing_to_one_is_refused(
        case, row, column, shift, reshape):
    experiment, key = case
    matrix = [list(r) for r in OmegaConf.select(_composed(experiment), key)]
    i, j = row % len(matrix), column % len(matrix[0])
    if reshape == "perturb":
        entry = matrix[i][j]
        number = float(eval(entry, {}, {})) if isinstance(entry, str) else float(entry)  # "29/30" fractions
        matrix[i][j] = number + shift if number + shift <= 1 else number - shift
    elif reshape == "drop_row":
        del matrix[i]
    else:
        for r in matrix:
            del r[j]
    _assert_refused(_with(experiment, key, matrix), key, matrix)


@EXAMPLES
@given(case=st.sampled_from(VECTOR_KEYS), extra=st.integers(1, 3), shorter=st.booleans())
def test_a_vector_of_the_wrong_length_is_refused(case, extra, shorter):
    experiment, key = case
    vector = list(OmegaConf.select(_composed(experiment), key))
    value = vector[:-1] if shorter else vector + [0.0] * extra
    _assert_refused(_with(experiment, key, value), key, value)


@EXAMPLES
@given(experiment=st.sampled_from(EXPERIMENTS),
       name=st.text(alphabet="abcdefghijklmnopqrstuvwxyz_0123456789", min_size=1, max_size=12))
def test_an_unknown_variant_name_is_refused(experiment, name):
    cfg = _composed(experiment)
    if name in cfg.filters:
        return
    with pytest.raises(ConfigError) as info:
        prepare(_with(experiment, "variants", [name]))
    assert name in str(info.value) and all(v in str(info.value) for v in cfg.filters)
    with pytest.raises(ConfigError) as info:
        prepare(_with(experiment, "metrics.reference_variant", name))
    assert name in str(info.value) and "reference_variant" in str(info.value)


# ---- pipeline.run.config.missing_keys names the unset values as OmegaConf.missing_keys does ------------
_NAMES = st.text(alphabet="abcdefghij_", min_size=1, max_size=4)
_LEAVES = st.one_of(st.integers(-3, 3), st.sampled_from(["???", "x", "?", "??? ", ""]), st.none())
_TREES = st.recursive(_LEAVES, lambda children: st.one_of(st.lists(children, max_size=3),
                                                          st.dictionaries(_NAMES, children, max_size=3)),
                      max_leaves=12)


@EXAMPLES
@given(tree=st.dictionaries(_NAMES, _TREES, max_size=4))
def test_the_missing_keys_of_a_resolved_config_are_omegaconfs(tree):
    """validate reads them off the config it has resolved once, instead of OmegaConf's own walk."""
    from pipeline.run.config import missing_keys
    cfg = OmegaConf.create(tree)
    assert sorted(missing_keys(OmegaConf.to_container(cfg, resolve=True))) == sorted(OmegaConf.missing_keys(cfg))


@pytest.mark.parametrize("experiment", ["ao_vsimm_s1", "sonar_case1"])
def test_a_mandatory_value_left_unset_is_refused_with_its_key(experiment):
    key = "mc.seed" if experiment == "ao_vsimm_s1" else "scenario.duration"
    with pytest.raises(ConfigError, match=rf"missing mandatory config value\(s\) \['{re.escape(key)}'\]"):
        prepare(_with(experiment, key, "???"))
