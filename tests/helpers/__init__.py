"""What several test files share (import these, never another test module or conftest.py;
tests/test_layout.py holds to it): ``processes`` starts the project's commands in a child process
the one way the tests do; ``config`` composes the configuration in process and ``runs`` runs it;
``filter_inputs`` and ``bias_reports`` build filter inputs without the pipeline; ``assertions``,
``rrd_reading`` and ``recording_checks`` check tables and recordings; ``report_targets`` and
``artifacts_tree`` build a report's and a query's inputs; ``extras`` skips a test of a missing
optional extra; ``tiers`` holds the two test tiers' pytest hooks."""
