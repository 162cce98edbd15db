"""What code produced a stage's output: the source of every module in the import closure of its producers.

A stage's cache key (``pipeline.storage.keys.stage_key``) hashes, besides its config and inputs,
``source_fingerprint(producers)``: the producers are the modules named by every ``_target_`` in
the stage's config subtree (the scenario, the sensor, a filter, its model set, a study adapter,
a user's own class in a package outside this project) plus the modules the runner itself uses to
make and encode the table. From those it follows imports, statically:

- every ``import a.b`` / ``from a import b`` / ``from . import c`` anywhere in a module's source
  (function-level imports too), to the module they name;
- a module whose file is not in the standard library and not inside an installed
  distribution's site-packages folder (this project's code, a user's package on ``sys.path``, an
  editable install) is hashed by content and followed;
- a module from site-packages is not read: its distribution's name and version are hashed
  instead (so upgrading it, or installing a new version of a user package, recomputes);
- numpy's and scipy's versions are always in (the numbers depend on them even where no module
  of the closure imports them by name).

So editing any line of a filter, of a helper it imports, or of a user's module named by
``_target_`` changes the key and the stage recomputes; editing the recording or the report does
not. Parsing is cached per file by (size, mtime), so a run pays for it once per file, and its
result (the imports) is kept beside the file's bytecode under its content hash
(``__pycache__/<name>.imports.json``), as is the map of installed distributions under a hash of
what is installed: a fresh process reads them instead of parsing the 46 files of an ADS-B job's
closure (0.69-0.83 s) and reading every distribution's metadata (0.20-0.30 s).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import json
import importlib.metadata
import importlib.util
import os
import site
import sys
import sysconfig
from pathlib import Path
from typing import Any, Iterable

ALWAYS_VERSIONED = ("numpy", "scipy")


def targets_in(node: Any) -> list[str]:
    """Every ``_target_`` string in a resolved config subtree (mappings and lists, any depth)."""
    found: list[str] = []
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "_target_" and isinstance(value, str):
                found.append(value)
            else:
                found += targets_in(value)
    elif isinstance(node, (list, tuple)):
        for value in node:
            found += targets_in(value)
    return found


def module_of(target: str) -> str | None:
    """The longest importable module prefix of a dotted ``_target_`` ('filters.imm.FSIMM' -> 'filters.imm')."""
    parts = target.split(".")
    for end in range(len(parts), 0, -1):
        name = ".".join(parts[:end])
        if _spec(name) is not None:
            return name
    return None


@functools.cache
def _external_roots() -> tuple[str, ...]:
    """Folders whose modules are identified by their distribution's version, not read."""
    paths = {sysconfig.get_paths()[k] for k in ("stdlib", "platstdlib", "purelib", "platlib")}
    paths.update(site.getsitepackages() if hasattr(site, "getsitepackages") else [])
    user = site.getusersitepackages() if hasattr(site, "getusersitepackages") else None
    if isinstance(user, str):
        paths.add(user)
    return tuple(sorted(os.path.realpath(p) + os.sep for p in paths if p))


def _spec(name: str):
    try:
        return importlib.util.find_spec(name)
    except (ImportError, ValueError, AttributeError):
        return None


@functools.cache
def _location(name: str) -> tuple[str | None, bool, bool]:
    """(real path of the module's file or None, is a package, is external). A module's location
    does not move within a process, so this is cached; its content is re-read when it changes."""
    spec = _spec(name)
    if spec is None or not spec.has_location or spec.origin is None:
        return None, False, False
    real = os.path.realpath(spec.origin)
    external = real.startswith(_external_roots()) or not real.endswith(".py")
    return real, spec.submodule_search_locations is not None, external


