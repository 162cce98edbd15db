"""Which code made a run: its git state, the diff of a dirty checkout, user packages outside git.

Every job records, with no code of the user's (``status.json`` "provenance", the tables' metadata
``mtt.code`` and ``mtt.git``):

- **git** (of the checkout this project's code is imported from): the commit, the branch, whether
  the work tree is dirty and, when it is, the diff itself against the commit, untracked files
  included as new-file diffs, written once per run as ``<run>/provenance/code.diff`` (``git apply``
  takes it) with its SHA-256. Outside a git checkout (an installed wheel, a tarball) or without a
  ``git`` command this says so (``"git": {"available": false, "reason": ...}``) and the run goes on.
- **user packages**: every module of the job's import closure (``pipeline.storage.fingerprint``:
  what the config's ``_target_``s and the runner import) whose file lies outside that checkout,
  grouped by top-level package: its folder, a hash of its modules' contents and, where the folder
  is in a git checkout of its own, that checkout's commit and dirty flag.
- **the environment** is ``pipeline.run.environment`` (the lock's hash, the versions that matter);
  **the invocation**: the command line, the working directory, the overrides, the seed, the host
  and the user, the time.

``code`` hashes what decides the numbers' code (the commit, the diff's SHA-256, the user packages'
hashes): two runs with one ``code`` ran the same code. ``mtt-query runs`` lists it, ``mtt-query
diff`` compares two runs' provenance and diffs (pipeline.results.tracking).
"""

from __future__ import annotations

import datetime as dt
import functools
import getpass
import hashlib
import json
import os
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any, Iterable

from pipeline.storage import fingerprint
from pipeline.storage.store import atomic_write_bytes

ROOT = Path(__file__).resolve().parents[2]       # the folder this project's code is imported from
DIFF_FILE = Path("provenance") / "code.diff"
GIT_TIMEOUT_S = 20
UNTRACKED_MAX_BYTES = 1 << 20     # an untracked file larger than this is named in the diff, not copied
UNTRACKED_MAX_FILES = 500


class _GitUnavailable(Exception):
    pass


def _git(cwd: Path, *args: str, binary: bool = False) -> Any:
    """``git args`` in ``cwd``: its stdout (bytes with ``binary``); raises _GitUnavailable with why."""
    # GIT_OPTIONAL_LOCKS=0: `git status` must not take the index lock of a checkout the user works in
    env = {**os.environ, "GIT_OPTIONAL_LOCKS": "0", "LC_ALL": "C"}
    try:
        done = subprocess.run(["git", "-C", str(cwd), *args], capture_output=True, timeout=GIT_TIMEOUT_S, env=env)
    except FileNotFoundError:
        raise _GitUnavailable("no git command on PATH") from None
    except subprocess.TimeoutExpired:
        raise _GitUnavailable(f"git {args[0]} took over {GIT_TIMEOUT_S} s") from None
    if done.returncode != 0:
        said = done.stderr.decode(errors="replace").strip().splitlines()
        raise _GitUnavailable(said[-1] if said else f"git {args[0]} exited {done.returncode}")
    return done.stdout if binary else done.stdout.decode(errors="replace").strip()


def _new_file_diff(top: Path, name: str) -> bytes:
    """An untracked file as git's new-file diff (``git apply`` recreates it)."""
    path = top / name
    header = f"diff --git a/{name} b/{name}\nnew file mode 100644\n"
    try:
        size = path.stat().st_size
        data = path.read_bytes() if size <= UNTRACKED_MAX_BYTES else None
    except OSError as exc:
        return (header + f"# not read: {exc.strerror}\n").encode()
    if data is None:
        return (header + f"# {size} bytes, over {UNTRACKED_MAX_BYTES} bytes: not copied\n").encode()
    if b"\0" in data:
        digest = hashlib.sha256(data).hexdigest()
        return (header + f"Binary files /dev/null and b/{name} differ\n# sha256 {digest}\n").encode()
    lines = data.split(b"\n")
    if lines and lines[-1] == b"":
        lines, end = lines[:-1], b""
    else:
        end = b"\n\\ No newline at end of file"
    body = b"".join(b"+" + line + b"\n" for line in lines)
    return (header + f"--- /dev/null\n+++ b/{name}\n@@ -0,0 +1,{len(lines)} @@\n").encode() + body.rstrip(b"\n") \
        + end + b"\n"


