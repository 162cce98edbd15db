"""Headless screenshot of a recording in the Rerun viewer, to look at what users will see.

    python tools/screenshot.py artifacts/runs/<experiment>/<time>/recording.rrd shot.png [--time 125] [--size 1600x900]

Needs a Vulkan software renderer (Debian: apt-get install mesa-vulkan-drivers libvulkan1).
The CLI's own `rerun --screenshot-to` shoots before a finished .rrd has loaded (empty views),
so this starts the viewer headless, opens the file through ViewerClient, waits for loading to
finish, pauses the playback with the time cursor at ``--time`` (default: the end of the
recording's ``time`` timeline, so that the same file always gives the same picture), then saves
the screenshot. Not a CI gate.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path


def viewer_binary() -> str:
    import rerun_cli
    return str(Path(rerun_cli.__file__).parent / "rerun")


def shot_time(timelines, requested: float | None, timeline: str = "time") -> float | None:
    """The time cursor [s] of the screenshot: ``requested``, else the end of ``timeline`` (a duration
    timeline, ends in ns) among the viewer's ``timelines`` (objects with name, start, end); None when
    neither is known (the viewer's own cursor is kept)."""
    if requested is not None:
        return float(requested)
    for t in timelines:
        if t.name == timeline and t.end is not None:
            return t.end / 1e9
    return None


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("rrd", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--time", type=float, default=None,
                        help="time cursor [s] on the 'time' timeline (default: the end of the recording)")
    parser.add_argument("--size", default="1600x900")
    parser.add_argument("--port", type=int, default=9877)
    args = parser.parse_args()
    from rerun.experimental import ViewerClient

    env = dict(os.environ, WGPU_BACKEND="vulkan", RERUN_APP_ONLY="true")
    viewer = subprocess.Popen([viewer_binary(), "--bind", "127.0.0.1", "--port", str(args.port), "--headless",
                               "--hide-welcome-screen", "--window-size", args.size], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        client = None
        for _ in range(150):
            try:
                client = ViewerClient.connect(f"rerun+http://127.0.0.1:{args.port}/proxy")
                client.get_state()
                break
            except Exception:
                client = None
                time.sleep(0.2)
        if client is None:
            print("the headless viewer did not start (is a Vulkan driver installed?)", file=sys.stderr)
            return 1
        client.open(str(args.rrd.resolve()))
        for _ in range(150):
            state = client.get_state()
            if not state.loading and state.recordings and state.recordings[0].timelines:
                break
            time.sleep(0.2)
        time.sleep(1.0)
        state = client.get_state()
        at = shot_time(state.recordings[0].timelines if state.recordings else [], args.time)
        if at is not None:
            client.set_time("time", duration=at, play_state="paused")
        else:
            try:
                client.set_time(play_state="paused")
            except ConnectionError:       # no timeline at all (static data only): nothing plays
                pass
        time.sleep(0.5)
        args.png.parent.mkdir(parents=True, exist_ok=True)
        client.save_screenshot(str(args.png.resolve()))   # the first paint can be incomplete
        time.sleep(1.0)
        client.save_screenshot(str(args.png.resolve()))
        print(f"time cursor: {'the viewer default' if at is None else f't = {at:g} s'} (paused)")
        for view in client.get_state().views:
            problems = [r.summary for r in view.reports]
            print(f"{view.view_class:>16}  {view.name!r}{'  ' + str(problems) if problems else ''}")
        return 0
    finally:
        viewer.terminate()
        viewer.wait(10)


if __name__ == "__main__":
    sys.exit(main())
