"""Write a runnable empty study in a package of your own: ``python tools/new_study.py NAME [--into DIR]``.

The study is the smallest one the pipeline runs end to end, a starting point to fill in
(docs/your-own-study.md): a planar constant-velocity target with white acceleration noise
(``scenario.py``), a sensor of its noisy positions (``sensor.py``, kind ``position_xy``), the config
files of the five groups an experiment composes, and one reproduction target. Every filter that takes
positions runs on it unchanged; the experiment starts with the project's KF-CV (matched to the scenario) and IMM-CV/CT. It lives
outside the project, like your own filter (docs/your-own-filter.md): the folder ``DIR/NAME`` is a
package and ``DIR/NAME/conf`` joins Hydra's search path, so nothing in the project changes.

The command prints the line that runs it (from DIR):

    python -m pipeline 'hydra.searchpath=[file://NAME/conf]' 'plugins.packages=[NAME]' experiment=NAME

Refused, before anything is written: a NAME that is not a Python identifier (it names the package,
the experiment and the config files), one that would shadow a package already importable (``numpy``,
``pipeline``), and a target folder that already exists (nothing of yours is overwritten).
"""

from __future__ import annotations

import argparse
import importlib.util
import keyword
import re
import sys
from pathlib import Path

NAME_PATTERN = re.compile(r"[a-z][a-z0-9_]{0,39}")

SCENARIO = '''"""{name}: the truth. A planar target at constant velocity driven by white acceleration noise.

Replace the motion model with your study's; keep the contract: ``generate(runs, seed) -> Truth`` with
``state`` (runs, scans, targets, n) in the order of ``state_names``, run r's randomness from
``run_generators(seed, "scenario", runs)`` (so run r is the same whatever the number of runs).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from filters.models import acceleration_input_gain, constant_velocity_transition
from pipeline.data import Truth
from pipeline.run.checks import non_negative, positive
from pipeline.run.seeding import run_generators


class ConstantVelocityScenario:
    """x_k = F x_(k-1) + Gamma w_k, w_k ~ N(0, acceleration_std^2 I2), k = 1..steps.

    Parameters
    ----------
    initial_state : (x, vx, y, vy) at k = 0 [m, m/s]
    steps : last scan index (steps + 1 scans)
    dt : scan period [s]
    acceleration_std : std of the white acceleration w_k [m/s^2]
    """

    def __init__(self, initial_state: Sequence[float], steps: int = 100, dt: float = 1.0,
                 acceleration_std: float = 1.0) -> None:
        if len(initial_state) != 4:
            raise ValueError(f"initial_state: {{list(initial_state)}} must be [x, vx, y, vy]")
        if int(steps) < 2:
            raise ValueError(f"steps: {{steps}} must be >= 2")
        positive("dt", dt, "s")
        non_negative("acceleration_std", acceleration_std, "m/s^2")
        self.initial_state = np.asarray(initial_state, dtype=float)
        self.steps, self.dt, self.acceleration_std = int(steps), float(dt), float(acceleration_std)

    def generate(self, runs: int, seed: int) -> Truth:
        F, G = constant_velocity_transition(self.dt), acceleration_input_gain(self.dt)
        scans = self.steps + 1
        noise = np.stack([g.standard_normal((scans, 2)) for g in run_generators(seed, "scenario", runs)])
        x = np.empty((runs, scans, 4))
        x[:, 0] = self.initial_state
        for k in range(1, scans):                     # a loop over scans, every run at once
            x[:, k] = x[:, k - 1] @ F.T + self.acceleration_std * noise[:, k] @ G.T
        return Truth(np.arange(scans) * self.dt, x[:, :, None, :], ("x", "vx", "y", "vy"), {{}})
'''

SENSOR = '''"""{name}: the measurements. The target's position with white Gaussian noise, every scan.

Replace it with your sensor; keep the contract: ``measure(truth, seed) -> Detections`` and
``produces``, a kind of ``filters.base.MEASUREMENT_KINDS`` (the filters that take it run unchanged).
"""

from __future__ import annotations

import numpy as np

from pipeline.data import Detections, Truth
from pipeline.run.checks import positive
from pipeline.run.seeding import run_generators


class NoisyPositions:
    """z_k = (x, y) + v_k, v_k ~ N(0, noise_std^2 I2)."""

    produces = "position_xy"

    def __init__(self, noise_std: float = 20.0) -> None:
        positive("noise_std", noise_std, "m")
        self.noise_std = float(noise_std)

    def measure(self, truth: Truth, seed: int) -> Detections:
        runs, scans, targets, _ = truth.state.shape
        index = [truth.state_names.index("x"), truth.state_names.index("y")]
        noise = np.stack([g.standard_normal((scans, targets, 2)) for g in run_generators(seed, "measure", runs)])
        covariance = np.broadcast_to(self.noise_std**2 * np.eye(2), (runs, scans, targets, 2, 2)).copy()
        return Detections(
            time=truth.time, sensor=np.zeros(scans, dtype=int), z=truth.state[..., index] + self.noise_std * noise,
            noise_covariance=covariance, target=np.broadcast_to(np.arange(targets), (runs, scans, targets)).copy(),
            detected=np.ones((runs, scans, targets), dtype=bool), measurement_names=("x", "y"),
        )
'''

