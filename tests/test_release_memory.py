"""pipeline.memory.release_freed_memory: what a finished sweep job freed goes back to the operating
system before the next job of a one-process sweep, instead of staying in the process's heap."""

from __future__ import annotations

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import psutil
    from pipeline.memory import release_freed_memory

    process = psutil.Process()
    blocks = [bytes(1000) + bytes([i % 256]) for i in range(350_000)]   # ~350 MB of small malloc blocks
    survivor = bytes(2000)           # pins the heap's top: glibc cannot give back the freed blocks by itself
    del blocks
    before = process.memory_info().rss
    trimmed = release_freed_memory()
    after = process.memory_info().rss
    print(trimmed, before >> 20, after >> 20)
""")


def test_the_heap_a_job_freed_is_returned_to_the_system():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, check=True).stdout.split()
    trimmed, before_mb, after_mb = out[0] == "True", int(out[1]), int(out[2])
    assert trimmed, "glibc's malloc_trim did not run (this project's machines use glibc)"
    assert before_mb - after_mb > 200, f"RSS {before_mb} MB before, {after_mb} MB after the release"
