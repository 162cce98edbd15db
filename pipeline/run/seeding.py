"""Randomness: one SeedSequence per experiment, spawned per stage and per run.

Run r's generator depends only on (seed, stage, r), never on how many runs there are, how
they are chunked or which worker computes them.
"""

from __future__ import annotations

import zlib

import numpy as np


def run_generators(seed: int, stage: str, runs: int) -> list[np.random.Generator]:
    stage_key = zlib.crc32(stage.encode())
    return [np.random.default_rng(np.random.SeedSequence(entropy=seed, spawn_key=(stage_key, r)))
            for r in range(runs)]
