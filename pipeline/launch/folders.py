"""Before any job: the folders a run or a sweep writes can be written.

A Hydra callback (conf/config.yaml ``hydra.callbacks.output_folders``), so it runs after Hydra has
composed the config and before it creates the run or sweep folder: ``paths.artifacts=/proc/x``, a
path under a file, a read-only or full disk give one paragraph and exit 2, not Hydra's traceback
from its own ``mkdir``. It also records that Hydra got that far (``COMPOSED``): an exit 1 before it
is Hydra refusing the command line (an unknown key, a missing config), which ``python -m pipeline``
then reports with the same exit code as every other input error, 2.

And it notes what the run folder held before Hydra made it (``BEFORE``): a single run refused before
any stage removes what this job made there, Hydra's ``.hydra/`` files and its log, and nothing else
(``remove_what_the_job_made``); a folder that was there before stays, with every file it held.
"""

from __future__ import annotations

import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.errors import cannot_write

COMPOSED = False      # set in this process once Hydra has composed the config and called the callbacks
HYDRA_FILES = (".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml")   # what Hydra saves in a job
# what a single run writes in its folder (besides the job's log): a folder that holds one of these and is not an
# earlier run's would have it replaced (tests/test_reliability_round3_config.py holds a run's folder to it)
RUN_FILES = frozenset({".hydra", "config.yaml", "status.json", "truth.parquet", "detections.parquet", "estimates",
                       "metrics.parquet", "per_run.parquet", "summary.parquet", "comparisons.parquet",
                       "resamples.parquet", "recording.rrd", "report.txt", "provenance"})


@dataclass(frozen=True)
class FolderBefore:
    """What a single run's folder was before Hydra made it: ``run_dir`` (absolute), ``made_from`` the
    outermost folder the job creates for it (``run_dir`` or one of its parents; None if ``run_dir``
    was there), and ``entries``, the relative paths it held (one level into ``.hydra/``)."""

    run_dir: Path
    made_from: Path | None
    entries: frozenset[str]


BEFORE: FolderBefore | None = None    # set by OutputFolders.on_run_start, before any folder is made


def folder_before(run_dir: Path) -> FolderBefore:
    """What ``run_dir`` holds now (``FolderBefore``)."""
    run_dir = Path(os.path.abspath(run_dir))
    if not os.path.lexists(run_dir):
        made_from = run_dir
        while not os.path.lexists(made_from.parent) and made_from.parent != made_from:
            made_from = made_from.parent
        return FolderBefore(run_dir, made_from, frozenset())
    entries: set[str] = set()
    if run_dir.is_dir():
        for p in run_dir.iterdir():
            entries.add(p.name)
            if p.name == ".hydra" and p.is_dir() and not p.is_symlink():
                entries.update(f".hydra/{q.name}" for q in p.iterdir())
    return FolderBefore(run_dir, None, frozenset(entries))


def remove_what_the_job_made(run_dir: Path, artifacts: Path, before: FolderBefore | None) -> None:
    """Remove what a single run refused before any stage left in ``run_dir``: Hydra's ``.hydra/``
    files and the job's ``*.log``, those not there before (``before``) and nothing else, then every
    folder the job made for it (``run_dir`` and its parents up to ``before.made_from``, never
    ``artifacts``) while it is empty. Without ``before`` (Hydra never called OutputFolders) nothing is
    removed: what the job made cannot be told from what was there."""
    run_dir = Path(os.path.abspath(run_dir))
    if before is None or before.run_dir != run_dir or not run_dir.is_dir() or run_dir.is_symlink():
        return
    made = [name for name in HYDRA_FILES if name not in before.entries]
    made += [p.name for p in run_dir.iterdir() if p.name.endswith(".log") and p.name not in before.entries]
    for name in made:
        path = run_dir / name
        if path.is_file() and not path.is_symlink():
            path.unlink()
    folders = [run_dir / ".hydra"] if ".hydra" not in before.entries else []
    if before.made_from is not None:          # the job made run_dir and the parents up to made_from
        folder = run_dir
        folders.append(folder)
        stop = Path(os.path.abspath(artifacts))
        while folder != before.made_from and folder.parent != folder:
            folder = folder.parent
            if folder == stop:
                break
            folders.append(folder)
    for folder in folders:
        try:
            folder.rmdir()                    # only if empty: anything else written there stays
        except OSError:
            if folder != run_dir / ".hydra":
                return


