"""The launcher's config node, ``hydra/launcher=isolated`` (Hydra imports this module when it scans
``hydra_plugins``, which registers the node, as hydra-joblib-launcher does for ``joblib``)."""

# no `from __future__ import annotations`: Hydra's plugin scan runs this module outside sys.modules,
# where @dataclass cannot resolve string annotations
from dataclasses import dataclass

from hydra.core.config_store import ConfigStore


@dataclass
class IsolatedLauncherConf:
    _target_: str = "hydra_plugins.isolated_launcher.launcher.IsolatedLauncher"
    # jobs running at a time, joblib's convention: -1 = one per CPU (cgroup-aware), -2 = all but one, ...
    n_jobs: int = -1


ConfigStore.instance().store(group="hydra/launcher", name="isolated", node=IsolatedLauncherConf,
                             provider="isolated_launcher")