FILES = {
    "__init__.py": '"""{name}: a study of my own (written by tools/new_study.py; docs/your-own-study.md)."""\n',
    "scenario.py": SCENARIO,
    "sensor.py": SENSOR,
    "conf/scenario/{name}.yaml": """\
_target_: {name}.scenario.ConstantVelocityScenario
initial_state: [0.0, 100.0, 0.0, 50.0]   # x, vx, y, vy [m, m/s]
steps: 100
dt: 1.0
acceleration_std: 1.0                    # [m/s^2]
""",
    "conf/sensors/{name}.yaml": """\
_target_: {name}.sensor.NoisyPositions
noise_std: 20.0                          # [m]
""",
    "conf/metrics/{name}.yaml": """\
# windows are inclusive step ranges; the paired comparisons are against reference_variant
reference_variant: kf
compute_reference: kf
windows:
  all: [2, 100]
""",
    "conf/report/{name}.yaml": """\
# `python -m pipeline.report <run> --check`: each target a query over the run's tables
# (`wide`: one row per window, one column per variant:series). Write your paper's claims here.
targets:
  kf_below_noise:
    target: "the matched KF-CV's position RMSE below the measurement noise (20 m)"
    paper: "a Kalman filter matched to the motion smooths white position noise"
    query: |
      SELECT 'KF-CV ' || CAST(ROUND("kf:position_rmse", 2) AS VARCHAR) || ' m' AS measured,
             "kf:position_rmse" < 20.0 AS pass
      FROM wide WHERE "window" = 'all'
""",
    "conf/experiment/{name}.yaml": """\
# @package _global_
# {name}: python -m pipeline 'hydra.searchpath=[file://{name}/conf]' 'plugins.packages=[{name}]' experiment={name}
defaults:
  - /scenario: {name}
  - /sensors: {name}
  - /filter@filters.kf: kalman_cv
  - /filter@filters.imm: imm_cv_ct
  - /metrics: {name}
  - /report@report: {name}
  - _self_

experiment_name: {name}
description: "{name}: a constant-velocity target, noisy positions; the matched KF-CV against IMM-CV/CT."
filters:
  kf:
    name: KF-CV matched
    acceleration_density: 1.0            # [m^2/s^3] = the scenario's acceleration_std^2 x dt: the matched filter
paper_runs: 100
smoke: ["scenario.steps=20"]
""",
}


class ScaffoldError(ValueError):
    """A name or folder the scaffold refuses (one paragraph, nothing written)."""


def check(name: str, into: Path) -> Path:
    if not NAME_PATTERN.fullmatch(name) or keyword.iskeyword(name):
        raise ScaffoldError(f"NAME: {name!r} is not allowed; the study's name is its package, experiment and "
                            f"config file names: 1-40 lower-case letters, digits or '_', starting with a letter, "
                            f"not a Python keyword (e.g. my_study).")
    target = into / name
    if target.exists():
        raise ScaffoldError(f"--into: {target} already exists; the scaffold writes a new folder only and "
                            f"overwrites nothing: choose another NAME or folder.")
    spec = importlib.util.find_spec(name)
    if spec is not None:
        where = spec.origin or ", ".join(spec.submodule_search_locations or [])
        raise ScaffoldError(f"NAME: {name!r} is already an importable package ({where}); a study package of "
                            f"that name would shadow it or be shadowed: choose another name.")
    return target


def write(name: str, into: Path) -> list[Path]:
    """Write the study's package ``into/name`` (see the module's docstring); return the files written."""
    target = check(name, into)
    written = []
    for relative, template in FILES.items():
        path = target / relative.format(name=name)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(template.format(name=name))
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python tools/new_study.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("name", help="the study's name: its package, experiment and config files")
    parser.add_argument("--into", type=Path, default=Path("."), help="the folder to write the package in (default: .)")
    args = parser.parse_args(argv)
    try:
        files = write(args.name, args.into)
    except ScaffoldError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {len(files)} files under {args.into / args.name}; run it from {args.into}:")
    print(f"  python -m pipeline 'hydra.searchpath=[file://{args.name}/conf]' 'plugins.packages=[{args.name}]' "
          f"experiment={args.name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
