"""``sensor.filter``: the sensor's own low-pass / moving-average filter on the sensor sources.

Parsing and its one-line errors; the simulated filtered white noise's variance and lag-1..3
autocorrelation against the closed forms (moving average: (N - d) / N, first order: a^d), within
five standard errors of the estimators (Bartlett's formula for the autocorrelation, the Gaussian
variance of a sample variance); the predicted variance, ACF and PSD against |H(e^{iw})|^2 s^2 2 Ts
with H from scipy's own design; the step path equal to the batch path; the filter's identity
(one tap) changes nothing; a bias walk through each filter kind: its variance from rest and its
variogram against a Monte Carlo, its PSD and the diagnosis' part against |H|^2 times the walk's, the variance of its mean (the
diagnosis' level term) against the Monte Carlo.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.cli import assert_bad
from helpers.cli import cli_in_process as cli
from noiselab.model import ModelError, parse_model
from noiselab.model.simulate import Stepper, simulate
from scipy.signal import butter, freqz, lfilter

TS = 0.01
GYRO = f"""name = "gyro"
[sampling]
Ts = {TS}
[outputs]
names = ["gyro_x"]
units = ["rad/s"]
[sensor.white]
std = 0.5
"""
STD = 0.5
KINDS = {
    "average": 'kind = "average"\ntaps = 4\n',
    "lowpass1": 'kind = "lowpass1"\ncutoff_hz = 5.0\n',
    "lowpass2": 'kind = "lowpass2"\ncutoff_hz = 10.0\n',
}


def _model(kind: str, extra: str = ""):
    return parse_model(GYRO + extra + "[sensor.filter]\n" + KINDS[kind])


def _reference_ba(kind: str):
    """(b, a) of each kind's filter here from scipy's design, independent of the effect's own
    coefficients."""
    if kind == "average":
        return np.full(4, 0.25), [1.0]
    if kind == "lowpass1":
        r = np.exp(-2 * np.pi * 5.0 * TS)
        return [1 - r], [1.0, -r]
    return butter(2, 10.0, fs=1 / TS)


def _reference_h(kind: str, f: np.ndarray) -> np.ndarray:
    """H(e^{i 2 pi f Ts}) of :func:`_reference_ba`."""
    b, a = _reference_ba(kind)
    return freqz(b, a, worN=f, fs=1 / TS)[1]


def _closed_acf(kind: str, L: int) -> np.ndarray:
    """The correlation rho(d), d = 0..L-1, of filtered white noise (module docstring)."""
    d = np.arange(L)
    if kind == "average":
        return np.clip((4 - d) / 4.0, 0.0, None)
    if kind == "lowpass1":
        return np.exp(-2 * np.pi * 5.0 * TS) ** d
    # second order: the impulse response's autocorrelation, long enough to converge
    b, a = butter(2, 10.0, fs=1 / TS)
    h = lfilter(b, a, np.r_[1.0, np.zeros(4000)])
    r = np.array([h[:h.size - k] @ h[k:] for k in range(L)])
    return r / r[0]


def _closed_var(kind: str) -> float:
    if kind == "average":
        return STD**2 / 4
    if kind == "lowpass1":
        a = np.exp(-2 * np.pi * 5.0 * TS)
        return STD**2 * (1 - a) / (1 + a)
    b, a = butter(2, 10.0, fs=1 / TS)
    h = lfilter(b, a, np.r_[1.0, np.zeros(4000)])
    return STD**2 * float(h @ h)


@pytest.mark.parametrize("kind", list(KINDS))
def test_simulated_filtered_white_noise_has_the_closed_form_variance_and_acf(kind):
    n, burn = 200_000, 1000                    # the filter starts at rest: its transient dropped
    y = simulate(_model(kind), n + burn, seed=44).y[burn:, 0]
    rho = _closed_acf(kind, 400)
    var = _closed_var(kind)
    # Var of the sample variance of a Gaussian process: (2 / n) sum_d R(d)^2 (d over all integers)
    se_var = np.sqrt(2.0 / n * var**2 * (rho[0] ** 2 + 2 * np.sum(rho[1:] ** 2)))
    assert abs(np.mean(y**2) - var) < 5 * se_var, (np.mean(y**2), var, se_var)
    r_all = np.r_[rho[::-1], rho[1:]]          # rho(-399..399)
    for k in (1, 2, 3):
        r_hat = np.mean(y[k:] * y[:-k]) / np.mean(y**2)
        # Bartlett: n Var(r_k) = sum_j (rho_{j+k} + rho_{j-k} - 2 rho_k rho_j)^2
        j = np.arange(-390, 391)
        rr = lambda i: r_all[i + 399]
        se = np.sqrt(np.sum((rr(j + k) + rr(j - k) - 2 * rho[k] * rr(j)) ** 2) / n)
        assert abs(r_hat - rho[k]) < 5 * se, (k, r_hat, rho[k], se)


@pytest.mark.parametrize("kind", list(KINDS))
def test_predicted_variance_acf_and_psd_are_the_filters(kind):
    pr = _model(kind).predictor()
    var = pr.steady_state().contributions["sensor.white"][0]
    assert var == pytest.approx(_closed_var(kind), rel=1e-9)
    R = pr.acf(4)["sensor.white"][:, 0]
    np.testing.assert_allclose(R / R[0], _closed_acf(kind, 4), rtol=1e-9, atol=1e-12)
    f = np.linspace(0.05, 0.5 / TS - 0.05, 37)
    S, lines = pr.psd(f)
    want = np.abs(_reference_h(kind, f)) ** 2 * STD**2 * 2 * TS
    np.testing.assert_allclose(S["sensor.white"][:, 0], want, rtol=1e-9, atol=1e-15)
    assert not lines


def test_a_gauss_markov_bias_and_a_tone_pass_through_the_filter():
    gm = "[sensor.bias_markov]\nstd = 0.2\ntau_s = 0.05\n[sensor.tone]\namplitude = 0.3\nfrequency_hz = 12.0\n"
    m = _model("lowpass1", gm)
    pr = m.predictor()
    f = np.linspace(0.05, 49.0, 23)
    S, lines = pr.psd(f)
    phi = np.exp(-TS / 0.05)
    c2 = 0.2**2 * (1 - phi**2)
    h2 = np.abs(_reference_h("lowpass1", f)) ** 2
    gm_psd = 2 * TS * c2 / np.abs(1 - phi * np.exp(-2j * np.pi * f * TS)) ** 2
    np.testing.assert_allclose(S["sensor.bias_markov"][:, 0], h2 * gm_psd, rtol=1e-9)
    (eid, f0, power, j), = lines
    assert (eid, f0, j) == ("sensor.tone", 12.0, 0)
    assert power == pytest.approx(0.3**2 / 2 * np.abs(_reference_h("lowpass1", np.array([12.0]))[0]) ** 2, rel=1e-12)


def test_the_quantizer_reads_the_filters_output_and_the_step_path_equals_the_batch_path():
    m = _model("lowpass2", "[sensor.bias_markov]\nstd = 0.2\ntau_s = 0.05\n[sensor.quantization]\nstep = 0.01\n")
    batch = simulate(m, 3000, seed=3).y
    np.testing.assert_allclose(batch / 0.01, np.rint(batch / 0.01), atol=1e-9)   # the register's grid
    st = Stepper(m, seed=3)
    steps = np.array([st.step()[3] for _ in range(3000)]).reshape(batch.shape)
    np.testing.assert_array_equal(steps, batch)


def test_the_one_tap_filter_changes_nothing():
    plain = parse_model(GYRO)
    one = parse_model(GYRO + '[sensor.filter]\nkind = "average"\ntaps = 1\n')
    np.testing.assert_array_equal(simulate(one, 5000, seed=5).y, simulate(plain, 5000, seed=5).y)
    f = np.linspace(0.1, 40.0, 9)
    np.testing.assert_allclose(one.predictor().psd(f)[0]["sensor.white"], plain.predictor().psd(f)[0]["sensor.white"],
                               rtol=1e-12)
    assert "sensor.filter" not in plain.effects


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_filter_writes_back_as_given(kind):
    m = _model(kind)
    again = parse_model(m.to_toml())
    assert again.effects["sensor.filter"].param_dict() == m.effects["sensor.filter"].param_dict()
    assert again.effects["sensor.filter"].param_dict()["kind"] == kind


@pytest.mark.parametrize("body, parts", [
    ('kind = "bessel"\ncutoff_hz = 5.0\n', ["kind", "'lowpass1'"]),
    ('kind = "lowpass1"\n', ["cutoff_hz"]),
    ('kind = "lowpass1"\ncutoff_hz = 50.0\n', ["cutoff_hz", "Nyquist frequency 50"]),
    ('kind = "lowpass2"\ncutoff_hz = -1.0\n', ["cutoff_hz", "between 0"]),
    ('kind = "lowpass1"\ncutoff_hz = 5.0\ntaps = 3\n', ["taps", "takes cutoff_hz"]),
    ('kind = "average"\ncutoff_hz = 5.0\n', ["cutoff_hz", "takes taps"]),
    ('kind = "average"\ntaps = 0\n', ["taps", "between 1 and 256"]),
    ('kind = "average"\ntaps = 2.5\n', ["taps", "integer"]),
    ('kind = "average"\ntaps = 300\n', ["taps", "between 1 and 256"]),
    ('kind = "average"\ntaps = 4\norder = 2\n', ["order"]),
])
def test_a_bad_filter_table_is_a_one_line_error(body, parts, tmp_path, capsys):
    with pytest.raises(ModelError) as exc:
        parse_model(GYRO + "[sensor.filter]\n" + body)
    msg = str(exc.value)
    assert "\n" not in msg and "[sensor.filter]" in msg, msg
    for part in parts:
        assert part in msg, (part, msg)
    path = tmp_path / "bad.toml"
    path.write_text(GYRO + "[sensor.filter]\n" + body)
    assert_bad(cli(capsys, "predict", str(path)), *parts)


def test_the_cli_predicts_and_analyses_a_filtered_sensor(tmp_path, capsys):
    """`noiselab simulate` of a gyro with a 4-tap moving average to a real MCAP recording: the
    filter's model explains it (the analysis' error about 1), the unfiltered model does not (its
    variance 4x, its spectrum flat); `predict --json` gives the closed-form variance and the
    filter's share of it as a modifier."""
    truth, plain = tmp_path / "filtered.toml", tmp_path / "plain.toml"
    truth.write_text(GYRO + "[sensor.filter]\n" + KINDS["average"])
    plain.write_text(GYRO)
    rc, out, err = cli(capsys, "predict", truth, "--json")
    assert rc == 0, err[-3000:]
    rep = json.loads(out)
    np.testing.assert_allclose(rep["var_y"], [STD**2 / 4], rtol=1e-12)
    np.testing.assert_allclose(rep["modifiers"]["sensor.filter"], [STD**2 / 4 - STD**2], rtol=1e-12)
    rec = tmp_path / "filtered.mcap"
    assert cli(capsys, "simulate", truth, "--duration", "120", "--seed", "2", "--out", rec)[0] == 0
    rc, out, err = cli(capsys, "analyze", rec, "--model", truth, "--json")
    assert rc == 0, err[-3000:]
    good = json.loads(out)["error"]
    rc, out, err = cli(capsys, "analyze", rec, "--model", plain, "--json")
    assert rc == 0, err[-3000:]
    bad = json.loads(out)["error"]
    assert good < 3.0 and bad > 30 * good, (good, bad)


