"""``mtt-query diff RUN_A RUN_B``: did my change make it better, beyond noise?

Three parts, as DVC's ``exp diff`` has them where they fit:

- **config**: the dotted keys whose values differ (where a job wrote, ``paths.*``/``hydra.*``, left out);
- **code**: the two commits (how many commits lie between, ``git diff --stat``), each run's
  uncommitted diff (pipeline.run.provenance) and the files whose uncommitted change differs between
  the runs, the user packages and the environment where they differ;
- **metrics**: for every variant and summary series and window both runs have, ``B - A`` with an
  interval at the runs' confidence, and which kind:

  - *paired by run*: both jobs ran on the same truth and measurements (the same ``truth`` and
    ``detections`` stage keys, hence the same seeds), with the same number of runs and the same
    job seed, so their bootstrap resamples drew the same run indices
    (pipeline.evaluation.uncertainty: one stream per job seed). Resample j of A and of B then
    describe the same resampled Monte Carlo runs, and the percentile interval of
    ``stat_B(j) - stat_A(j)`` is the paired bootstrap interval of the difference: run-to-run noise
    common to both cancels, which is what resolves a small change of a filter.
  - *unpaired*: different data (another scenario or noise, other runs or seed). The interval is
    ``(B - A) ± z sqrt(se_A^2 + se_B^2)`` from the two summaries' standard errors (normal).
  - *identical*: the variant's estimates have the same cache key in both (same code, config and
    inputs), or a paired row whose value and every resample are equal in both: the difference is 0
    (left out of the table unless ``--all``).

``diff SWEEP_A SWEEP_B`` pairs the jobs of two sweep folders by their swept values (the overrides
that vary within each sweep) and compares each pair.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import polars as pl
from scipy import stats

from pipeline.evaluation.uncertainty import CONFIDENCE
from pipeline.results.query import QueryError, render as render_table
from pipeline.results.tracking import LOCATION_KEYS, STATUS, Run, load_runs, resolve_folder, resolve_run

PAIRED, UNPAIRED, IDENTICAL = "paired by run", "unpaired", "identical"
METRIC_COLUMNS = ["variant", "series", "window", "a", "b", "difference", "ci_low", "ci_high", "resolved", "pairing"]


@dataclass
class RunDiff:
    a: Run
    b: Run
    config: list[dict[str, Any]]
    code: dict[str, Any]
    metrics: pl.DataFrame
    pairing: str                    # why paired or not, one sentence
    left_out: int = 0               # identical rows not shown
    job: str | None = None          # a sweep pair's swept values


@dataclass
class Comparison:
    pairs: list[RunDiff]
    unmatched: dict[str, list[str]] = field(default_factory=dict)
    sweeps: tuple[str, str] | None = None


# ---- config ----------------------------------------------------------------------------------
def config_changes(a: Run, b: Run) -> list[dict[str, Any]]:
    ca, cb = a.config(), b.config()
    rows = []
    for key in sorted(set(ca) | set(cb)):
        if key.startswith(LOCATION_KEYS):
            continue
        va, vb = ca.get(key, "(absent)"), cb.get(key, "(absent)")
        if json.dumps(va, default=str) != json.dumps(vb, default=str):
            rows.append({"key": key, "a": va, "b": vb})
    return rows


# ---- code ------------------------------------------------------------------------------------
def _patches(run: Run) -> dict[str, str]:
    """The run's uncommitted diff split per file (``diff --git a/X b/X`` blocks)."""
    name = run.git.get("diff_file")
    if not name:
        return {}
    try:
        text = (run.path / name).read_text(errors="replace")
    except OSError:
        return {"(diff file missing)": ""}
    files: dict[str, str] = {}
    current = None
    for line in text.splitlines(keepends=True):
        if line.startswith("diff --git "):
            current = line.split(" b/", 1)[-1].strip()
            files[current] = ""
        if current is not None:
            files[current] += line
    return files


