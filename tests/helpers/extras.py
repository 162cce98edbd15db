"""Tests of an optional extra ([distributed], [tune], [slurm]): skipped where it is not installed,
failed instead where ``MTT_REQUIRE_<EXTRA>=1`` says it must be (.ci/run sets it for every extra
the README's test command installs, so a green CI run means those tests really ran)."""

from __future__ import annotations

import importlib
import os

import pytest


def require_extra(extra: str, *modules: str) -> None:
    """Import ``modules`` (the extra's packages); call at the top of the test module."""
    install = f"pip install -e '.[test,{extra}]'"
    flag = f"MTT_REQUIRE_{extra.upper()}"
    try:
        for module in modules:
            importlib.import_module(module)
    except ImportError as exc:
        if os.environ.get(flag) == "1":
            raise ImportError(f"{exc}. {flag}=1 (set by .ci/run): this run needs the [{extra}] extra: {install}") from exc
        pytest.skip(f"{', '.join(modules)} not importable ({exc}); needs the [{extra}] extra: {install}",
                    allow_module_level=True)
