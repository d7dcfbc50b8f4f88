"""``sensor.bias_instability``: a flicker (1/f) bias of IEEE Std 952's B, realised and predicted as
a sum of first-order Gauss-Markov processes (service/model/effects/sensor_bias_instability.py).

Checks: the table's parsing and its one-line errors; the predicted PSD of the sum against the exact
one-sided 1/f PSD B^2 / (pi f) (IEEE 952's two-sided B^2 / (2 pi f)) within the accuracy the module
states, over its band; the predicted Allan deviation flat at sqrt(2 ln 2 / pi) B ~ 0.664 B; the
simulation against the prediction (a stationary start: the covariance recursion, and a Monte Carlo
of the Allan variance); the step API against the batch; the IEEE 952 coefficient B.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from noiselab.model import ModelError, parse_model
from noiselab.model.coefficients import model_coefficients
from noiselab.model.effects import CATALOGUE
from noiselab.model.effects.sensor_bias_instability import ACCURACY_DB, FLOOR, flicker_psd

ID = "sensor.bias_instability"


def gyro(body: str, ts: float = 0.01, names=("gx",)) -> str:
    """A sensor-only model (no [plant]) with the effect's table ``body``."""
    units = ["rad/s"] * len(names)
    return (f'name = "flicker"\n[sampling]\nTs = {ts}\n[outputs]\nnames = {json.dumps(list(names))}\n'
            f"units = {json.dumps(units)}\n[{ID}]\n{body}\n")


def one_line(text: str, *parts: str) -> None:
    with pytest.raises(ModelError) as info:
        parse_model(text, "bad.toml")
    msg = str(info.value)
    assert isinstance(info.value, ValueError) and "\n" not in msg and msg.startswith("bad.toml: "), msg
    for part in parts:
        assert part in msg, (part, msg)


def test_floor_is_the_ieee_952_constant():
    # sigma_A^2 = (2 B^2 / pi) int_0^inf sin^4(x) / x^3 dx = (2 ln 2 / pi) B^2 (IEEE 952 Annex C)
    assert FLOOR == pytest.approx(0.6643, abs=1e-4)
    from scipy.integrate import quad
    integral = quad(lambda x: np.sin(x) ** 4 / x**3, 0, 200, limit=2000)[0] + 3 / 8 / (2 * 200**2)
    assert integral == pytest.approx(np.log(2), rel=1e-4)


def test_parsing_defaults_and_per_output_values():
    m = parse_model(gyro("B = [0.002, 0.001]", names=("gx", "gy")))
    e = m.effects[ID]
    np.testing.assert_array_equal(e.params["B"], [0.002, 0.001])
    assert (e.f_lo, e.f_hi) == pytest.approx((1e-6 / 0.01, 0.1 / 0.01))
    assert e.param_dict() == {"B": [0.002, 0.001]}           # the defaults are not written back
    # 3 per decade over the band widened by 1.5 decades
    assert e.K == int(np.ceil((5 + 1.5) * 3)) + 1
    assert np.allclose(np.diff(np.log10(e.taus)), np.log10(e.taus[1] / e.taus[0]))
    band = parse_model(gyro("B = 0.002\nf_lo_hz = 0.01\nf_hi_hz = 2.0")).effects[ID]
    assert band.param_dict() == {"B": 0.002, "f_lo_hz": 0.01, "f_hi_hz": 2.0}
    assert band.taus[0] < 1 / (2 * np.pi * 2.0) and band.taus[-1] > 1 / (2 * np.pi * 0.01)
    # a diagnosis candidate: B scales a noise of fixed shape, one per output, a slow sensor drift
    cls = CATALOGUE[ID]
    assert (cls.fit.kind, cls.fit.scale, cls.fit.shape) == ("noise", "B", ())
    assert (cls.channels, cls.drift) == ("output", "sensor")


@pytest.mark.parametrize("body,parts", [
    ("", ("[sensor.bias_instability] B", "missing")),
    ("B = -0.1", ("[sensor.bias_instability] B", "B >= 0")),
    ("B = [0.1, 0.2]", ("[sensor.bias_instability] B",)),
    ('B = "x"', ("[sensor.bias_instability] B",)),
    ("B = 0.1\nf_hi_hz = 20.0", ("f_hi_hz", "1/(10 Ts) = 10")),
    ("B = 0.1\nf_hi_hz = 0.0", ("f_hi_hz",)),
    ("B = 0.1\nf_lo_hz = -1.0", ("f_lo_hz", "> 0")),
    ("B = 0.1\nf_lo_hz = 5.0", ("f_lo_hz", "f_hi_hz / 10 = 1")),
    ("B = 0.1\nf_lo_hz = 1e-20", ("f_lo_hz", "12 decades")),
    ("B = 0.1\ntau_s = 3.0", ("tau_s",)),
])
def test_bad_values_are_one_line_errors(body, parts):
    one_line(gyro(body), *parts)


