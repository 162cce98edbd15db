"""Filters with injected numerical faults, for the fault-flag tests (used as config _target_s)."""

from __future__ import annotations

import os
import signal
from dataclasses import replace

import numpy as np

from filters.imm import FSIMM
from filters.models import AccelerationModelSet


class FaultyFSIMM(FSIMM):
    """FSIMM whose output is broken on purpose: run 1's covariance loses symmetry at step 10,
    run 2 diverges to NaN from step 20 on, run 3's covariance is not positive definite at step 15."""

    def run(self, measurements):
        estimate = super().run(measurements)
        state, covariance = estimate.state.copy(), estimate.covariance.copy()
        covariance[1, 10, 0, 1] += 1e-3 * np.abs(covariance[1, 10]).max()
        state[2, 20:] = np.nan
        covariance[2, 20:] = np.nan
        covariance[3, 15] = -np.eye(covariance.shape[-1])
        return replace(estimate, state=state, covariance=covariance)


class SelfKillingFSIMM(FSIMM):
    """FSIMM whose process SIGKILLs itself as it starts filtering when ``sigkill`` is true: a sweep
    job that dies the way the out-of-memory killer ends one (tests/test_sweep_isolation.py)."""

    def __init__(self, models: AccelerationModelSet, name: str = "FSIMM", initial_model: str = "m1",
                 sigkill: bool = False, engine: str = "numba") -> None:
        super().__init__(models, name, initial_model, engine=engine)
        self.sigkill = sigkill

    def run(self, measurements):
        if self.sigkill:
            os.kill(os.getpid(), signal.SIGKILL)
        return super().run(measurements)