WALK = GYRO.replace("[sensor.white]\nstd = 0.5\n", "[sensor.bias_walk]\nstd = 0.4\n")   # the same gyro, a walk alone


def _walk_model(kind: str, init: str = ""):
    return parse_model(WALK + init + "[sensor.filter]\n" + KINDS[kind])


@pytest.mark.parametrize("kind", list(KINDS))
def test_a_bias_walk_through_the_filter_matches_a_monte_carlo(kind):
    """Var w_k from rest (with an initial bias) and the variogram of the filtered walk against
    4000 independent simulated records (fixed seed), each within five standard errors of its
    estimator: a Gaussian's sample variance over T records has Var = 2 sigma^4 / T, and so has
    the mean of (w_(k+d) - w_k)^2 / 2 (a chi-square of one degree scaled by gamma: Var = 2 gamma^2 / T)."""
    T, n, k0 = 4000, 120, 60
    m = _walk_model(kind, "initial_std = 0.3\n")
    y = simulate(m, n, seed=952, trials=T).y[..., 0]             # (T, n)
    pr = m.predictor()
    var = pr.covariance(n).parts["sensor.bias_walk"][:, 0]
    for k in (0, 1, 3, 10, n - 1):
        got = np.mean(y[:, k] ** 2)
        assert abs(got - var[k]) < 5 * var[k] * np.sqrt(2.0 / T), (k, got, var[k])
    gam = pr.variogram(40)["sensor.bias_walk"][:, 0]
    for d in (1, 2, 3, 5, 39):
        got = np.mean((y[:, k0 + d] - y[:, k0]) ** 2) / 2
        assert abs(got - gam[d]) < 5 * gam[d] * np.sqrt(2.0 / T), (d, got, gam[d])
    # the record's mean (the diagnosis' level term) over the first N samples from rest
    from noiselab.diagnose.whittle import level_density
    N = 10                                       # short: the filter from rest shows
    C, qq, b0 = level_density(m, N)
    v_mean = C[0, 0] + b0[0] + qq[0] * (N - 1) * (2 * N - 1) / (6.0 * N)
    got = np.var(y[:, :N].mean(axis=1), ddof=0) + np.mean(y[:, :N].mean(axis=1)) ** 2
    assert abs(got - v_mean) < 5 * v_mean * np.sqrt(2.0 / T), (got, v_mean)
    unfiltered = b0[0] + qq[0] * (N - 1) * (2 * N - 1) / (6.0 * N)
    assert abs(got - unfiltered) > 5 * v_mean * np.sqrt(2.0 / T), (got, unfiltered)
    # unfiltered, the variogram would be d q / 2: the filter's shows (and the test can tell them apart)
    q = 0.4**2 * TS
    assert abs(gam[1] - q / 2) > 10 * gam[1] * np.sqrt(2.0 / T)


