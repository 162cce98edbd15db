"""The 3-D radar seen on the horizontal plane: study 000's Radar3D measures the flight in range,
azimuth and elevation; its reports are converted to Cartesian (first order, J R_p J') and the
horizontal part (x, y with its 2x2 covariance) is what a 2-D filter gets (kind ``position_xy``).

For study 001's FSIMM and AO-VSIMM, which track a horizontal target with position measurements:
the truth is then the flight's horizontal state (``RecordedFlight(horizontal=True)``), and the
height the radar needs comes from the truth's ``up`` label.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pipeline.data import Detections, Truth
from pipeline.sensors import Radar3D


class HorizontalRadar(Radar3D):
    """Radar3D's noise, draws and parameters; reports as horizontal positions with their covariance."""

    produces = "position_xy"          # filters.base.MEASUREMENT_KINDS

    def measure(self, truth: Truth, seed: int) -> Detections:
        if "z" not in truth.state_names:
            if "up" not in truth.labels:
                raise ValueError("HorizontalRadar: a horizontal truth needs its height as the label 'up'")
            index = [truth.state_names.index(n) for n in ("x", "y")]
            xyz = np.concatenate([truth.state[..., index], np.asarray(truth.labels["up"])], axis=-1)
            truth = replace(truth, state=xyz, state_names=("x", "y", "z"))
        polar = Radar3D.measure(self, truth, seed)           # the same noise draws as the 3-D radar
        cartesian = self.to_cartesian(polar)
        return Detections(cartesian.time, cartesian.sensor, cartesian.z[..., :2].copy(),
                          cartesian.noise_covariance[..., :2, :2].copy(), cartesian.target, cartesian.detected,
                          ("x", "y"), ("m", "m"))
