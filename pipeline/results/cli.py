"""``mtt-query``: the query commands (pipeline.results.query: list, tables, sql) and the tracking
commands (pipeline.results.tracking: runs, tag, note, rm; pipeline.results.diff: diff;
pipeline.results.gc: gc; pipeline.results.mlflow_export: export-mlflow) on one parser."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

from pipeline.results import diff, gc, mlflow_export, query, tracking


def main(argv: Sequence[str] | None = None) -> int:
    return query.main(argv, more=sys.modules[__name__])


def add_commands(sub: Any) -> None:
    """The tracking commands on ``mtt-query``'s parser (``sub``: its subparsers, argparse's
    ``add_subparsers()``)."""
    def with_format(p: argparse.ArgumentParser) -> None:
        p.add_argument("--root", type=Path, default=Path("artifacts"),
                       help="artifacts directory holding runs/ and multirun/ (default: artifacts)")
        p.add_argument("--format", choices=tracking.FORMATS, default="table", help="output format (default: table)")

    p = sub.add_parser("runs", help="runs with their commit, dirty flag, code, tags; filters; --only-changed",
                       description="One row per run/job: its status, commit, branch, dirty flag, code hash "
                                   "(pipeline.run.provenance), tags and note. Runs marked deleted are left out "
                                   "unless --include-deleted.")
    with_format(p)
    p.add_argument("--sweep", metavar="DIR", help="only the jobs of this sweep folder")
    p.add_argument("--experiment", metavar="NAME")
    p.add_argument("--status", metavar="STATUS", help="ok, failed, running, ...")
    p.add_argument("--tag", action="append", default=[], metavar="TAG", help="only runs with this tag (repeatable)")
    p.add_argument("--since", metavar="WHEN", help="started at or after (ISO date/time)")
    p.add_argument("--until", metavar="WHEN", help="started at or before (ISO date/time)")
    p.add_argument("--include-deleted", action="store_true")
    p.add_argument("--wide", action="store_true", help="table/markdown: every column, also those equal in every row")
    p.add_argument("--only-changed", action="store_true",
                   help="only the config keys and provenance fields that differ between the listed runs")
    p.add_argument("--metric", metavar="SERIES", help="add a column per variant: value ± half-width of this "
                                                      "summary series (e.g. position_rmse)")
    p.add_argument("--window", default="all", metavar="WINDOW", help="the metric's window (default: all)")

    p = sub.add_parser("diff", help="what differs between two runs or sweeps: config, code, metrics (paired)",
                       description="The config keys that differ, the code that differs (commit range, diff "
                                   "stat, dirty diffs), and for every variant and metric both have, B - A with "
                                   "its interval: paired by Monte Carlo run when both ran on the same truth and "
                                   "measurements (same scenario and measure keys, runs and seed), unpaired "
                                   "otherwise; each row says which. Two sweep folders: jobs paired by their "
                                   "swept values.")
    with_format(p)
    p.add_argument("a", metavar="RUN_A")
    p.add_argument("b", metavar="RUN_B")
    p.add_argument("--metric", action="append", default=[], metavar="SERIES", help="only these series (repeatable)")
    p.add_argument("--window", action="append", default=[], metavar="WINDOW", help="only these windows")
    p.add_argument("--patch", action="store_true", help="also print the code diffs that differ between the runs")
    p.add_argument("--all", action="store_true", help="every metric row, not only those that changed")

    for name, help_text in (("tag", "add tags to a run (or --remove them)"), ("note", "set a run's note"),
                            ("rm", "mark a run deleted (gc --apply removes it; --undo)")):
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--root", type=Path, default=Path("artifacts"))
        p.add_argument("run", metavar="RUN")
        if name == "tag":
            p.add_argument("names", nargs="+", metavar="TAG")
            p.add_argument("--remove", action="store_true")
        elif name == "note":
            p.add_argument("text", metavar="TEXT")
        else:
            p.add_argument("--undo", action="store_true")

    p = sub.add_parser("gc", help="remove unreferenced cache entries and deleted runs (dry run unless --apply)",
                       description="Lists (and with --apply removes) the cache entries no kept run refers to, "
                                   "and the folders of runs marked deleted, with the bytes freed. Entries newer "
                                   "than --grace seconds or than a running job's start are kept.")
    with_format(p)
    p.add_argument("--apply", action="store_true", help="remove them (default: only list)")
    p.add_argument("--grace", type=float, default=600.0, metavar="S",
                   help="keep cache entries modified in the last S seconds (default 600)")

    p = sub.add_parser("export-mlflow", help="write runs or a sweep into an MLflow SQLite store ([mlflow] extra)",
                       description="Writes each run (params flattened, summary metrics with their intervals, "
                                   "provenance as tags, links to the recording and report) into an MLflow "
                                   "tracking store, so `mlflow ui` compares them. Needs pip install -e '.[mlflow]'.")
    p.add_argument("--root", type=Path, default=Path("artifacts"))
    p.add_argument("runs", nargs="+", metavar="RUN_OR_SWEEP")
    p.add_argument("--store", required=True, metavar="URI_OR_FILE",
                   help="an sqlite:/// URI or a .db file (made if missing)")
    p.add_argument("--mlflow-experiment", default=None, metavar="NAME",
                   help="the MLflow experiment (default: each run's experiment name)")


COMMANDS = ("runs", "diff", "tag", "note", "rm", "gc", "export-mlflow")


def run_command(args: argparse.Namespace) -> int:
    root = Path(args.root)
    if args.command == "runs":
        runs = tracking.select(tracking.load_runs(root, args.sweep), experiment=args.experiment, status=args.status, tags=args.tag,
                      since=args.since, until=args.until, include_deleted=args.include_deleted)
        df = tracking.runs_table(runs, only_changed=args.only_changed, metric=args.metric, window=args.window)
        sys.stdout.write(tracking.emit(df, args.format, wide=args.wide))
    elif args.command == "diff":
        sys.stdout.write(diff.render(diff.compare(root, args.a, args.b, metrics=args.metric, windows=args.window,
                                                  everything=args.all), args.format, patch=args.patch))
    elif args.command == "tag":
        tags = tracking.tag(tracking.resolve_run(root, args.run), args.names, remove=args.remove)
        print(f"{args.run}: tags {', '.join(tags) or '(none)'}")
    elif args.command == "note":
        tracking.note(tracking.resolve_run(root, args.run), args.text)
        print(f"{args.run}: note set")
    elif args.command == "rm":
        run = tracking.resolve_run(root, args.run)
        tracking.mark_deleted(run, undo=args.undo)
        print(f"{args.run}: " + ("no longer marked deleted" if args.undo else
                                 "marked deleted (hidden from `runs`; `mtt-query gc --apply` removes its folder)"))
    elif args.command == "gc":
        plan = gc.plan(root, grace_s=args.grace)
        if args.apply:
            plan = gc.apply(plan)
        sys.stdout.write(gc.render(plan, args.format, applied=args.apply))
    elif args.command == "export-mlflow":
        written = mlflow_export.export(root, args.runs, args.store, experiment=args.mlflow_experiment)
        print(f"exported {len(written)} runs to {mlflow_export.store_uri(args.store)}"
              f" (mlflow ui --backend-store-uri {mlflow_export.store_uri(args.store)})")
    sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