@pytest.mark.parametrize("ts,band", [(0.01, None), (1.0, (1e-4, 0.1)), (0.005, (0.05, 20.0))])
def test_psd_of_the_sum_is_1_over_f_within_the_stated_db(ts, band):
    body = "B = 0.003" + ("" if band is None else f"\nf_lo_hz = {band[0]}\nf_hi_hz = {band[1]}")
    m = parse_model(gyro(body, ts))
    e = m.effects[ID]
    f = np.geomspace(e.f_lo, e.f_hi, 400)
    psd, lines = m.predictor().psd(f)
    err = 10 * np.log10(psd[ID] / flicker_psd(e.params["B"], f))
    assert not lines and np.max(np.abs(err)) <= ACCURACY_DB, np.max(np.abs(err))
    # the ripple between the correlation times, away from the band's ends, is far smaller
    mid = (f > 10 * e.f_lo) & (f < e.f_hi / 10)
    assert np.max(np.abs(err[mid])) < 0.06


@pytest.mark.parametrize("ts,band", [(0.01, (0.01, None)), (0.01, None), (1.0, (1e-4, 0.1)), (0.005, (0.05, 20.0))])
def test_allan_deviation_is_flat_at_0664_B_over_the_band(ts, band):
    B = 0.002
    body = f"B = {B}" + ("" if band is None else f"\nf_lo_hz = {band[0]}") + \
        ("" if band is None or band[1] is None else f"\nf_hi_hz = {band[1]}")
    m = parse_model(gyro(body, ts))
    e = m.effects[ID]
    taus = np.geomspace(3 / e.f_hi, 0.1 / e.f_lo, 25)
    mm = np.unique(np.round(taus / ts).astype(int))
    adev = np.sqrt(m.predictor().allan(mm)[ID][:, 0])
    np.testing.assert_allclose(adev / (FLOOR * B), 1.0, atol=0.03)
    if band == (0.01, None):
        # and it leaves the floor beyond the band: white-like (falling) far above 1/f_lo
        far = np.sqrt(m.predictor().allan(np.array([int(5 / e.f_lo / ts)]))[ID][0, 0])
        assert far < 0.8 * FLOOR * B


def test_simulation_starts_stationary_as_the_covariance_recursion_says():
    m = parse_model(gyro("B = [0.002, 0.001]\nf_lo_hz = 0.01", names=("gx", "gy")))
    pr = m.predictor()
    cov = pr.covariance(40)
    var = pr.steady_state().var_y
    np.testing.assert_allclose(cov.Sy, np.broadcast_to(var, cov.Sy.shape), rtol=1e-12)
    trials = 4000
    y = m.simulate(40, seed=5, trials=trials).y[:, [0, 39], :]
    emp = y.var(axis=0, ddof=1)                  # (2, p)
    a = 1e-3 / emp.size
    lo, hi = (stats.chi2.ppf(q, trials - 1) / (trials - 1) for q in (a / 2, 1 - a / 2))
    assert np.all((emp / var > lo) & (emp / var < hi)), emp / var


def test_step_api_equals_batch_bit_for_bit():
    m = parse_model(gyro("B = [0.002, 0.001]\nf_lo_hz = 0.01", names=("gx", "gy")) + "[sensor.white]\nstd = 0.01\n")
    n = 5000                                    # more than one of the stepper's noise buffers
    batch = m.simulate(n, seed=7)
    st = m.stepper(seed=7)
    assert np.array_equal(np.array([st.step()[3] for _ in range(n)]), batch.y)


def _overlapping_avar(y: np.ndarray, m: int) -> np.ndarray:
    """Overlapping Allan variance of each row of ``y`` (trials, N) at m samples."""
    c = np.concatenate([np.zeros((y.shape[0], 1)), np.cumsum(y, axis=1)], axis=1)
    means = (c[:, m:] - c[:, :-m]) / m
    d = means[:, m:] - means[:, :-m]
    return 0.5 * np.mean(d**2, axis=1)


def test_simulated_allan_matches_the_prediction_monte_carlo():
    """The overlapping Allan estimator is unbiased for a stationary process (the sum starts
    stationary), so its mean over independent trials is the predicted AVAR within z standard errors
    of the trials' own spread (two-sided family-wise level 1e-3 over the taus)."""
    m = parse_model(gyro("B = 1.0\nf_lo_hz = 1e-4\nf_hi_hz = 0.1", ts=1.0))
    mm = np.array([4, 16, 64, 256])
    pred = m.predictor().allan(mm)[ID][:, 0]
    trials, n = 1000, 4096
    y = m.simulate(n, seed=2026, trials=trials).y[:, :, 0]
    z = stats.norm.ppf(1 - 1e-3 / (2 * mm.size))
    for k, mk in enumerate(mm):
        est = _overlapping_avar(y, int(mk))
        se = est.std(ddof=1) / np.sqrt(trials)
        assert abs(est.mean() - pred[k]) < z * se, (mk, est.mean() / pred[k], se / pred[k])
    # and the prediction there is the flicker floor
    np.testing.assert_allclose(np.sqrt(pred), FLOOR, rtol=0.03)


