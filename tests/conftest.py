from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf

from filters.base import MeasurementSeries

ROOT = Path(__file__).resolve().parents[1]
CONF = ROOT / "conf"


@pytest.fixture(scope="session")
def models13():
    return instantiate(OmegaConf.load(CONF / "models" / "acceleration13.yaml"), _convert_="all")


def scenario(name: str, **overrides):
    node = OmegaConf.load(CONF / "scenario" / f"{name}.yaml")
    return instantiate(OmegaConf.merge(node, overrides), _convert_="all")


def measurements(truth, seed: int, noise_std: float = 20.0) -> MeasurementSeries:
    from pipeline.studies.ao_vsimm.sensor import PositionSensor
    det = PositionSensor(noise_std).measure(truth, seed)
    return MeasurementSeries(det.time, det.z[:, :, 0], noise_std**2 * np.eye(2), det.detected[:, :, 0], det.sensor)
