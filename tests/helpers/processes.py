"""The one way a test starts a project command in a child process.

Use a child process only where the claim is about one (the command line, exit codes, a package
outside the project, kills, launchers); in-process composition (``tests.conftest.composed``) is
cheaper everywhere else. The child imports this checkout (``PYTHONPATH`` = the project root first,
then ``paths``), gets Hydra's one-paragraph errors (``HYDRA_FULL_ERROR=0``) and never the progress
bars (``MTT_PROGRESS=off``) unless ``env`` says otherwise.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Mapping, Sequence

ROOT = Path(__file__).resolve().parents[2]


def child_env(paths: Sequence[Path | str] = (), env: Mapping[str, str] | None = None) -> dict[str, str]:
    """os.environ with the checkout (then ``paths``) on the import path; ``env`` overrides."""
    return {**os.environ, "HYDRA_FULL_ERROR": "0", "MTT_PROGRESS": "off",
            "PYTHONPATH": os.pathsep.join([str(ROOT), *map(str, paths)]), **(env or {})}


def run_module(module: str, *args: str, cwd: Path | str = ROOT, paths: Sequence[Path | str] = (),
               env: Mapping[str, str] | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    """``python -m module args...`` in ``cwd``, output captured as text."""
    return subprocess.run([sys.executable, "-m", module, *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env=child_env(paths, env))


def run_pipeline(*args: str, artifacts: Path | str, cwd: Path | str | None = None, **kwargs) -> subprocess.CompletedProcess:
    """``python -m pipeline paths.artifacts=<artifacts> args...`` (cwd: ``artifacts`` unless given)."""
    return run_module("pipeline", f"paths.artifacts={artifacts}", *args, cwd=cwd or artifacts, **kwargs)