def _stat(patch: str) -> tuple[int, int]:
    added = sum(1 for ln in patch.splitlines() if ln.startswith("+") and not ln.startswith("+++"))
    removed = sum(1 for ln in patch.splitlines() if ln.startswith("-") and not ln.startswith("---"))
    return added, removed


def _git(root: str, *args: str) -> str | None:
    try:
        done = subprocess.run(["git", "-C", root, *args], capture_output=True, timeout=20, text=True)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return done.stdout.strip() if done.returncode == 0 else None


def code_changes(a: Run, b: Run) -> dict[str, Any]:
    ga, gb = a.git, b.git
    out: dict[str, Any] = {"a": _code_line(a), "b": _code_line(b), "same_code": a.provenance.get("code") ==
                           b.provenance.get("code") and a.provenance.get("code") is not None}
    if ga.get("available") and gb.get("available") and ga.get("commit") != gb.get("commit"):
        root = gb.get("root") if ga.get("root") == gb.get("root") else None
        if root:
            ahead = _git(root, "rev-list", "--count", f"{ga['commit']}..{gb['commit']}")
            behind = _git(root, "rev-list", "--count", f"{gb['commit']}..{ga['commit']}")
            stat = _git(root, "diff", "--stat=100", ga["commit"], gb["commit"])
            out["commits"] = (f"{gb['commit'][:10]} is {ahead} commits after and {behind} before {ga['commit'][:10]}"
                              if ahead is not None else "one of the commits is not in the checkout any more")
            out["commit_stat"] = stat
    pa, pb = _patches(a), _patches(b)
    changed = sorted(f for f in set(pa) | set(pb) if pa.get(f) != pb.get(f))
    out["uncommitted"] = [{"file": f, "a": "+%d -%d" % _stat(pa[f]) if f in pa else "", "b": "+%d -%d" % _stat(pb[f])
                           if f in pb else ""} for f in changed]
    out["patches"] = {f: {"a": pa.get(f), "b": pb.get(f)} for f in changed}
    ua, ub = a.provenance.get("user_packages") or {}, b.provenance.get("user_packages") or {}
    out["user_packages"] = [{"package": k, "a": (ua.get(k) or {}).get("sha256", "(absent)")[:12],
                             "b": (ub.get(k) or {}).get("sha256", "(absent)")[:12]}
                            for k in sorted(set(ua) | set(ub)) if (ua.get(k) or {}).get("sha256") !=
                            (ub.get(k) or {}).get("sha256")]
    ea, eb = a.status.get("environment") or {}, b.status.get("environment") or {}
    da, db = ea.get("distributions") or {}, eb.get("distributions") or {}
    out["environment"] = [{"distribution": k, "a": da.get(k), "b": db.get(k)} for k in sorted(set(da) | set(db))
                          if da.get(k) != db.get(k)]
    if ea.get("python") != eb.get("python"):
        out["environment"].append({"distribution": "python", "a": ea.get("python"), "b": eb.get("python")})
    return out


def _code_line(run: Run) -> str:
    git = run.git
    if not run.provenance:
        return "not recorded (a run from before provenance)"
    if not git.get("available"):
        return f"no git: {git.get('reason')}"
    dirty = f", dirty (diff {git['diff_sha256'][:10]}, {git.get('diff_file')})" if git.get("dirty") else ", clean"
    return f"{git['commit'][:10]} on {git.get('branch') or 'a detached HEAD'}{dirty}; code {run.provenance.get('code')}"


# ---- metrics ---------------------------------------------------------------------------------
def _seed_and_confidence(run: Run) -> tuple[Any, float]:
    config = run.config()
    return config.get("mc.seed"), float(config.get("uncertainty.confidence", CONFIDENCE))


