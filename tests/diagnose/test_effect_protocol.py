"""An effect is one module: a new effect defined here, and nowhere else, is parsed from a model file,
simulated, predicted, compared and found by the diagnosis, through the hooks of
:mod:`noiselab.model.effects.base` alone. And the generic diagnosis modules name no effect.

The effect: white noise seen through a difference over two samples, v_k = std (e_{k-1} - e_{k-3}) (a
sensor that reports the increment of a noisy reading over two of its periods), a band noise:
variance 2 std^2, lag-2 autocorrelation -1/2 and none at lag 1, spectrum 4 std^2 sin^2(2 pi f Ts) Ts
(none at DC and at Nyquist; the catalogue's one-sample difference, ``sensor.integral_white``, has
its maximum at Nyquist). It is a linear sensor source with states s_k = (e_{k-1}, e_{k-2}, e_{k-3})
(the ``sensor_linear`` prediction hook), fitted as a ``noise`` by its std, one per output (the
``channels`` diagnosis hook).
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import numpy as np
import pytest

from noiselab.diagnose.compare import compare
from noiselab.diagnose.diagnose import diagnose
from noiselab.diagnose.thresholds import THRESHOLD
from noiselab.model import parse_model
from noiselab.model.effects import CATALOGUE
from noiselab.model.effects.base import Effect, FitSpec
from noiselab.model.schema import nonnegative

ROOT = Path(__file__).resolve().parents[2]
EID = "sensor.differenced"


class SensorDifferenced(Effect):
    """``sensor.differenced``: v_k = std (e_{k-1} - e_{k-3}), e white N(0, 1), one per output."""

    id = EID
    stage = "sensor"
    chain_order = 50
    summary = "differenced white sensor noise"
    fit = FitSpec("noise", scale="std")
    # -- diagnosis hooks
    channels = "output"

    def parse(self, t):
        self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0")

    def n_normals(self):
        return self.dims.p

    def init_state(self, static_rng, trials):
        return {"e": np.zeros((trials, 3, self.dims.p))}          # e_{k-3}, e_{k-2}, e_{k-1}

    def sensor_terms(self, e, state):
        ext = np.concatenate([state["e"], e], axis=1)              # e_{-3}, e_{-2}, e_{-1}, e_0, ...
        n = e.shape[1]
        state["e"] = ext[:, n:n + 3].copy()
        return self.params["std"] * (ext[:, 2:n + 2] - ext[:, :n])

    def sensor_linear(self):
        p, std = self.dims.p, np.broadcast_to(self.params["std"], (self.dims.p,))
        F = np.zeros((3 * p, 3 * p))
        F[p:2 * p, :p] = np.eye(p)                                 # s2_{k+1} = s1_k
        F[2 * p:, p:2 * p] = np.eye(p)                             # s3_{k+1} = s2_k
        G = np.vstack([np.diag(std), np.zeros((2 * p, p))])        # s1_{k+1} = std e_k
        H = np.hstack([np.eye(p), np.zeros((p, p)), -np.eye(p)])
        return F, G, H


MODEL = """
name = "msd"
[sampling]
Ts = 0.005
[plant]
m = 1.2
c = 0.35
k = 4.0
[command]
kind = "sine"
amplitude = 0.8
frequency_hz = 0.7
[process.white]
std = 0.2
[sensor.white]
std = 0.005
"""
PLANTED = MODEL + f"[{EID}]\nstd = 0.008\n"


@pytest.fixture
def registered():
    """The new effect in the catalogue for one test, and out of it after."""
    assert EID not in CATALOGUE
    CATALOGUE[EID] = SensorDifferenced
    try:
        yield SensorDifferenced
    finally:
        del CATALOGUE[EID]


def test_parsed_simulated_and_predicted(registered):
    truth = parse_model(PLANTED)
    assert isinstance(truth.effects[EID], SensorDifferenced)
    assert truth.effects[EID].param_dict() == {"std": 0.008}
    assert f"[{EID}]" in truth.to_toml()
    # a sensor-only model (y = reference + sensor effects): y is the effect alone
    alone = parse_model(f'name = "s"\n[sampling]\nTs = 0.01\n[outputs]\nnames = ["x"]\nunits = ["m"]\n'
                        f"[{EID}]\nstd = 0.5\n")
    y = alone.simulate(200_000, seed=3).y[:, 0]
    y = y - np.mean(y)
    var = float(np.mean(y * y))
    rho1 = float(np.mean(y[1:] * y[:-1])) / var
    rho2 = float(np.mean(y[2:] * y[:-2])) / var
    assert abs(var / (2 * 0.25) - 1) < 0.02, var                  # 2 std^2
    assert abs(rho1) < 0.01 and abs(rho2 + 0.5) < 0.01, (rho1, rho2)   # 0, -1/2
    # predicted: its part of the measurement's variance, 2 std^2
    st = alone.predictor().steady_state()
    assert np.isclose(float(np.ravel(st.contributions[EID])[0]), 2 * 0.25, rtol=1e-9)
    assert np.isclose(float(np.ravel(st.var_y)[0]), 2 * 0.25, rtol=1e-9)
    st = truth.predictor().steady_state()
    assert np.isclose(float(np.ravel(st.contributions[EID])[0]), 2 * 0.008**2, rtol=1e-9)


def test_compared_and_found_by_the_diagnosis(registered):
    truth = parse_model(PLANTED)
    nominal = parse_model(MODEL)
    rec = truth.simulate(12_000, seed=5)
    # compared: the views carry its part, and the model with it explains the record
    with_it = compare(truth, rec.t, rec.y, rec.u, burn=None)
    without = compare(nominal, rec.t, rec.y, rec.u, burn=None)
    assert any(EID in (v.contributions or {}) for v in with_it.views), [v.name for v in with_it.views]
    assert with_it.error < 1.5 < without.error, (with_it.error, without.error)
    # found: ranked first, its std within its 95 % interval, the model error down to about 1
    rep = diagnose(nominal, rec.t, rec.y, rec.u, max_effects=1)
    first = rep["missing"][0]
    assert first["effect"] == EID and first["mode"] == "add", [(m["effect"], m["score"]) for m in rep["missing"]]
    assert first["score"] > THRESHOLD and first["evidence"]
    lo, hi = first["interval"]["std"]
    assert lo <= 0.008 <= hi, (lo, hi)
    assert abs(first["params"]["std"] / 0.008 - 1) < 0.2
    assert rep["error_after"] < rep["error_before"] and rep["error_after"] <= 1.5
    assert f"[{EID}]" in rep["fitted_model"]


ID = re.compile(r"(sensor|process|actuator)\.[a-z_0-9]+(:.*)?")


def _docstrings(tree) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def test_generic_code_names_no_effect():
    """No string in the code of the package outside the effects' own modules (docstrings aside)
    is an effect id: the simulation, the prediction, the comparison, the diagnosis and the viewers
    ask the effects' hooks (service/model/effects/base.py)."""
    found = []
    effects = ROOT / "service" / "model" / "effects"
    for path in sorted([*(ROOT / "service").rglob("*.py"), *(ROOT / "viewers").rglob("*.py")]):
        if effects in path.parents:
            continue
        tree = ast.parse(path.read_text())
        docs = _docstrings(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs \
                    and (ID.fullmatch(node.value) or node.value in CATALOGUE):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {node.value!r}")
    assert not found, found


def test_a_mode_is_a_small_type_spelled_as_the_json_contract():
    from noiselab.diagnose.modes import ADD, REFIT, Mode, replacing
    rep = replacing("actuator.white")
    assert str(rep) == "replace:actuator.white" and Mode.parse("replace:actuator.white") == rep
    assert (str(ADD), str(REFIT)) == ("add", "refit") and Mode.parse("add") == ADD
    assert rep.phrase() == "in place of actuator.white" and REFIT.phrase() == "refit"
    # near-ties: replace, refit, add; exact ties: replace, add, refit (the user's value kept)
    assert rep.rank < REFIT.rank < ADD.rank and rep.exact_rank < ADD.exact_rank < REFIT.exact_rank
    with pytest.raises(ValueError):
        Mode.parse("remove")
    with pytest.raises(ValueError):
        Mode("replace")
