"""Before any job: the folders a run or a sweep writes can be written.

A Hydra callback (conf/config.yaml ``hydra.callbacks.output_folders``), so it runs after Hydra has
composed the config and before it creates the run or sweep folder: ``paths.artifacts=/proc/x``, a
path under a file, a read-only or full disk give one paragraph and exit 2, not Hydra's traceback
from its own ``mkdir``. It also records that Hydra got that far (``COMPOSED``): an exit 1 before it
is Hydra refusing the command line (an unknown key, a missing config), which ``python -m pipeline``
then reports with the same exit code as every other input error, 2.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from pipeline.errors import cannot_write

COMPOSED = False      # set in this process once Hydra has composed the config and called the callbacks


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


class OutputFolders(Callback):
    def _check(self, config: DictConfig, output: str) -> None:
        global COMPOSED
        COMPOSED = True
        cwd = Path(str(config.hydra.runtime.cwd))
        artifacts = config.paths.artifacts
        check_writable(cwd / str(artifacts), "paths.artifacts", artifacts)
        check_writable((cwd / output).parent, "paths.artifacts", artifacts)

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        self._check(config, str(config.hydra.run.dir))

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        self._check(config, str(config.hydra.sweep.dir))
