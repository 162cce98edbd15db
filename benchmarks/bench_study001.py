"""Study 001 compute benchmark: batched FSIMM / VSIMM / AO-VSIMM vs the obvious-way loop and FilterPy.

Run from the repository root:

    .venv/bin/python benchmarks/bench_study001.py --runs 100 --seed 1

Inputs are built exactly as the pipeline builds them: ``conf/models/acceleration13.yaml``,
scenario S1 (``conf/scenario/ao_vsimm_s1.yaml``, 200 steps), ``PositionSensor(20 m)``. The
estimators' parameters come from ``conf/filter/{fsimm,vsimm,ao_vsimm}.yaml``.

What is timed (``time.perf_counter``; filtering only, no data generation):

- our batched estimators, all ``--runs`` runs in one ``.run`` call, best of 3, each with its
  configured engine (the compiled cycle, ``filters/imm/kernel.py``) and with ``engine="numpy"``
  (the numpy cycle, the reference), the two timed in turn; the compiled engine's first call, which
  loads the kernel from numba's cache or compiles it, is timed apart;
- the reference loop FSIMM (``benchmarks/reference_imm.py``), one run at a time, over the first
  ``--loop-runs`` runs, exact start mu_0 = e_m1;
- FilterPy's ``IMMEstimator`` (``benchmarks/filterpy_imm.py``), one run at a time, over the first
  ``--filterpy-runs`` runs, with the floored start mu_0 = (1 - 1e-6) e_m1 + 1e-6/12 elsewhere,
  because FilterPy 2.0 cannot run from a zero-probability start (see that module).

When a slow implementation runs fewer runs than ``--runs``, its time for ``--runs`` runs and per
100 runs is extrapolated linearly from its measured per-run time (marked ``*`` in the table).

Correctness checks (printed, and in the JSON; the script exits 1 if one fails; there are no
timing assertions): reference loop vs our FSIMM (exact start), each estimator's numpy engine vs
its compiled engine, FilterPy vs the reference loop
with the same floored start, and FilterPy vs our FSIMM driven from the same floored start
(``FSIMM(initial_mode_probabilities=...)``). Each compares states (k = 1..200) and acceleration estimates, max abs and
relative difference, and the acceleration RMSE.

Acceleration RMSE: RMSE_k = sqrt(mean over runs of (a_hat_k - a_k)^2) per axis, then averaged
over k = 2..200 (the spec's "time-averaged acceleration RMSE (k = 2..200)").
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from hydra.utils import get_class, instantiate  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from benchmarks.reference_imm import reference_fsimm  # noqa: E402
from benchmarks.results_file import Column, Table, add_results_argument, start, write_result  # noqa: E402
from filters.base import MeasurementSeries  # noqa: E402
from filters.imm import FSIMM  # noqa: E402
from pipeline.studies.ao_vsimm.sensor import PositionSensor  # noqa: E402

MEASUREMENT_STD = 20.0
REL_TOL = 1e-9          # max |difference| / max |value|, per quantity
FIRST_SCORED_STEP = 2   # RMSE window k = 2..K-1


# ---------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------
def build_inputs(runs: int, seed: int):
    models = instantiate(OmegaConf.load(ROOT / "conf/models/acceleration13.yaml"))
    scenario = instantiate(OmegaConf.load(ROOT / "conf/scenario/ao_vsimm_s1.yaml"))
    truth = scenario.generate(runs, seed)
    det = PositionSensor(MEASUREMENT_STD).measure(truth, seed)
    R = MEASUREMENT_STD**2 * np.eye(2)
    meas = MeasurementSeries(det.time, det.z[:, :, 0], R, det.detected[:, :, 0], det.sensor)
    return models, scenario, truth, meas


def build_estimator(models, config_name: str, engine: str | None = None):
    """The estimator of ``conf/filter/<config_name>.yaml`` with ``models`` (its other keys as kwargs),
    with ``engine`` in place of the file's when given."""
    cfg = OmegaConf.to_container(OmegaConf.load(ROOT / f"conf/filter/{config_name}.yaml"))
    cls = get_class(cfg.pop("_target_"))
    cfg.pop("models", None)
    cfg.pop("defaults", None)
    if engine is not None:
        cfg["engine"] = engine
    return cls(models, **cfg)