def pairing(a: Run, b: Run) -> tuple[bool, str]:
    """(paired?, why): paired by run when both ran on the same truth and measurements, runs and seed."""
    ka, kb = a.stage_keys(), b.stage_keys()
    reasons = []
    for output, what in (("truth.parquet", "scenario"), ("detections.parquet", "measurements")):
        if not ka.get(output) or not kb.get(output):
            reasons.append(f"a run does not record its {what} key")
        elif ka[output] != kb[output]:
            reasons.append(f"the {what} differ ({output} has key {ka[output]} in A, {kb[output]} in B)")
    if a.status.get("runs") != b.status.get("runs"):
        reasons.append(f"the numbers of runs differ ({a.status.get('runs')} and {b.status.get('runs')})")
    if _seed_and_confidence(a)[0] != _seed_and_confidence(b)[0]:
        reasons.append("the job seeds differ")
    for run in (a, b):
        if not (run.path / "resamples.parquet").is_file():
            reasons.append(f"{run.run_id} has no resamples.parquet")
    if reasons:
        return False, "unpaired: " + "; ".join(reasons)
    return True, (f"paired by run: both ran on the same truth and measurements ({a.status.get('runs')} runs, "
                  f"same seed), so run r is the same target and noise in both and the bootstrap resamples match")


def _summary(run: Run) -> pl.DataFrame:
    path = run.path / "summary.parquet"
    if not path.is_file():
        raise QueryError(f"{run.run_id}: no summary.parquet (status {run.status.get('status')}); only finished "
                         f"runs can be compared.")
    cols = ["variant", "variant_key", "series", "window", "value", "standard_error"]
    return pl.read_parquet(path, columns=cols).filter(pl.col("window").is_not_null() & pl.col("series").is_not_null())


def metric_differences(a: Run, b: Run, metrics: Sequence[str] = (), windows: Sequence[str] = ()
                       ) -> tuple[pl.DataFrame, str]:
    paired, why = pairing(a, b)
    confidence = _seed_and_confidence(b)[1]
    sa, sb = _summary(a), _summary(b)
    joined = sa.join(sb, on=["variant_key", "series", "window"], suffix="_b", how="inner")
    if metrics:
        joined = joined.filter(pl.col("series").is_in(list(metrics)))
    if windows:
        joined = joined.filter(pl.col("window").is_in(list(windows)))
    low_q, high_q = (1 - confidence) / 2, (1 + confidence) / 2
    intervals: dict[tuple[str, str, str], tuple[float, float]] = {}
    unchanged: set[tuple[str, str, str]] = set()        # every resample equal: the same numbers in both
    resampled: set[tuple[str, str, str]] = set()        # the rows both runs have resamples of
    if paired:
        ra = pl.read_parquet(a.path / "resamples.parquet")
        rb = pl.read_parquet(b.path / "resamples.parquet")
        both = ra.join(rb, on=["variant_key", "series", "window", "resample"], suffix="_b")
        both = both.with_columns((pl.col("value_b") - pl.col("value")).alias("d")).filter(pl.col("d").is_not_nan())
        resampled = set(map(tuple, ra.select("variant_key", "series", "window").unique().iter_rows())) & \
            set(map(tuple, rb.select("variant_key", "series", "window").unique().iter_rows()))
        for (variant_key, series, window), group in both.group_by(["variant_key", "series", "window"]):
            d = group["d"].to_numpy()
            if d.size and not d.any():
                unchanged.add((variant_key, series, window))
            if d.size >= 20:
                intervals[(variant_key, series, window)] = (float(np.quantile(d, low_q)), float(np.quantile(d, high_q)))
    z = float(stats.norm.ppf(high_q))
    ka, kb = a.stage_keys(), b.stage_keys()
    rows = []
    for row in joined.iter_rows(named=True):
        key = (row["variant_key"], row["series"], row["window"])
        va, vb = row["value"], row["value_b"]
        difference = None if va is None or vb is None else vb - va
        track = f"estimates/{row['variant_key']}.parquet"
        if paired and (ka.get(track) and ka.get(track) == kb.get(track) or key in unchanged and difference == 0):
            kind, low, high = IDENTICAL, 0.0, 0.0
            difference = 0.0 if difference is not None else None
        elif paired and key in intervals:
            kind, (low, high) = PAIRED, intervals[key]
        elif paired and key not in resampled:
            # a row without resamples (a constant such as a chi-square band's bound, a ratio of means,
            # a single timing): equal means the same number, else a difference with no interval
            low = high = None
            kind = IDENTICAL if difference == 0 else f"{PAIRED} (no interval: the row has no resamples)"
        else:
            kind = UNPAIRED
            se_a, se_b = row["standard_error"], row["standard_error_b"]
            if difference is None or se_a is None or se_b is None or not np.isfinite(se_a + se_b):
                low = high = None
                kind = f"{UNPAIRED} (no interval: a single sample)" if difference is not None else UNPAIRED
            else:
                half = z * float(np.hypot(se_a, se_b))
                low, high = difference - half, difference + half
        resolved = None if low is None or high is None else bool(low > 0 or high < 0)
        rows.append({"variant": row["variant_b"] or row["variant"], "series": row["series"], "window": row["window"],
                     "a": va, "b": vb, "difference": difference, "ci_low": low, "ci_high": high,
                     "resolved": resolved, "pairing": kind})
    schema = {"variant": pl.String, "series": pl.String, "window": pl.String, "a": pl.Float64, "b": pl.Float64,
              "difference": pl.Float64, "ci_low": pl.Float64, "ci_high": pl.Float64, "resolved": pl.Boolean,
              "pairing": pl.String}
    df = pl.DataFrame(rows, schema=schema).sort(["variant", "series", "window"])
    return df, f"{why}; intervals at {confidence:g} confidence"


