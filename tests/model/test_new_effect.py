"""An effect is one module: a new effect defined here, registered in the catalogue, is simulated,
predicted and compared with no edit of the generic code (the simulation, the predictor and the
comparison ask it through the hooks of service/model/effects/base.py)."""

from __future__ import annotations

import numpy as np

from noiselab.diagnose.compare import cache_clear, compare
from noiselab.model import parse_model
from noiselab.model.effects import CATALOGUE
from noiselab.model.effects.base import Effect
from noiselab.model.schema import nonnegative


class SensorFloor(Effect):
    """A white measurement floor given by its variance (units^2 per sample)."""

    id = "sensor.floor"
    stage = "sensor"
    chain_order = 9
    draw_order = 7
    summary = "a white floor given by its variance"

    def parse(self, t):
        self.params["var"] = t.vector("var", self.dims.p, check=nonnegative, expect="variances >= 0")

    def n_normals(self):
        return self.dims.p

    def sensor_terms(self, e, state):
        return np.sqrt(self.params["var"]) * e

    def spectral(self):
        return [("white", self.params["var"])]


DOC = """name = "floor"
[sampling]
Ts = 0.01
[plant]
m = 1.2
c = 0.35
k = 4.0
[command]
kind = "sine"
amplitude = 0.8
frequency_hz = 0.7
[process.white]
std = 0.05
[sensor.floor]
var = 4e-4
"""


def test_a_new_effect_is_simulated_predicted_and_compared(monkeypatch):
    """The floor's variance is its steady-state contribution and its PSD part 2 Ts var; a record
    simulated with it has the residual variance the model predicts (within 5 sd of the sample
    variance's spread) and a model error near 1 (within 0.5) against the model that has it, while
    the model without it is far off (its error above 3)."""
    monkeypatch.setitem(CATALOGUE, SensorFloor.id, SensorFloor)
    cache_clear()
    mdl = parse_model(DOC, "floor")
    assert list(mdl.effects) == ["process.white", "sensor.floor"]
    pr = mdl.predictor()
    st = pr.steady_state()
    assert np.allclose(st.contributions["sensor.floor"], 4e-4, rtol=0, atol=0)
    parts, _ = pr.psd(np.array([1.0, 10.0]))
    assert np.allclose(parts["sensor.floor"], 2 * 0.01 * 4e-4)
    n = 40_000
    rec = mdl.simulate(n, seed=3)
    r = rec.y[:, 0] - pr.mean_response(n).y[:, 0]
    var = float(np.var(r[2000:]))
    sd = float(st.var_y[0]) * np.sqrt(2.0 / (n - 2000) * 50)   # correlated samples: generous dof
    assert abs(var - st.var_y[0]) < 5 * sd, (var, st.var_y)
    c = compare(mdl, rec.t, rec.y, rec.u, burn=None)
    assert abs(c.error - 1.0) < 0.5, c.error
    assert all("sensor.floor" in v.contributions for v in c.views if v.contributions)
    without = parse_model(DOC.replace("[sensor.floor]\nvar = 4e-4\n", ""), "without")
    assert compare(without, rec.t, rec.y, rec.u, burn=None).error > 3.0
    cache_clear()
