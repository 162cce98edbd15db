"""Before Hydra builds anything: the classes a command's config names for Hydra itself.

Hydra instantiates every ``hydra.callbacks`` node when a run or a sweep starts, and a sweep's launcher
and sweeper with the nodes nested in them, all before the task function, and so before
``pipeline.run.config.check_targets`` sees the job's config: ``'+hydra.callbacks.evil={_target_:
logging.FileHandler, filename: F, mode: w}'`` truncated F and the job ended 0; an experiment file can
set the same node. ``check_command(argv)``, called by ``python -m pipeline`` first, composes the config
as Hydra will (the same config directory, ``--config-path``, ``--config-dir``, ``--config-name`` and
overrides; a sweep's swept values left out, as Hydra leaves them out of the sweep's own config) and
checks what it names there (``pipeline.run.config.check_hydra_targets``).

A command line or config Hydra refuses (an unknown key, a missing experiment) composes no config
here; Hydra then refuses it itself, before it builds anything.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any, Sequence

from omegaconf import DictConfig

CONF = Path(__file__).resolve().parents[2] / "conf"      # hydra.main's config_path, ../conf of pipeline/__main__.py
APP_DIR = Path(__file__).resolve().parents[1]            # where a relative --config-path starts (pipeline/)


class _Refused(Exception):
    pass


class _HydraArguments(argparse.ArgumentParser):
    """Hydra's command-line flags (hydra._internal.utils.get_args_parser), parsed without printing or exiting."""

    def error(self, message: str) -> None:  # type: ignore[override]
        raise _Refused(message)


def _parser() -> _HydraArguments:
    parser = _HydraArguments(add_help=False, allow_abbrev=False)
    parser.add_argument("overrides", nargs="*")
    for flags in (("--help", "-h"), ("--hydra-help",), ("--version",), ("--resolve",), ("--run", "-r"),
                  ("--multirun", "-m"), ("--shell-completion", "-sc")):
        parser.add_argument(*flags, action="store_true")
    for flags in (("--cfg", "-c"), ("--package", "-p"), ("--config-path", "-cp"), ("--config-name", "-cn"),
                  ("--config-dir", "-cd"), ("--experimental-rerun",)):
        parser.add_argument(*flags)
    parser.add_argument("--info", "-i", nargs="?", const="all")
    return parser


def _overrides(args: argparse.Namespace) -> list[str] | None:
    """The overrides Hydra composes a run's or a sweep's own config with: a sweep's swept values left
    out (Hydra composes the sweep's config without them and refuses them in a single run), the
    ``--config-dir`` folder added to ``hydra.searchpath`` (Hydra adds it to the search path)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(list(args.overrides))
    except Exception:  # noqa: BLE001 - Hydra refuses the same line itself
        return None
    kept = [o for o in parsed if not o.is_sweep_override()]
    overrides = [o.input_line for o in kept]
    if args.config_dir is not None:
        extra = f"file://{os.path.abspath(args.config_dir)}"
        searchpath = [o for o in kept if o.key_or_group == "hydra.searchpath" and not o.is_delete()]
        listed: list[Any] = list(searchpath[-1].value()) if searchpath and isinstance(searchpath[-1].value(), list) else []
        overrides = [line for o, line in zip(kept, overrides) if o not in searchpath]
        quoted = ",".join("'" + str(p).replace("\\", "\\\\").replace("'", "\\'") + "'" for p in [*listed, extra])
        overrides.append(f"hydra.searchpath=[{quoted}]")
    return overrides


def composed(argv: Sequence[str]) -> DictConfig | None:
    """The config, its ``hydra`` node included, that Hydra composes for this command line before it
    builds its callbacks (a run or a sweep); None for a command that builds none (``--help``,
    ``--cfg``, ``--info``, ...) or that Hydra refuses itself."""
    from hydra import compose, initialize_config_dir, initialize_config_module

    try:
        args = _parser().parse_args(list(argv))
    except _Refused:
        return None
    if (args.help or args.hydra_help or args.version or args.cfg is not None or args.info is not None
            or args.shell_completion or args.experimental_rerun is not None):
        return None
    overrides = _overrides(args)
    if overrides is None:
        return None
    config_path = args.config_path
    try:
        if config_path is not None and config_path.startswith("pkg://"):
            context = initialize_config_module(config_module=config_path[len("pkg://"):], version_base="1.3")
        else:
            folder = CONF if config_path is None else (Path(config_path) if os.path.isabs(config_path)
                                                       else APP_DIR / config_path)
            context = initialize_config_dir(config_dir=str(folder.resolve()), version_base="1.3")
        with context:
            return compose(config_name=args.config_name or "config", overrides=overrides, return_hydra_config=True)
    except Exception:  # noqa: BLE001 - whatever fails to compose here fails in Hydra before it builds anything
        return None


def check_command(argv: Sequence[str]) -> None:
    """Refuse (ConfigError, one paragraph) a command whose config names for Hydra a class outside what
    ``check_hydra_targets`` allows, before Hydra composes, makes a folder or builds anything."""
    from pipeline.run.config import check_hydra_targets

    cfg = composed(argv)
    if cfg is not None:
        check_hydra_targets(cfg)