def compare_runs(a: Run, b: Run, metrics: Sequence[str] = (), windows: Sequence[str] = (), everything: bool = False,
                 job: str | None = None) -> RunDiff:
    table, why = metric_differences(a, b, metrics, windows)
    left_out = 0
    if not everything:
        shown = table.filter(pl.col("pairing") != IDENTICAL)
        left_out = table.height - shown.height
        table = shown
    return RunDiff(a, b, config_changes(a, b), code_changes(a, b), table, why, left_out, job)


# ---- sweeps ----------------------------------------------------------------------------------
def _swept(jobs: Sequence[Run]) -> dict[str, Run]:
    """Each job by its swept values: the overrides that vary within the sweep."""
    sets = [frozenset(o for o in (j.status.get("overrides") or []) if not o.startswith(("hydra.", "paths.")))
            for j in jobs]
    common = frozenset.intersection(*sets) if sets else frozenset()
    by_values: dict[str, Run] = {}
    for job, overrides in zip(jobs, sets):
        name = " ".join(sorted(overrides - common)) or "(no swept values)"
        by_values[name] = job
    return by_values


def compare(root: Path, a: str, b: str, metrics: Sequence[str] = (), windows: Sequence[str] = (),
            everything: bool = False) -> Comparison:
    path_a, path_b = resolve_folder(root, a, "RUN_A"), resolve_folder(root, b, "RUN_B")
    if (path_a / STATUS).is_file() and (path_b / STATUS).is_file():
        return Comparison([compare_runs(resolve_run(root, a), resolve_run(root, b), metrics, windows, everything)])
    if (path_a / STATUS).is_file() or (path_b / STATUS).is_file():
        raise QueryError(f"diff: '{a}' and '{b}' must both be runs or both be sweep folders; one is a run "
                         f"(it has {STATUS}) and the other is not.")
    jobs_a = _swept(load_runs(root, path_a))
    jobs_b = _swept(load_runs(root, path_b))
    if not jobs_a or not jobs_b:
        raise QueryError(f"diff: '{a if not jobs_a else b}' holds no runs or sweep jobs.")
    shared = [k for k in jobs_a if k in jobs_b]
    if not shared:
        raise QueryError(f"diff: no job of '{a}' has the swept values of a job of '{b}'. {a}: "
                         f"{sorted(jobs_a)[:6]}; {b}: {sorted(jobs_b)[:6]}.")
    pairs = [compare_runs(jobs_a[k], jobs_b[k], metrics, windows, everything, job=k) for k in shared]
    return Comparison(pairs, {"a": sorted(set(jobs_a) - set(shared)), "b": sorted(set(jobs_b) - set(shared))},
                      (str(a), str(b)))


