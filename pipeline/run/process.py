"""Which process runs a job, and whether it still does: a job killed (SIGKILL, the OOM killer, a
power cut) cannot write its own status, so ``status.json`` records its process and a reader
(``mtt-query list``) decides that a ``running`` job whose process is gone was ``interrupted``."""

from __future__ import annotations

import os
import socket
from pathlib import Path


def _boot_id() -> str | None:
    try:   # changes at every boot: a pid from before a reboot names nobody
        return Path("/proc/sys/kernel/random/boot_id").read_text().strip()
    except OSError:
        return None


def _start_ticks(pid: int) -> int | None:
    """The process's start time since boot in clock ticks (/proc/<pid>/stat field 22): with the pid,
    it names one process even after the pid is reused."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return int(stat.rsplit(")", 1)[1].split()[19])      # fields after the command name, which may hold spaces


def identity() -> dict:
    """This process: host, pid, boot id and start time (the last two on Linux only)."""
    pid = os.getpid()
    return {"host": socket.gethostname(), "pid": pid, "boot_id": _boot_id(), "start_ticks": _start_ticks(pid)}


def is_running(pid: int, start_ticks: int | None) -> bool:
    """Whether the process ``pid`` of this boot that started at ``start_ticks`` still runs: a reused pid
    is told apart by its start time (Linux); without one, by the pid alone."""
    if start_ticks is not None and _boot_id() is not None:
        return _start_ticks(pid) == start_ticks
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:       # alive, someone else's
        return True
    return True


def is_gone(process: dict | None) -> bool | None:
    """True if the recorded process has ended, False if it still runs, None if this machine cannot tell
    (another host, or no process recorded)."""
    if not isinstance(process, dict) or process.get("host") != socket.gethostname():
        return None
    pid = process.get("pid")
    if not isinstance(pid, int):
        return None
    if process.get("boot_id") and _boot_id() and process["boot_id"] != _boot_id():
        return True
    if process.get("start_ticks") is not None and _boot_id() is not None:
        return _start_ticks(pid) != process["start_ticks"]
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:       # alive, someone else's
        return False
    return False
