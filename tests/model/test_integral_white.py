"""``sensor.integral_white``: white noise on the output's integral, IEEE Std 952's quantization
noise Q (service/model/effects/sensor_integral_white.py).

Checks: parsing and one-line errors; the closed forms (variance 2 Q^2 / Ts^2, lag-1
autocorrelation -1/2 and none beyond, the one-sided PSD (8 Q^2 / Ts) sin^2(pi f Ts), the Allan
variance 3 Q^2 / tau^2 at every m); the simulation against them (chi-squared and the lag-1
estimator's spread) and started stationary; the step API against the batch; the coefficient Q; the
Allan command's Q reading (the -1 line at tau = sqrt(3) s) on a simulated recording; the diagnosis
finding it on its hidden pair is tests/diagnose/test_diagnose.py's.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from noiselab.model import ModelError, parse_model
from noiselab.model.coefficients import model_coefficients
from noiselab.model.effects import CATALOGUE

ID = "sensor.integral_white"


def gyro(body: str, ts: float = 0.01, names=("gx",)) -> str:
    units = ["rad/s"] * len(names)
    return (f'name = "iw"\n[sampling]\nTs = {ts}\n[outputs]\nnames = {json.dumps(list(names))}\n'
            f"units = {json.dumps(units)}\n[{ID}]\n{body}\n")


@pytest.mark.parametrize("body,parts", [
    ("", ("[sensor.integral_white] Q", "missing")),
    ("Q = -0.1", ("[sensor.integral_white] Q", "Q >= 0")),
    ("Q = [0.1, 0.2]", ("[sensor.integral_white] Q",)),
    ("Q = 0.1\nstd = 3.0", ("std",)),
])
def test_bad_values_are_one_line_errors(body, parts):
    with pytest.raises(ModelError) as info:
        parse_model(gyro(body), "bad.toml")
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith("bad.toml: "), msg
    for part in parts:
        assert part in msg, (part, msg)


def test_closed_forms_variance_acf_psd_and_allan():
    Q, ts = np.array([2e-5, 5e-5]), 0.01
    m = parse_model(gyro(f"Q = {Q.tolist()}", ts, names=("gx", "gy")))
    pr = m.predictor()
    np.testing.assert_allclose(pr.steady_state().var_y, 2 * Q**2 / ts**2, rtol=1e-12)
    np.testing.assert_allclose(pr.covariance(4).Sy, np.broadcast_to(2 * Q**2 / ts**2, (4, 2)), rtol=1e-12)
    f = np.array([0.1, 1.0, 10.0, 49.0])
    psd, lines = pr.psd(f)
    exact = 8 * Q[None, :] ** 2 / ts * np.sin(np.pi * f[:, None] * ts) ** 2
    assert not lines
    np.testing.assert_allclose(psd[ID], exact, rtol=1e-9)
    mm = np.array([1, 2, 7, 100, 1000])
    # the predictor forms the Allan variance from second differences of sums over m samples, whose
    # terms are m^2 times larger than the result here: 1e-6 relative is that cancellation's level
    np.testing.assert_allclose(pr.allan(mm)[ID], 3 * Q[None, :] ** 2 / (mm[:, None] * ts) ** 2, rtol=1e-6)
    cls = CATALOGUE[ID]
    assert (cls.fit.kind, cls.fit.scale, cls.fit.shape, cls.channels) == ("noise", "Q", (), "output")


def test_simulation_has_the_variance_and_the_lag_one_autocorrelation():
    Q, ts, n = 3e-5, 0.01, 200_000
    y = parse_model(gyro(f"Q = {Q}", ts)).simulate(n, seed=3).y[:, 0]
    var = 2 * Q**2 / ts**2
    # an MA(1) with theta = -1: Var(s^2) = (2 / n) sum_h gamma_h^2 = (2 / n) var^2 (1 + 2 / 4)
    z = (y.var() - var) / (var * np.sqrt(3.0 / n))
    assert abs(z) < 4, z
    r1 = np.corrcoef(y[1:], y[:-1])[0, 1]
    r2 = np.corrcoef(y[2:], y[:-2])[0, 1]
    # Bartlett: Var(r_h) = (1 + 2 rho_1^2) / n for h >= 2; about 1/(2n)-ish at h = 1 for this MA(1)
    assert abs(r1 + 0.5) < 4 / np.sqrt(n) and abs(r2) < 4 * np.sqrt(1.5 / n), (r1, r2)


def test_starts_stationary_and_steps_as_the_batch():
    Q, ts, trials = 3e-5, 0.01, 4000
    m = parse_model(gyro(f"Q = {Q}", ts) + "[sensor.white]\nstd = 0.002\n")
    y = m.simulate(8, seed=5, trials=trials).y[:, [0, 7], 0]
    var = m.predictor().covariance(8).Sy[[0, 7], 0]
    ratio = y.var(axis=0, ddof=1) / var
    lo, hi = (stats.chi2.ppf(q, trials - 1) / (trials - 1) for q in (1e-3 / 4, 1 - 1e-3 / 4))
    assert np.all((ratio > lo) & (ratio < hi)), ratio
    n = 5000
    st = m.stepper(seed=7)
    assert np.array_equal(np.array([st.step()[3] for _ in range(n)]), m.simulate(n, seed=7).y)


def test_coefficient_Q_and_the_evidence_sentence():
    co = model_coefficients(parse_model(gyro("Q = [2e-5, 1e-5]", names=("gx", "gy"))))
    assert co["gy"]["Q"] == {"value": 1e-5, "interval": None, "unit": "(rad/s)*s"}
    text = CATALOGUE[ID].explain({"Q": 2e-5}, 0.01)
    assert "f^2" in text and "Allan" in text and "-1/2" in text and "Q = 2e-05" in text


def test_the_allan_command_reads_Q_on_the_minus_one_line(tmp_path, capsys):
    """A simulated record whose Allan deviation falls as 1/tau (Q) and then as 1/sqrt(tau) (N): the
    Allan command identifies white PM there and reads Q at tau = sqrt(3) s, N at 1 s, within their
    intervals widened by the estimator's own spread (3 of them, the intervals being 68 %)."""
    from helpers.cli import cli_in_process as cli

    Q, N = 2e-3, 1e-3             # sqrt(3) Q / tau meets N / sqrt(tau) at tau = 3 Q^2 / N^2 = 12 s
    model = tmp_path / "iw.toml"
    model.write_text(gyro(f"Q = {Q}", 0.1) + f"[sensor.white]\ndensity = {N}\n")
    rec = tmp_path / "iw.mcap"
    rc, _, err = cli(capsys, "simulate", model, "--duration", 20_000, "--seed", 9, "--out", rec)
    assert rc == 0, err
    rc, out, err = cli(capsys, "allan", rec, "--model", model, "--json")
    assert rc == 0, err
    o = json.loads(out)["outputs"]["gx"]
    assert o["noise_type"][0] == "white PM", o["noise_type"]
    rq, rn = o["readings"]["Q"], o["readings"]["N"]
    assert rq["unit"] == "(rad/s)*s" and o["model_coefficients"]["Q"]["value"] == pytest.approx(Q)
    for rd, true in ((rq, Q), (rn, N)):
        lo, hi = rd["interval"]
        w = np.log(hi / lo) / 2            # one sigma in ln
        assert abs(np.log(rd["value"] / true)) < 3 * w, (rd, true)
