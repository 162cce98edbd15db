"""tools/screenshot.py: without --time the screenshot is taken at a defined time, the end of the
recording's ``time`` timeline (not wherever the viewer's playback happens to be), paused."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]


def _tool():
    spec = importlib.util.spec_from_file_location("screenshot_tool", ROOT / "tools" / "screenshot.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _timeline(name, start, end):
    return SimpleNamespace(name=name, time_type="duration", start=start, end=end)


def test_default_is_the_end_of_the_time_timeline():
    shot_time = _tool().shot_time
    timelines = [_timeline("step", 0, 200), _timeline("time", 0, 200_000_000_000)]
    assert shot_time(timelines, None) == 200.0


def test_requested_time_wins():
    shot_time = _tool().shot_time
    assert shot_time([_timeline("time", 0, 200_000_000_000)], 12.5) == 12.5
    assert shot_time([], 0.0) == 0.0


def test_no_time_timeline_keeps_the_viewer_cursor():
    shot_time = _tool().shot_time
    assert shot_time([_timeline("step", 0, 5)], None) is None
    assert shot_time([_timeline("time", None, None)], None) is None


def test_the_screenshot_is_taken_paused():
    text = (ROOT / "tools" / "screenshot.py").read_text()
    assert 'play_state="paused"' in text