# ---- output ----------------------------------------------------------------------------------
def _fmt(v: Any) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _text_pair(pair: RunDiff, markdown: bool, patch: bool) -> str:
    h = (lambda t: f"### {t}\n\n") if markdown else (lambda t: f"{t}\n")
    lines = []
    if pair.job is not None:
        lines.append(("## " if markdown else "== ") + f"job: {pair.job}\n")
    lines.append(f"A: {pair.a.run_id}\nB: {pair.b.run_id}\n")
    lines.append(h("config"))
    if pair.config:
        lines.append(render_table(pl.DataFrame([{k: _fmt(v) for k, v in r.items()} for r in pair.config]),
                                  "markdown" if markdown else "table", max_rows=0))
    else:
        lines.append("(no config key differs)\n")
    code = pair.code
    lines.append(h("code"))
    lines.append(f"A: {code['a']}\nB: {code['b']}\n")
    if code.get("commits"):
        lines.append(code["commits"] + "\n")
        if code.get("commit_stat"):
            lines.append(code["commit_stat"] + "\n")
    if code["uncommitted"]:
        lines.append("uncommitted changes that differ between the runs (lines added/removed in each run's diff):\n")
        lines.append(render_table(pl.DataFrame(code["uncommitted"]), "markdown" if markdown else "table", max_rows=0))
        if patch:
            for name, both in code["patches"].items():
                for side in ("a", "b"):
                    if both[side]:
                        lines.append(f"--- {side.upper()}'s uncommitted change to {name}:\n{both[side]}")
    elif code["same_code"]:
        lines.append("same code (commit, uncommitted diff and user packages)\n")
    for part, title in (("user_packages", "user packages that differ"), ("environment", "environment differences")):
        if code[part]:
            lines.append(f"{title}:\n" + render_table(pl.DataFrame(code[part]), "markdown" if markdown else "table",
                                                     max_rows=0))
    lines.append(h("metrics: B - A"))
    lines.append(pair.pairing + "\n")
    if pair.metrics.height:
        shown = pair.metrics.with_columns(pl.col("resolved").replace_strict({True: "*", False: ""}, default="")
                                          .alias("resolved"))
        lines.append(render_table(shown, "markdown" if markdown else "table", max_rows=0))
    if pair.left_out:
        lines.append(f"({pair.left_out} rows identical in both runs left out (the same estimates, or the same value "
                     f"and resamples): difference 0; --all shows them)\n")
    lines.append("* = resolved: the interval excludes 0\n")
    return "\n".join(lines)


def render(comparison: Comparison, fmt: str, patch: bool = False) -> str:
    if fmt == "json":
        return json.dumps({"sweeps": comparison.sweeps, "unmatched": comparison.unmatched, "pairs": [
            {"job": p.job, "a": p.a.run_id, "b": p.b.run_id, "config": p.config,
             "code": {k: v for k, v in p.code.items() if patch or k != "patches"}, "pairing": p.pairing,
             "metrics": p.metrics.to_dicts(), "identical_rows_left_out": p.left_out}
            for p in comparison.pairs]}, indent=2, default=str) + "\n"
    if fmt == "csv":
        frames = [p.metrics.with_columns(pl.lit(p.job).alias("job"), pl.lit(p.a.run_id).alias("run_a"),
                                         pl.lit(p.b.run_id).alias("run_b")) for p in comparison.pairs]
        return pl.concat(frames).write_csv()
    markdown = fmt == "markdown"
    text = "\n".join(_text_pair(p, markdown, patch) for p in comparison.pairs)
    if comparison.unmatched.get("a") or comparison.unmatched.get("b"):
        text += (f"\njobs without a partner: A {comparison.unmatched['a'] or '(none)'}, "
                 f"B {comparison.unmatched['b'] or '(none)'}\n")
    return text