@pytest.mark.parametrize("kind", list(KINDS))
def test_a_filtered_walks_psd_and_diagnosis_part_are_the_walks_times_the_filters_gain(kind):
    pr = _walk_model(kind).predictor()
    q = 0.4**2 * TS
    f = np.linspace(0.05, 0.5 / TS - 0.05, 37)
    h2 = np.abs(_reference_h(kind, f)) ** 2
    want = h2 * 2 * TS * q / (4 * np.sin(np.pi * f * TS) ** 2)
    np.testing.assert_allclose(pr.psd(f)[0]["sensor.bias_walk"][:, 0], want, rtol=1e-9)
    # the diagnosis' differenced record: the walk's increments (white, q) through the filter, so
    # its expected periodogram is q |H|^2 up to the taper's leakage (small for a record this long)
    from noiselab.diagnose.whittle.parts import walk_part
    from noiselab.diagnose.whittle.periodograms import n_freqs
    M = 4096
    flt = pr.model.effects["sensor.filter"]
    E = walk_part(np.array([q]), M, None, flt)[:, 0]
    fk = np.arange(n_freqs(M)) / (M * TS)
    np.testing.assert_allclose(E, q * np.abs(_reference_h(kind, fk)) ** 2, rtol=0, atol=2e-3 * q)
    assert E.shape == walk_part(np.array([q]), M)[:, 0].shape


