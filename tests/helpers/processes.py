"""The one way a test starts a project command in a child process.

Use a child process only where the claim is about one (the command line, exit codes, a package
outside the project, kills, launchers, a fresh interpreter's imports or memory); in-process runs
(``tests.helpers.runs``) are cheaper everywhere else. The child imports this checkout
(``PYTHONPATH`` = the project root first, then ``paths``), gets Hydra's one-paragraph errors
(``HYDRA_FULL_ERROR=0``) and never the progress bars (``MTT_PROGRESS=off``) unless ``env`` says
otherwise; ``env`` maps a name to None to leave that variable out.

``run_*`` wait for the child (output captured as text unless ``capture_output=False``; other
keywords go to ``subprocess.run``, e.g. ``check``, ``preexec_fn``); ``start_*`` return the
``Popen`` of a child a test stops or kills itself (keywords go to ``subprocess.Popen``).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Mapping, Sequence

ROOT = Path(__file__).resolve().parents[2]


def child_env(paths: Sequence[Path | str] = (), env: Mapping[str, str | None] | None = None) -> dict[str, str]:
    """os.environ with the checkout (then ``paths``) on the import path; ``env`` overrides (None: unset)."""
    merged = {**os.environ, "HYDRA_FULL_ERROR": "0", "MTT_PROGRESS": "off",
              "PYTHONPATH": os.pathsep.join([str(ROOT), *map(str, paths)]), **(env or {})}
    return {k: v for k, v in merged.items() if v is not None}


def run_command(argv: Sequence[str], *, cwd: Path | str = ROOT, paths: Sequence[Path | str] = (),
                env: Mapping[str, str | None] | None = None, timeout: float | None = 300,
                **kwargs) -> subprocess.CompletedProcess:
    """``argv`` (a project command, e.g. through ``bash -c``) in ``cwd`` with ``child_env``."""
    kwargs.setdefault("capture_output", True)
    kwargs.setdefault("text", True)
    return subprocess.run(list(argv), cwd=cwd, timeout=timeout, env=child_env(paths, env), **kwargs)


def start_command(argv: Sequence[str], *, cwd: Path | str = ROOT, paths: Sequence[Path | str] = (),
                  env: Mapping[str, str | None] | None = None, **kwargs) -> subprocess.Popen:
    """``argv`` started in ``cwd`` with ``child_env``; the caller waits for it, stops or kills it."""
    return subprocess.Popen(list(argv), cwd=cwd, env=child_env(paths, env), **kwargs)


def run_module(module: str, *args: str, **kwargs) -> subprocess.CompletedProcess:
    """``python -m module args...`` (keywords: ``run_command``'s)."""
    return run_command([sys.executable, "-m", module, *args], **kwargs)


def start_module(module: str, *args: str, **kwargs) -> subprocess.Popen:
    """``python -m module args...`` started (keywords: ``start_command``'s)."""
    return start_command([sys.executable, "-m", module, *args], **kwargs)


def run_code(code: str, *args: str, **kwargs) -> subprocess.CompletedProcess:
    """``python -c code args...``: a fresh interpreter running project code (keywords: ``run_command``'s)."""
    return run_command([sys.executable, "-c", code, *args], **kwargs)


def start_code(code: str, *args: str, **kwargs) -> subprocess.Popen:
    """``python -c code args...`` started (keywords: ``start_command``'s)."""
    return start_command([sys.executable, "-c", code, *args], **kwargs)


def start_script(script: Path | str, *args: str, **kwargs) -> subprocess.Popen:
    """``python script args...`` started (keywords: ``start_command``'s)."""
    return start_command([sys.executable, str(script), *args], **kwargs)


def pipeline_args(args: Sequence[str], artifacts: Path | str) -> list[str]:
    """``python -m pipeline``'s arguments: the flags (``-m``, ``--cfg``, ...) first, then
    ``paths.artifacts=<artifacts>``, then the overrides."""
    flags = [a for a in args if a.startswith("-")]
    return [*flags, f"paths.artifacts={artifacts}", *(a for a in args if not a.startswith("-"))]


def run_pipeline(*args: str, artifacts: Path | str, cwd: Path | str | None = None, timeout: float | None = 120,
                 **kwargs) -> subprocess.CompletedProcess:
    """``python -m pipeline [flags] paths.artifacts=<artifacts> overrides...`` (cwd: ``artifacts``
    unless given)."""
    return run_module("pipeline", *pipeline_args(args, artifacts), cwd=cwd or artifacts, timeout=timeout, **kwargs)


def start_pipeline(*args: str, artifacts: Path | str, cwd: Path | str | None = None, **kwargs) -> subprocess.Popen:
    """``run_pipeline``'s command started (keywords: ``start_command``'s)."""
    return start_module("pipeline", *pipeline_args(args, artifacts), cwd=cwd or artifacts, **kwargs)