# ---------------------------------------------------------------------------------------------
# metrics and checks
# ---------------------------------------------------------------------------------------------
def acceleration_rmse(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(2,) time-averaged RMSE over k = 2..K-1; estimate, truth (R, K, 2)."""
    err = estimate[:, FIRST_SCORED_STEP:] - truth[:, FIRST_SCORED_STEP:]
    return np.sqrt(np.mean(err**2, axis=0)).mean(axis=0)


def compare(name: str, states: np.ndarray, acc: np.ndarray, ref_states: np.ndarray, ref_acc: np.ndarray,
            truth_acc: np.ndarray, against: str) -> dict:
    """Differences of (states, acc) from (ref_states, ref_acc) over k = 1..K-1 (same runs)."""
    ds = np.abs(states[:, 1:] - ref_states[:, 1:])
    da = np.abs(acc[:, 1:] - ref_acc[:, 1:])
    rmse, ref_rmse = acceleration_rmse(acc, truth_acc), acceleration_rmse(ref_acc, truth_acc)
    out = {
        "implementation": name,
        "against": against,
        "runs": int(states.shape[0]),
        "state_max_abs_diff": float(ds.max()),
        "state_rel_diff": float(ds.max() / np.abs(ref_states[:, 1:]).max()),
        "final_state_max_abs_diff": float(ds[:, -1].max()),
        "acceleration_max_abs_diff": float(da.max()),
        "acceleration_rel_diff": float(da.max() / np.abs(ref_acc[:, 1:]).max()),
        "rmse": rmse.tolist(),
        "rmse_against": ref_rmse.tolist(),
        "rmse_max_abs_diff": float(np.abs(rmse - ref_rmse).max()),
        "all_finite": bool(np.isfinite(states[:, 1:]).all() and np.isfinite(acc[:, 1:]).all()),
    }
    out["passed"] = bool(out["all_finite"] and out["state_rel_diff"] < REL_TOL
                         and out["acceleration_rel_diff"] < REL_TOL)
    return out


def print_check(c: dict) -> None:
    verdict = "PASS" if c["passed"] else "FAIL"
    print(f"  [{verdict}] {c['implementation']} vs {c['against']} ({c['runs']} runs): "
          f"states max|d| = {c['state_max_abs_diff']:.3e} m (rel {c['state_rel_diff']:.1e}), "
          f"final-state max|d| = {c['final_state_max_abs_diff']:.3e}, "
          f"acceleration max|d| = {c['acceleration_max_abs_diff']:.3e} m/s^2 (rel {c['acceleration_rel_diff']:.1e}), "
          f"RMSE X/Y {c['rmse'][0]:.6f}/{c['rmse'][1]:.6f} vs {c['rmse_against'][0]:.6f}/{c['rmse_against'][1]:.6f} "
          f"(max|d| {c['rmse_max_abs_diff']:.1e})")


# ---------------------------------------------------------------------------------------------
# timing
# ---------------------------------------------------------------------------------------------
def time_batched(estimator, meas: MeasurementSeries, repeats: int = 3):
    best, estimate = np.inf, None
    for _ in range(repeats):
        t0 = time.perf_counter()
        estimate = estimator.run(meas)
        best = min(best, time.perf_counter() - t0)
    return best, estimate


def time_alternating(estimators: list, meas: MeasurementSeries, repeats: int = 3):
    """Best of ``repeats`` for each estimator, their runs taken in turn (a, b, a, b, ...), so a change
    of load on a shared machine touches both alike; returns [(seconds, estimate), ...]."""
    best = [np.inf] * len(estimators)
    estimates = [None] * len(estimators)
    for _ in range(repeats):
        for i, est in enumerate(estimators):
            t0 = time.perf_counter()
            estimates[i] = est.run(meas)
            best[i] = min(best[i], time.perf_counter() - t0)
    return list(zip(best, estimates))


def time_loop(fn, meas: MeasurementSeries, runs: int, label: str):
    """Call fn(z (K, 2)) -> (states, acc) for runs 0..runs-1; return total seconds and stacked outputs."""
    K = meas.z.shape[1]
    states = np.full((runs, K, 4), np.nan)
    acc = np.full((runs, K, 2), np.nan)
    total = 0.0
    for r in range(runs):
        t0 = time.perf_counter()
        states[r], acc[r] = fn(meas.z[r])
        total += time.perf_counter() - t0
        if (r + 1) % max(1, runs // 10) == 0 or r + 1 == runs:
            print(f"    {label}: {r + 1}/{runs} runs, {total:.1f} s", file=sys.stderr, flush=True)
    return total, states, acc


# ---------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    context = start("benchmarks/bench_study001.py", argv)
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=100, help="Monte Carlo runs for the batched estimators")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--filterpy-runs", type=int, default=None, help="runs for FilterPy (default: --runs)")
    parser.add_argument("--loop-runs", type=int, default=None, help="runs for the reference loop (default: --runs)")
    parser.add_argument("--skip-filterpy", action="store_true")
    parser.add_argument("--json", type=Path, default=ROOT / "artifacts/benchmarks/study001.json")
    add_results_argument(parser)
    args = parser.parse_args(argv)
    runs = args.runs
    loop_runs = min(args.loop_runs if args.loop_runs is not None else runs, runs)
    fp_runs = min(args.filterpy_runs if args.filterpy_runs is not None else runs, runs)
    if runs < 1 or loop_runs < 1 or fp_runs < 1:
        parser.error("--runs, --loop-runs and --filterpy-runs must be >= 1")

    models, scenario, truth, meas = build_inputs(runs, args.seed)
    truth_acc = truth.labels["acceleration"][:, :, 0]
    R = meas.noise_covariance
    dt = float(np.diff(meas.time[:2])[0])
    K = meas.z.shape[1]
    print(f"Study 001 benchmark: S1, {K - 1} steps, {runs} runs, seed {args.seed}, {models.n_models} models")

    rows: list[dict] = []
    checks: list[dict] = []

    # ---- ours, batched -----------------------------------------------------------------------
    # each configuration with its own engine (compiled by default) and with engine=numpy (the
    # reference), timed in turn; the first call of the compiled engine loads (or compiles) the kernel
    ours, numpy_rows, numpy_estimates, first_call = {}, [], {}, {}
    for config_name in ("fsimm", "vsimm", "ao_vsimm"):
        est = build_estimator(models, config_name)
        reference = build_estimator(models, config_name, engine="numpy")
        t0 = time.perf_counter()
        est.run(meas)
        first_call[config_name] = time.perf_counter() - t0
        pairs = time_alternating([est, reference] if est.engine != "numpy" else [est], meas)
        for (seconds, estimate), label in zip(pairs, ["", ", numpy engine"]):
            evaluated = estimate.extras["models_evaluated"][:, FIRST_SCORED_STEP:].mean()
            row = {"implementation": f"ours {est.name} (batched{label})", "start": "e_m1", "runs": runs,
                   "seconds": seconds, "extrapolated": False, "models_per_step": float(evaluated),
                   "engine": "numpy" if label else est.engine,
                   "rmse": acceleration_rmse(estimate.extras["acceleration"], truth_acc).tolist()}
            if label:
                numpy_rows.append(row)
                numpy_estimates[config_name] = estimate
            else:
                rows.append(row)
                ours[config_name] = estimate
            print(f"  ours {est.name}{label}: {seconds:.3f} s (best of 3), {evaluated:.2f} models/step",
                  file=sys.stderr)
        print(f"  ours {est.name}: first call {first_call[config_name]:.3f} s", file=sys.stderr)
    rows += numpy_rows
    fs = ours["fsimm"]
    fs_states, fs_acc = fs.state, fs.extras["acceleration"]

    # ---- reference loop, exact start ---------------------------------------------------------
    seconds, ref_states, ref_acc = time_loop(lambda z: reference_fsimm(models, z, R, dt), meas, loop_runs,
                                             "reference loop")
    rows.append({"implementation": "reference loop FSIMM", "start": "e_m1", "runs": loop_runs,
                 "seconds": seconds, "extrapolated": loop_runs < runs, "models_per_step": float(models.n_models),
                 "rmse": acceleration_rmse(ref_acc, truth_acc[:loop_runs]).tolist()})
    checks.append(compare("reference loop FSIMM", ref_states, ref_acc, fs_states[:loop_runs], fs_acc[:loop_runs],
                          truth_acc[:loop_runs], "ours FSIMM (exact start e_m1)"))
    for config_name, estimate in numpy_estimates.items():
        # the numpy engine against the default one, every estimator, every run
        checks.append(compare(f"ours {config_name}, numpy engine", estimate.state, estimate.extras["acceleration"],
                              ours[config_name].state, ours[config_name].extras["acceleration"], truth_acc,
                              f"ours {config_name}, {build_estimator(models, config_name).engine} engine"))

    # ---- FilterPy, floored start ---------------------------------------------------------------
    filterpy_info: dict = {"skipped": True}
    if not args.skip_filterpy:
        import filterpy

        from benchmarks.filterpy_imm import FLOOR, exact_start_is_finite, filterpy_fsimm, floored_initial_probabilities
        mu0 = floored_initial_probabilities(models)
        exact_ok = exact_start_is_finite(models, meas.z[0], R, dt)
        filterpy_info = {"skipped": False, "version": filterpy.__version__, "floor": FLOOR,
                         "initial_probabilities": mu0.tolist(), "exact_start_runs": exact_ok}
        print(f"  FilterPy {filterpy.__version__} from the exact start e_m1: "
              f"{'finite' if exact_ok else 'fails (NaN mixing weights, 0/0)'}; using mu_0 floor {FLOOR:g}",
              file=sys.stderr)
        seconds, fp_states, fp_acc = time_loop(lambda z: filterpy_fsimm(models, z, R, dt, mu0), meas, fp_runs,
                                               "FilterPy")
        rows.append({"implementation": "FilterPy IMMEstimator", "start": f"floored ({FLOOR:g})", "runs": fp_runs,
                     "seconds": seconds, "extrapolated": fp_runs < runs, "models_per_step": float(models.n_models),
                     "rmse": acceleration_rmse(fp_acc, truth_acc[:fp_runs]).tolist()})
        # the reference loop from the same floored start (not timed)
        _, reff_states, reff_acc = time_loop(lambda z: reference_fsimm(models, z, R, dt, mu0), meas, fp_runs,
                                             "reference loop, floored start (check only)")
        checks.append(compare("FilterPy IMMEstimator", fp_states, fp_acc, reff_states, reff_acc,
                              truth_acc[:fp_runs], "reference loop (same floored start)"))
        fsf = FSIMM(models, name="FSIMM (floored start)", initial_mode_probabilities=mu0.tolist()).run(meas)
        checks.append(compare("FilterPy IMMEstimator", fp_states, fp_acc, fsf.state[:fp_runs],
                              fsf.extras["acceleration"][:fp_runs], truth_acc[:fp_runs],
                              "ours FSIMM (same floored start)"))
        both = min(fp_runs, loop_runs)      # the runs both reference loops filtered
        floor_effect = compare("reference loop, floored start", reff_states[:both], reff_acc[:both],
                               ref_states[:both], ref_acc[:both], truth_acc[:both], "reference loop, exact start")
        floor_effect["passed"] = None       # informational: the floor is a different filter
        filterpy_info["floor_effect"] = floor_effect

    # ---- derived columns ---------------------------------------------------------------------
    fp_row = next((r for r in rows if r["implementation"].startswith("FilterPy")), None)
    loop_row = next(r for r in rows if r["implementation"].startswith("reference loop"))
    fs_row = rows[0]
    for r in rows:
        r["seconds_per_run"] = r["seconds"] / r["runs"]
        r["seconds_at_runs"] = r["seconds_per_run"] * runs
        r["seconds_per_100_runs"] = r["seconds_per_run"] * 100
    for r in rows:
        r["speedup_vs_filterpy"] = (fp_row["seconds_per_run"] / r["seconds_per_run"]) if fp_row else None
        r["speedup_vs_loop"] = loop_row["seconds_per_run"] / r["seconds_per_run"]
        r["models_pct_of_fsimm"] = 100.0 * r["models_per_step"] / models.n_models
        # CPU share of FSIMM is only meaningful between the batched estimators (same code path, same runs):
        # each engine's rows against that engine's FSIMM
        same = next((f for f in rows if f["implementation"].startswith("ours FSIMM") and f.get("engine") == r.get("engine")),
                    fs_row)
        r["time_pct_of_fsimm"] = (100.0 * r["seconds_per_run"] / same["seconds_per_run"]
                                  if r["implementation"].startswith("ours") else None)

    # ---- report --------------------------------------------------------------------------------
    print()
    print("Correctness (max abs difference over k = 1..200, all listed runs):")
    for c in checks:
        print_check(c)
    if "floor_effect" in filterpy_info:
        fe = filterpy_info["floor_effect"]
        print(f"  [info] effect of the 1e-6 floor itself (reference loop floored vs exact, {fe['runs']} runs): "
              f"states max|d| = {fe['state_max_abs_diff']:.2e} m, acceleration max|d| = "
              f"{fe['acceleration_max_abs_diff']:.2e} m/s^2, RMSE max|d| = {fe['rmse_max_abs_diff']:.1e}")
    print()
    print(f"| implementation | start | runs timed | filtering s | s/run | s for {runs} runs | s per 100 runs "
          f"| speed-up vs FilterPy | models/step | % of FSIMM (models) | % of FSIMM (time) "
          f"| acc RMSE X | acc RMSE Y |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        star = "*" if r["runs"] != runs else ""
        per100_star = "*" if r["runs"] != 100 else ""
        speed = f"{r['speedup_vs_filterpy']:.1f}x" if r["speedup_vs_filterpy"] is not None else "n/a"
        time_pct = "-" if r["time_pct_of_fsimm"] is None else f"{r['time_pct_of_fsimm']:.1f}"
        print(f"| {r['implementation']} | {r['start']} | {r['runs']} | {r['seconds']:.3f} | {r['seconds_per_run']:.4f} "
              f"| {r['seconds_at_runs']:.2f}{star} | {r['seconds_per_100_runs']:.2f}{per100_star} | {speed} "
              f"| {r['models_per_step']:.2f} | {r['models_pct_of_fsimm']:.1f} | {time_pct} "
              f"| {r['rmse'][0]:.4f} | {r['rmse'][1]:.4f} |")
    notes = []
    if any(r["runs"] != runs for r in rows) or runs != 100:
        notes.append("* not measured: scaled linearly from the measured per-run time (that row timed fewer runs"
                     + (f"; the batched rows timed {runs}, and batching makes their per-100 figure indicative only"
                        if runs != 100 else "") + ").")
    notes.append("Batched: one .run over all runs, best of 3, each estimator's engines timed in turn; the first "
                 "call (not in the table) loads or compiles the compiled engine's kernel: "
                 + ", ".join(f"{k} {v:.2f} s" for k, v in first_call.items()) + ".")
    notes.append("Loops: one run at a time, summed. "
                 "RMSE: per-k RMSE over the timed runs, averaged over k = 2..200.")
    if fp_row:
        notes.append("FilterPy runs from mu_0 = (1-1e-6) e_m1 + 1e-6/12 elsewhere (it fails from e_m1); "
                     "all other rows from e_m1.")
    for n in notes:
        print(n)
    print(f"Machine: {platform.platform()}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} CPUs, Python {platform.python_version()}, numpy {np.__version__}")

    result = {
        "study": "001", "scenario": "S1", "steps": K - 1, "runs": runs, "seed": args.seed,
        "loop_runs": loop_runs, "filterpy_runs": fp_runs if not args.skip_filterpy else 0,
        "rmse_definition": "mean over k=2..K-1 of sqrt(mean over runs of (a_hat - a)^2), per axis",
        "rows": rows, "checks": checks, "filterpy": filterpy_info, "first_call_seconds": first_call,
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpus": os.cpu_count(), "python": platform.python_version(), "numpy": np.__version__},
        "all_checks_passed": all(c["passed"] for c in checks),
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(result, indent=2))
    print(f"JSON: {args.json}")
    table_rows = [{**r, "timed": f"{r['runs']}" + (" (extrapolated)" if r["runs"] != runs else ""),
                   "rmse_x": r["rmse"][0], "rmse_y": r["rmse"][1]} for r in rows]
    columns = [Column("implementation", "implementation"), Column("start", "start"),
               Column("timed", "runs timed"), Column("seconds_at_runs", f"{runs} runs", "seconds", ".3f"),
               Column("speedup_vs_filterpy", "vs FilterPy", "ratio", ".1f"),
               Column("speedup_vs_loop", "vs reference loop", "ratio", ".1f"),
               Column("time_pct_of_fsimm", "time, of FSIMM (same engine)", "percent", ".1f"),
               Column("models_per_step", "models/step", "number", ".2f"),
               Column("rmse_x", "acc RMSE X", "number", ".4f"), Column("rmse_y", "acc RMSE Y", "number", ".4f")]
    check_notes = [f"{'PASS' if c['passed'] else 'FAIL'}: {c['implementation']} vs {c['against']} ({c['runs']} runs): "
                   f"states rel. difference {c['state_rel_diff']:.1e}, acceleration {c['acceleration_rel_diff']:.1e}"
                   for c in checks]
    write_result("study001", "Study 001: the batched IMMs against the reference loop and FilterPy (filtering only)",
                 [Table(columns, table_rows)], notes + check_notes, context=context,
                 parameters={"scenario": "S1", "steps": K - 1, "runs": runs, "reference-loop runs": loop_runs,
                             "FilterPy runs": fp_runs if not args.skip_filterpy else 0, "seed": args.seed},
                 directory=args.results_dir)
    return 0 if result["all_checks_passed"] else 1


if __name__ == "__main__":
    sys.exit(main())