def is_run_folder(folder: Path) -> bool:
    """Whether ``folder`` is an earlier run's: its ``status.json`` is a run's status (a run id and an experiment)."""
    import json
    try:
        status = json.loads((folder / "status.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(status, dict) and "run_id" in status and "experiment" in status


def check_run_folder(run_dir: Path, value: object) -> None:
    """``hydra.run.dir`` may be a new or empty folder, or an earlier run's (run into again, as after a
    kill); a folder that holds what a run writes (``RUN_FILES``: ``config.yaml``, ``summary.parquet`` ...;
    Hydra's own ``.hydra/`` aside)
    and is not a run's would have those files replaced: print one paragraph naming them and exit 2,
    before anything is made (``hydra.run.dir=../..`` wrote its config.yaml over another folder's)."""
    try:
        entries = set(os.listdir(run_dir)) if run_dir.is_dir() else set()
    except OSError:
        return                                # check_writable names what is wrong with it
    # .hydra/ alone is Hydra's (any Hydra app's job writes it; a job killed before its status.json leaves it)
    clashes = sorted(entries & (RUN_FILES - {".hydra"}))
    if not clashes or is_run_folder(run_dir):
        return
    print(f"error: hydra.run.dir={value}: {run_dir} already holds {', '.join(clashes)}, which a run writes there, and "
          f"it is not an earlier run's folder (no status.json of a run); the run would replace them, so it is refused "
          f"and nothing was written. Allowed is a new or empty folder, or an earlier run's folder to run into again "
          f"(e.g. hydra.run.dir={Path(str(value)) / 'run1'}); without hydra.run.dir each run gets its own, "
          f"runs/<experiment_name>/<time> under paths.artifacts.", file=sys.stderr)
    sys.exit(2)


def check_writable(folder: Path, key: str, value: object) -> None:
    """Create ``folder`` (and its parents) and write a probe file in it; on an OSError print one
    paragraph naming ``key=value`` and exit 2."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder, prefix=".probe."):
            pass
    except OSError as exc:
        print(f"error: {key}={value}: {cannot_write(folder, exc, 'write in')}", file=sys.stderr)
        sys.exit(2)


def check_experiment(config: DictConfig) -> None:
    """The experiment file placed its keys at the top level and set ``experiment_name``; else print one
    paragraph naming the file and what it holds, and exit 2. A file without ``# @package _global_`` (a
    list, a string, a mapping) lands under an ``experiment`` key, and the run folder's name, which
    interpolates ``experiment_name``, then fails in Hydra with a traceback."""
    choices = config.hydra.runtime.get("choices") or {}
    name = choices.get("experiment")
    where = f"experiment={name}: conf/experiment/{name}.yaml (or the --config-dir file of that name)" if name \
        else "experiment=null: the config"
    misplaced = config.get("experiment") if "experiment" in config else None
    if "experiment" in config:
        kind = ("a list" if isinstance(misplaced, ListConfig) else "a mapping without '# @package _global_'"
                if isinstance(misplaced, DictConfig) else f"a {type(misplaced).__name__} ({misplaced!r})")
        shown = repr(OmegaConf.to_container(misplaced) if isinstance(misplaced, (DictConfig, ListConfig)) else misplaced)
        problem = f"holds {kind}: {shown[:80]}{' ...' if len(shown) > 80 else ''}"
    elif OmegaConf.is_missing(config, "experiment_name"):
        problem = "does not set experiment_name"
    else:
        from pipeline.errors import ConfigError
        from pipeline.run.config import check_experiment_name
        try:
            check_experiment_name(config.get("experiment_name"))     # it names the run folder, made next
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)
        return
    print(f"error: {where} {problem}; an experiment file is a mapping of config keys whose first line is "
          f"'# @package _global_' and which sets experiment_name (see conf/experiment/ao_vsimm_s1.yaml).",
          file=sys.stderr)
    sys.exit(2)


class OutputFolders(Callback):
    def _check(self, config: DictConfig, output: str) -> None:
        global COMPOSED
        COMPOSED = True
        check_experiment(config)
        cwd = Path(str(config.hydra.runtime.cwd))
        artifacts = config.paths.artifacts
        check_writable(cwd / str(artifacts), "paths.artifacts", artifacts)
        check_writable((cwd / output).parent, "paths.artifacts", artifacts)

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        global BEFORE
        check_experiment(config)      # before hydra.run.dir, which interpolates experiment_name, is read
        # before anything is made (check_writable makes the run folder's parent): what was there
        run_dir = Path(str(config.hydra.runtime.cwd)) / str(config.hydra.run.dir)
        BEFORE = folder_before(run_dir)
        check_run_folder(Path(os.path.abspath(run_dir)), config.hydra.run.dir)
        self._check(config, str(config.hydra.run.dir))

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        self._check(config, str(config.hydra.sweep.dir))