@functools.cache
def _distributions() -> dict[str, list[str]]:
    """Top-level import name -> the distributions that install it
    (``importlib.metadata.packages_distributions``: 0.29 s, as it reads the metadata and file list
    of every installed distribution), kept beside this module's bytecode under a hash of what is
    installed: the names of the ``*.dist-info`` / ``*.egg-info`` folders on ``sys.path``, which
    carry each distribution's version, so installing, upgrading or removing one computes it anew."""
    installed = _installed()
    kept = _kept_path(__file__, ".distributions.json")
    record = _read_record(kept)
    if record is not None and record.get("installed") == installed:
        try:
            return {str(top): [str(d) for d in dists] for top, dists in record["distributions"].items()}
        except (AttributeError, TypeError):
            pass
    found = importlib.metadata.packages_distributions()
    _write_record(kept, {"format": RECORD_FORMAT, "installed": installed, "distributions": found})
    return found


def _installed() -> str:
    """sha256 of the distribution folders' names on ``sys.path`` (a listing of each folder: ~1 ms)."""
    names = []
    for entry in sys.path:
        try:
            with os.scandir(entry or ".") as listing:
                names += [f"{entry}/{e.name}" for e in listing if e.name.endswith((".dist-info", ".egg-info"))]
        except OSError:                   # a zip, a missing folder
            names.append(f"{entry}:unlisted")
    return hashlib.sha256("\n".join(sorted(names)).encode()).hexdigest()


@functools.cache
def _version_of(top_level: str) -> str:
    """Cached per process (reading a distribution's metadata scans sys.path, a few ms each, and every
    stage key asks for several): a process computes with the versions it imported at start, so an
    upgrade during a long sweep reaches the next process, and with it the next key."""
    names = _distributions().get(top_level) or [top_level]
    versions = []
    for dist in sorted(set(names)):
        try:
            versions.append(f"{dist}=={importlib.metadata.version(dist)}")
        except importlib.metadata.PackageNotFoundError:
            versions.append(f"{dist}==?")
    return ",".join(versions)


RECORD_FORMAT = 1       # of the kept records; bump when _imports_in changes what it finds


@functools.cache
def _parsed(path: str, size: int, mtime_ns: int) -> tuple[str, tuple[tuple[str, int], ...]]:
    """(sha256 of the file, the imports it makes as (name, relative level)): those kept for this
    very content if there are (a missing, unreadable or other content's record is not trusted,
    only replaced), else parsed and kept."""
    source = Path(path).read_bytes()
    digest = hashlib.sha256(source).hexdigest()
    kept = _kept_path(path, ".imports.json")
    record = _read_record(kept)
    if record is not None and record.get("sha256") == digest:
        try:
            return digest, tuple((str(name), int(level)) for name, level in record["imports"])
        except (KeyError, TypeError, ValueError):
            pass
    imports = _imports_in(source, path)
    _write_record(kept, {"format": RECORD_FORMAT, "sha256": digest, "imports": imports})
    return digest, imports


