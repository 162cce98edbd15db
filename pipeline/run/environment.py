"""The software a run ran with: the lock it was meant to be installed from and the versions it got.

A result is only reproducible with the versions it was computed with. Every run's ``status.json``
carries :func:`environment` (and its tables' metadata ``mtt.lock`` and ``mtt.environment``): the
Python and platform, the SHA-256 of ``lock/ci.txt`` (the exact versions CI tested; ``lock/core.txt``
is its subset for the core), the installed version of every distribution the project requires
directly, and those that differ from the lock. ``lock/`` ships with the source tree; an install
without it (a wheel) says so instead of a hash.
"""

from __future__ import annotations

import functools
import hashlib
import platform
import re
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
LOCK = ROOT / "lock" / "ci.txt"
PROJECT = "mtt-experiments"
# the project's direct requirements (pyproject.toml [project] dependencies) when its metadata is missing
FALLBACK_REQUIREMENTS = ("numpy", "scipy", "polars", "pyarrow", "hydra-core", "omegaconf", "hydra-joblib-launcher",
                         "joblib", "cloudpickle", "pyyaml", "rerun-sdk", "matplotlib", "pymap3d", "tqdm", "numba",
                         "llvmlite")
_PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;#]+)\s*(?:;\s*([^#]+?))?\s*(?:#.*)?$")


def canonical(name: str) -> str:
    """PEP 503's normalised distribution name: ``PyYAML`` and ``pyyaml``, ``rerun_sdk`` and ``rerun-sdk`` agree."""
    return re.sub(r"[-_.]+", "-", name).lower()


def read_lock(path: Path = LOCK) -> dict[str, set[str]]:
    """``name -> the versions the lock pins`` (more than one where it forks by platform or Python:
    the lock is one universal resolution, and a marker picks the line)."""
    pins: dict[str, set[str]] = {}
    for line in path.read_text().splitlines():
        match = _PIN.match(line.strip())
        if match:
            pins.setdefault(canonical(match.group(1)), set()).add(match.group(2))
    return pins


def direct_requirements() -> tuple[str, ...]:
    """The distributions the project requires without an extra, from its installed metadata."""
    try:
        requires = metadata.requires(PROJECT) or []
    except metadata.PackageNotFoundError:
        return FALLBACK_REQUIREMENTS
    names = [canonical(re.split(r"[\s;<>=!~\[(]", r, maxsplit=1)[0]) for r in requires if "extra ==" not in r]
    return tuple(dict.fromkeys(names))


def installed_version(name: str) -> str | None:
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def differences(installed: dict[str, str | None], lock: dict[str, set[str]]) -> dict[str, dict[str, Any]]:
    """The distributions whose installed version is not one the lock pins (or that the lock lacks)."""
    out: dict[str, dict[str, Any]] = {}
    for name, version in installed.items():
        pinned = lock.get(canonical(name))
        if version is None or pinned is None or version not in pinned:
            out[name] = {"installed": version, "lock": None if pinned is None else " or ".join(sorted(pinned))}
    return out


@functools.lru_cache(maxsize=1)
def environment() -> dict[str, Any]:
    """This process's environment as a run records it (computed once per process: a sweep's jobs share it)."""
    installed = {name: installed_version(name) for name in direct_requirements()}
    record: dict[str, Any] = {
        "python": platform.python_version(), "implementation": sys.implementation.name,
        "platform": f"{platform.system()} {platform.machine()}",
        "project": installed_version(PROJECT) or "not installed",
        "distributions": installed,
    }
    if LOCK.is_file():
        data = LOCK.read_bytes()
        record["lock"] = {"file": LOCK.relative_to(ROOT).as_posix(), "sha256": hashlib.sha256(data).hexdigest()}
        record["differs_from_lock"] = differences(installed, read_lock(LOCK))
    else:
        record["lock"] = None      # an install without the source tree: nothing to compare with
        record["differs_from_lock"] = None
    record["hash"] = hashlib.sha256(repr(sorted((k, str(v)) for k, v in record.items())).encode()).hexdigest()[:16]
    return record


def table_metadata() -> dict[str, str]:
    """What every table of a run carries: the lock's hash and the environment record's hash."""
    env = environment()
    return {"mtt.lock": env["lock"]["sha256"][:16] if env["lock"] else "none", "mtt.environment": env["hash"]}


def drift(lock_path: Path = LOCK) -> list[tuple[str, str | None, str]]:
    """Every installed distribution whose version the lock does not pin: ``(name, locked, installed)``
    (``locked`` None: the lock does not know it). The project itself and pip's own tools are left out."""
    lock = read_lock(lock_path)
    skip = {canonical(PROJECT), "pip", "setuptools", "wheel"}
    rows = []
    for dist in metadata.distributions():
        name = canonical(dist.metadata["Name"] or "")
        if not name or name in skip:
            continue
        pinned = lock.get(name)
        if pinned is None or dist.version not in pinned:
            rows.append((name, None if pinned is None else " or ".join(sorted(pinned)), dist.version))
    return sorted(set(rows))


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline.run.environment [--check] [--lock FILE]``: this environment as a run records it;
    ``--check`` lists every installed distribution the lock does not pin at that version and exits 1
    if there is one (``.ci/run`` calls it when the unlocked install breaks)."""
    import argparse
    import json
    parser = argparse.ArgumentParser(prog="python -m pipeline.run.environment", description=main.__doc__)
    parser.add_argument("--check", action="store_true", help="compare every installed distribution with the lock")
    parser.add_argument("--lock", type=Path, default=LOCK, help=f"the lock to compare with (default {LOCK.relative_to(ROOT)})")
    args = parser.parse_args(argv)
    if not args.check:
        print(json.dumps(environment(), indent=2))
        return 0
    if not args.lock.is_file():
        print(f"error: --lock {args.lock}: no such file; the locks are in {ROOT / 'lock'}", file=sys.stderr)
        return 2
    rows = drift(args.lock)
    if not rows:
        print(f"every installed distribution is the version {args.lock} pins")
        return 0
    print(f"{len(rows)} installed distributions differ from {args.lock}:")
    for name, locked, installed in rows:
        print(f"  {name}: {'not in the lock' if locked is None else 'lock ' + locked}, installed {installed}")
    return 1


if __name__ == "__main__":
    sys.exit(main())