@pytest.mark.parametrize("kind", list(KINDS))
def test_the_impulse_response_autocorrelation_is_the_filters(kind):
    """R_h(j) = sum_i h_i h_(i+j) against scipy's impulse response (5000 samples: decayed below
    1e-300 for these cutoffs) correlated directly."""
    flt = _model(kind).effects["sensor.filter"]
    b, a = _reference_ba(kind)
    imp = np.zeros(5000)
    imp[0] = 1.0
    h = lfilter(b, a, imp)
    want = np.array([h[:h.size - j] @ h[j:] for j in range(60)])
    np.testing.assert_allclose(flt.impulse_acf(60)[:, 0], want, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(flt.step_response(60)[:, 0], np.cumsum(h[:60]), rtol=1e-12)


def test_a_sentence_names_the_filters_kind_as_it_is():
    """The evidence sentences format parameters with ``_g``: a filter's kind (a string) and a
    tone's lines (tables) are written as they are, not converted to numbers (a white noise's refit
    with a filter as its alternative stopped a report so)."""
    from noiselab.model.effects.base import _g

    assert _g("lowpass1") == "lowpass1"
    assert _g({"amplitude": 0.00123456, "frequency_hz": 12.5}) == "{amplitude = 0.00123, frequency_hz = 12.5}"
    assert _g([1.23456, 2.0]) == "[1.23, 2]"