def _imports_in(source: bytes, path: str) -> tuple[tuple[str, int], ...]:
    imports: list[tuple[str, int]] = []
    try:
        tree = ast.parse(source, filename=path)
    except SyntaxError:                   # the import itself will fail with the real message
        tree = ast.Module(body=[], type_ignores=[])
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            imports += [(alias.name, 0) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            imports.append((base, node.level))
            # 'from pkg import mod' may name submodules: try each as a module too
            imports += [(f"{base}.{alias.name}" if base else alias.name, node.level)
                        for alias in node.names if alias.name != "*"]
    return tuple(imports)


def _kept_path(path: str, suffix: str) -> Path | None:
    """Where a record about a source file is kept: beside its bytecode
    (``importlib.util.cache_from_source``, so ``sys.pycache_prefix`` is followed), None where Python
    names no bytecode file. Kept even under PYTHONDONTWRITEBYTECODE (set in many containers, and on
    this project's machine), as numba keeps its compiled kernels there: it is the pipeline's cache,
    not Python's bytecode."""
    try:
        return Path(importlib.util.cache_from_source(path)).with_suffix(suffix)
    except (NotImplementedError, ValueError):
        return None


def _read_record(kept: Path | None) -> dict | None:
    if kept is None:
        return None
    try:
        record = json.loads(kept.read_bytes())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and record.get("format") == RECORD_FORMAT else None


def _write_record(kept: Path | None, record: dict) -> None:
    """Atomically (``store.atomic_write_bytes``: a reader sees the old file or the new one); where
    the folder cannot be written the next process computes it again, as before."""
    from pipeline.errors import StorageError
    from pipeline.storage.store import atomic_write_bytes
    if kept is None:
        return
    try:
        atomic_write_bytes(json.dumps(record).encode(), kept)
    except StorageError:
        pass


def _resolve(name: str, level: int, importer: str, is_package: bool) -> str:
    if level == 0:
        return name
    package = importer if is_package else importer.rpartition(".")[0]
    for _ in range(level - 1):
        package = package.rpartition(".")[0]
    return f"{package}.{name}" if name else package


def _closure(roots: Iterable[str], paths: dict[str, str] | None = None) -> tuple[dict[str, str], set[str]]:
    """(module -> content hash for the followed modules, external top-level packages seen); with
    ``paths``, each followed module's real file path is put there too."""
    hashed: dict[str, str] = {}
    external: set[str] = set()
    stack = [r for r in roots if r]
    seen: set[str] = set()
    while stack:
        name = stack.pop()
        if name in seen:
            continue
        seen.add(name)
        top = name.partition(".")[0]
        if top in sys.stdlib_module_names or top == "__future__":
            continue
        if top != name and _location(top)[2]:
            external.add(top)             # a submodule of an installed library: not imported to look
            continue
        if "." in name:
            parent_real, parent_is_package, _ = _location(name.rpartition(".")[0])
            if parent_real is not None and not parent_is_package:
                continue                  # 'from module import function': an attribute; looking it up
                                          # would import the module (and a lazy import's numba with it)
        # None: an attribute ('from pkg import function'), not a module, or a namespace package
        real, is_package, is_external = _location(name)
        if real is None:
            continue
        if is_external:
            external.add(top)
            continue
        stat = os.stat(real)
        digest, imports = _parsed(real, stat.st_size, stat.st_mtime_ns)
        hashed[name] = digest
        if paths is not None:
            paths[name] = real
        if "." in name:                   # importing a.b runs a/__init__.py first
            stack.append(name.rpartition(".")[0])
        for imported, level in imports:
            stack.append(_resolve(imported, level, name, is_package))
    return hashed, external


def source_fingerprint(modules: Iterable[str]) -> str:
    """Hash of the import closure of ``modules`` (module names): the followed modules' sources and
    the versions of the installed distributions they import, plus numpy's and scipy's."""
    hashed, external = _closure(sorted(set(modules)))
    digest = hashlib.sha256()
    for name in sorted(hashed):
        digest.update(f"{name}:{hashed[name]}\n".encode())
    for top in sorted(external | set(ALWAYS_VERSIONED)):
        digest.update(f"{top}:{_version_of(top)}\n".encode())
    return digest.hexdigest()[:16]


def closure_modules(modules: Iterable[str]) -> list[str]:
    """The followed (hashed) modules of the closure, for inspection and tests."""
    return sorted(_closure(sorted(set(modules)))[0])


def closure_files(modules: Iterable[str]) -> dict[str, tuple[str, str]]:
    """``module -> (real path of its file, sha256 of its content)`` for every followed module of the
    closure of ``modules`` (pipeline.run.provenance: which user code outside git made a run)."""
    paths: dict[str, str] = {}
    hashed, _ = _closure(sorted(set(modules)), paths)
    return {name: (paths[name], hashed[name]) for name in sorted(hashed)}


def producers(config: Any, *modules: str) -> list[str]:
    """The modules behind a stage: those named by ``_target_`` in its config subtree, plus ``modules``."""
    found = [module_of(t) for t in targets_in(config)]
    return sorted({m for m in found if m} | set(modules))
