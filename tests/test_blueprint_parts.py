"""pipeline.views.blueprints: the pieces that make the recordings read at a glance (issue 19)."""

from __future__ import annotations

import numpy as np

from pipeline.views.blueprints import (_key_positions, fit_title, fit_titles, path_segments, quiet_corner,
                                      title_chars)


def test_titles_fit_or_fall_back():
    assert fit_title(1600, "a long and complete title", "short") == "a long and complete title"
    assert fit_title(150, "a long and complete title", "short") == "short"
    room = title_chars(300)
    assert len(fit_title(300, "x" * (room + 1), "x" * room)) == room
    # a row of views gets one level: all full where all fit, else all shorter
    assert fit_titles(300, [["A · run 0", "A"], ["B" * room + " · run 0", "B"]]) == ["A", "B"]
    assert fit_titles(1600, [["A · run 0", "A"], ["B · run 0", "B"]]) == ["A · run 0", "B · run 0"]


def test_path_segments_join_consecutive_valid_rows():
    pos = np.array([[0.0, 0.0], [1.0, 0.0], [np.nan, np.nan], [3.0, 0.0], [4.0, 1.0]])
    rows, counts, segments = path_segments(pos)
    assert rows.tolist() == [1, 4] and counts.tolist() == [1, 1]
    assert segments.tolist() == [[[0.0, 0.0], [1.0, 0.0]], [[3.0, 0.0], [4.0, 1.0]]]
    # several objects per row (e.g. every target of a run), with a mask
    many = np.stack([pos, pos + 10.0], axis=1)                        # (5, 2, 2)
    ok = np.ones((5, 2), dtype=bool)
    ok[1, 1] = False
    rows, counts, segments = path_segments(many, ok)
    assert rows.tolist() == [1, 4] and counts.tolist() == [1, 2] and segments.shape == (3, 2, 2)


def test_key_entries_do_not_overlap():
    labels = ["KF+MGEKF paper-like", "EKF", "KF+MGEKF consistent", "x"]
    x, total = _key_positions(labels)
    for i in range(len(labels) - 1):                                  # room for both half labels between them
        assert x[i + 1] - x[i] >= (len(labels[i]) + len(labels[i + 1])) / 2
    assert total >= x[-1] + len(labels[-1]) / 2


def test_quiet_corner_avoids_the_curves():
    t = np.linspace(0.0, 1.0, 200)
    falling = (t, 1.0 - t)                        # high on the left, low on the right: right top is free
    assert quiet_corner([falling], 2) == "RightTop"
    rising = (t, t)
    assert quiet_corner([rising], 2) == "LeftTop"
    assert quiet_corner([], 3) == "RightTop"