def git_state(where: Path = ROOT) -> tuple[dict[str, Any], bytes]:
    """(the git record, the diff against HEAD with untracked files; empty when clean)."""
    try:
        top = Path(_git(where, "rev-parse", "--show-toplevel"))
    except _GitUnavailable as exc:
        return {"available": False, "reason": f"{where} is not in a git checkout ({exc})"}, b""
    try:
        commit = _git(top, "rev-parse", "HEAD")
    except _GitUnavailable:
        return {"available": False, "reason": f"{top} is a git checkout with no commit yet"}, b""
    branch = _git(top, "rev-parse", "--abbrev-ref", "HEAD")
    tracked = _git(top, "diff", "HEAD", "--binary", "--no-color", "--no-ext-diff", binary=True)
    # bytecode caches (and the fingerprint's import records beside them) are never source, ignored or not
    untracked = [n for n in _git(top, "ls-files", "--others", "--exclude-standard", "-z", binary=True)
                 .decode(errors="replace").split("\0") if n and "__pycache__/" not in f"/{n}" and
                 not n.endswith((".pyc", ".pyo"))]
    diff = tracked + b"".join(_new_file_diff(top, name) for name in untracked[:UNTRACKED_MAX_FILES])
    if len(untracked) > UNTRACKED_MAX_FILES:
        diff += f"# {len(untracked) - UNTRACKED_MAX_FILES} more untracked files not copied\n".encode()
    record = {"available": True, "root": str(top), "commit": commit, "branch": None if branch == "HEAD" else branch,
              "dirty": bool(diff), "diff_sha256": hashlib.sha256(diff).hexdigest() if diff else None,
              "untracked_files": len(untracked)}
    return record, diff


@functools.lru_cache(maxsize=64)
def _package_git(folder: str) -> dict[str, Any] | None:
    try:
        top = _git(Path(folder), "rev-parse", "--show-toplevel")
        commit = _git(Path(top), "rev-parse", "HEAD")
        dirty = bool(_git(Path(top), "status", "--porcelain", "--untracked-files=normal"))
    except _GitUnavailable:
        return None
    return {"root": top, "commit": commit, "dirty": dirty}


def user_packages(modules: Iterable[str], inside: Path | None) -> dict[str, dict[str, Any]]:
    """The import closure's modules outside ``inside`` (this checkout; None: none), by top-level package."""
    grouped: dict[str, list[tuple[str, str, str]]] = {}
    for name, (path, digest) in fingerprint.closure_files(modules).items():
        if inside is not None and Path(path).is_relative_to(inside):
            continue
        grouped.setdefault(name.partition(".")[0], []).append((name, path, digest))
    out: dict[str, dict[str, Any]] = {}
    for top, members in sorted(grouped.items()):
        digest = hashlib.sha256("".join(f"{n}:{d}\n" for n, _, d in sorted(members)).encode()).hexdigest()
        folder = os.path.commonpath([os.path.dirname(p) for _, p, _ in members])
        out[top] = {"path": folder, "modules": len(members), "sha256": digest, "git": _package_git(folder)}
    return out


def collect(resolved: dict, overrides: list[str], modules: Iterable[str]) -> tuple[dict[str, Any], bytes]:
    """(the provenance record of a job, its code diff). ``modules``: the job's producers (their
    import closure is searched for user packages)."""
    git, diff = git_state(ROOT)
    inside = Path(git["root"]).resolve() if git.get("available") else ROOT
    packages = user_packages(modules, inside)
    code = hashlib.sha256(json.dumps({"commit": git.get("commit"), "diff": git.get("diff_sha256"),
                                      "packages": {k: v["sha256"] for k, v in packages.items()}},
                                     sort_keys=True).encode()).hexdigest()[:16]
    try:
        user = getpass.getuser()
    except (KeyError, OSError):       # a container's uid without a passwd entry
        user = str(os.getuid()) if hasattr(os, "getuid") else None
    mc = resolved.get("mc") or {}
    record = {"code": code, "git": git, "user_packages": packages, "command": list(getattr(sys, "orig_argv", [sys.executable, *sys.argv])),
              "cwd": os.getcwd(), "overrides": list(overrides), "seed": mc.get("seed"),
              "host": socket.gethostname(), "user": user, "recorded_at": dt.datetime.now().isoformat(timespec="seconds")}
    return record, diff


def record(run_dir: Path, resolved: dict, overrides: list[str], modules: Iterable[str]) -> dict[str, Any]:
    """Collect the job's provenance and write its diff (when dirty) to ``run_dir/provenance/code.diff``."""
    provenance, diff = collect(resolved, overrides, modules)
    if diff:
        atomic_write_bytes(diff, run_dir / DIFF_FILE)
        provenance["git"]["diff_file"] = DIFF_FILE.as_posix()
    return provenance


def table_metadata(provenance: dict[str, Any]) -> dict[str, str]:
    """What every table of the run carries: the code hash and the git state in one line."""
    git = provenance["git"]
    line = (f"{git['commit']}{' dirty ' + git['diff_sha256'][:16] if git['dirty'] else ''}"
            if git.get("available") else "unavailable")
    return {"mtt.code": provenance["code"], "mtt.git": line}