def test_coefficient_B_and_the_evidence_sentence():
    m = parse_model(gyro("B = [0.002, 0.001]", names=("gx", "gy")))
    co = model_coefficients(m)
    assert co["gx"]["B"]["value"] == pytest.approx(0.002) and co["gy"]["B"]["unit"] == "rad/s"
    text = CATALOGUE[ID].explain({"B": 0.002}, 0.01)
    assert "1/f" in text and "Allan" in text and f"{FLOOR * 0.002:.3g}" in text and "B = 0.002" in text


def test_cli_predicts_simulates_and_analyses_it(tmp_path, capsys):
    """End to end through the CLI and a real MCAP: the predicted variance is the white noise's plus
    the sum's, a recording of the model agrees with it, and the Allan table's noise identification
    reads flicker on the floor (NIST SP 1065's lag-1 ACF / slope rule)."""
    from helpers.cli import cli_in_process as cli

    white = "[sensor.white]\nstd = 0.001\n"
    model = tmp_path / "flk.toml"
    model.write_text(gyro("B = 0.002\nf_lo_hz = 0.001") + white)
    e = parse_model(model.read_text()).effects[ID]
    rc, out, err = cli(capsys, "predict", model, "--json")
    assert rc == 0, err
    rep = json.loads(out)
    np.testing.assert_allclose(rep["contributions"][ID], [np.sum(e.s**2)], rtol=1e-12)
    np.testing.assert_allclose(rep["var_y"], [1e-6 + np.sum(e.s**2)], rtol=1e-12)
    rec = tmp_path / "flk.mcap"
    rc, out, err = cli(capsys, "simulate", model, "--duration", 600, "--seed", 4, "--out", rec)
    assert rc == 0, err
    rc, out, err = cli(capsys, "analyze", rec, "--model", model, "--json")
    assert rc == 0, err
    assert json.loads(out)["error"] < 3.0
    nominal = tmp_path / "white.toml"                  # the same sensor without its flicker
    nominal.write_text(gyro("B = 0.002").split(f"[{ID}]")[0] + white)
    rc, out, err = cli(capsys, "analyze", rec, "--model", nominal, "--json")
    assert rc == 0, err
    assert json.loads(out)["error"] > 100
    rc, out, err = cli(capsys, "allan", rec)
    assert rc == 0, err
    rows = [ln.split() for ln in out.splitlines() if ln.strip()[:1].isdigit() and "flicker" in ln]
    assert any(0.1 <= float(r[0]) <= 10 for r in rows), out


def test_through_the_sensors_filter_it_starts_stationary_and_the_filter_from_rest():
    """A flicker bias after a Gauss-Markov bias, both before a 4-tap moving average
    (``sensor.filter``): the simulation draws the flicker's states stationary, starts the
    Gauss-Markov and the filter from rest, so y_0 = b_0 / 4 (a sixteenth of the flicker's variance);
    the covariance recursion must put the stationary start on the flicker's states, which follow
    the Gauss-Markov's cascade (its state and the filter's) in the augmented system."""
    m = parse_model(gyro("B = 0.002\nf_lo_hz = 0.01") + '[sensor.filter]\nkind = "average"\ntaps = 4\n'
                    "[sensor.bias_markov]\nstd = 0.003\ntau_s = 0.5\n")
    pr = m.predictor()
    Sy = pr.covariance(12).Sy[:, 0]
    var_b = float(np.sum(np.diag(m.effects[ID].initial_cov())))
    assert Sy[0] == pytest.approx(var_b / 16, rel=1e-9)
    trials = 4000
    y = m.simulate(12, seed=11, trials=trials).y[:, [0, 1, 5], 0]
    emp = y.var(axis=0, ddof=1)
    ratio = emp / Sy[[0, 1, 5]]
    a = 1e-3 / ratio.size
    lo, hi = (stats.chi2.ppf(q, trials - 1) / (trials - 1) for q in (a / 2, 1 - a / 2))
    assert np.all((ratio > lo) & (ratio < hi)), ratio


def test_a_stationary_start_has_no_transient_to_skip():
    """The diagnosis skips a record's first transient_samples() when it does not start at rest (the
    model's covariance from rest is not yet stationary there). The flicker's states start
    stationary, so they add no transient, however long their correlation times (here up to
    1.6e4 s, 1.6e6 samples): a Gauss-Markov bias beside them keeps its own, ln(0.01) / (2 ln phi)
    samples."""
    from noiselab.diagnose.compare import transient_samples

    m = parse_model(gyro("B = 0.002") + "[sensor.white]\nstd = 0.01\n")
    assert max(m.effects[ID].taus) > 1e4 and transient_samples(m) == 0
    gm = parse_model(gyro("B = 0.002") + "[sensor.bias_markov]\nstd = 0.003\ntau_s = 2.0\n")
    phi = np.exp(-0.01 / 2.0)
    assert transient_samples(gm) == int(np.ceil(np.log(0.01) / (2 * np.log(phi))))
