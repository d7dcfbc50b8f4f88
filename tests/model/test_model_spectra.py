"""Long simulations against the predicted PSD, ACF and Allan deviation, one effect at a time
(issue 2). The data are the residual r = y - (predicted mean response to the command).

PSD: scipy-backed Welch (noiselab.stats.welch, Hann, 50 % overlap) against the model's expected
Welch estimate (Predictor.expected_welch: the prediction seen through the same window). Each bin
is ~ E chi2(nu)/nu with nu the estimator's equivalent dof; every other bin is used (Hann bins two
apart are nearly uncorrelated) and the number outside the two-sided 99.9 % interval must not
exceed the binomial 99.9 % quantile. ACF: the sample autocorrelation at a few lags within
Bartlett's band of the predicted one (family-wise 1e-3). Allan: the predicted deviation inside
the estimator's chi-squared bounds at a family-wise 1e-3 level.
"""

import numpy as np
import pytest
from scipy import stats

from helpers.models import ALL_LINEAR, load
from noiselab.stats import acf, oadev, welch

BASE = """
name = "one"
[sampling]
Ts = 0.01
[plant]
m = 1.0
c = 0.8
k = 3.0
[command]
kind = "sine"
amplitude = 0.5
frequency_hz = 0.3
"""

CASES = {
    "process.white std": "[process.white]\nstd = 0.3",
    "process.white psd": "[process.white]\npsd = 0.05",
    "actuator.white": "[actuator.white]\nstd = 0.2",
    "actuator.ar1": "[actuator.ar1]\nstd = 0.2\ntau_s = 0.3",
    "actuator.lag": "[actuator.white]\nstd = 0.3\n[actuator.lag]\ntau_s = 0.05",
    "actuator.saturation": "[actuator.white]\nstd = 0.2\n[actuator.saturation]\nlimit = 0.6",
    "actuator.deadzone": "[actuator.white]\nstd = 0.2\n[actuator.deadzone]\nwidth = 0.1",
    "sensor.scale_factor": "[process.white]\nstd = 0.3\n[sensor.scale_factor]\nerror = 0.05",
    "sensor.bias_markov": "[sensor.bias_markov]\nstd = 0.01\ntau_s = 2.0",
    "sensor.white": "[sensor.white]\nstd = 0.01",
    "sensor.tone": "[sensor.white]\nstd = 0.002\n[sensor.tone]\namplitude = 0.01\nfrequency_hz = 7.0",
    "sensor.jitter": "[sensor.white]\nstd = 0.0005\n[sensor.jitter]\nstd_s = 0.002",
    "sensor.quantization": "[sensor.white]\nstd = 0.01\n[sensor.quantization]\nstep = 0.005",
    # a coarse step (25x the sensor noise) on a signal that crosses few steps per sample: the
    # quantizer's error is a correlated sawtooth, not white (predicted lag-1 correlation 0.55);
    # the signal's random part spans ~1 step (std 0.9 step), where the formula's dropped terms
    # (exp(-2 pi^2 sigma^2 / step^2)) are below 1e-7
    "sensor.quantization coarse": "[process.white]\nstd = 1.0\n[sensor.white]\nstd = 0.002\n"
                                  "[sensor.quantization]\nstep = 0.05",
}

N = 1 << 19
NPERSEG = 2048
LEVEL = 1e-3


def residual(mdl, seed):
    rec = mdl.simulate(N, seed=seed)
    return rec.y - mdl.predictor().mean_response(N).y


def check_psd(mdl, r):
    pr = mdl.predictor()
    expected = pr.expected_welch(NPERSEG)
    total = sum(v for v in expected.values() if v is not None)
    for j in range(mdl.p):
        est = welch(r[:, j], 1.0 / mdl.Ts, nperseg=NPERSEG)
        np.testing.assert_allclose(est.f, np.arange(NPERSEG // 2 + 1) / (NPERSEG * mdl.Ts))
        sel = np.arange(3, est.f.size - 1, 2)          # skip DC and the two detrend-biased bins
        nu = est.dof[sel]
        ratio = est.psd[sel] / total[sel, j]
        lo = stats.chi2.ppf(LEVEL / 2, nu) / nu
        hi = stats.chi2.ppf(1 - LEVEL / 2, nu) / nu
        out = np.sum((ratio < lo) | (ratio > hi))
        allowed = stats.binom.ppf(1 - LEVEL, sel.size, LEVEL)
        assert out <= allowed, (j, out, allowed, np.round(ratio[(ratio < lo) | (ratio > hi)], 3))
        # and no systematic bias: the mean ratio over all bins is 1 within its standard error
        se = np.sqrt(np.mean(2.0 / nu) / sel.size)
        assert abs(ratio.mean() - 1) < 4 * se + 0.002, (j, ratio.mean())


def check_acf(mdl, r):
    R = mdl.predictor().acf(4000)     # Bartlett's sum runs over all lags: give it the long tail
    total = sum(v for v in R.values() if v is not None)
    lags = np.array([1, 3, 10, 30, 100, 199])
    z = stats.norm.ppf(1 - LEVEL / (2 * lags.size * mdl.p))
    for j in range(mdl.p):
        rho_pred = total[:, j] / total[0, j]
        est = acf(r[:, j], 200, demean=True)
        lo, hi = est.ci(conf=1 - LEVEL / (lags.size * mdl.p), rho_ref=rho_pred)
        assert np.all((est.rho[lags] >= lo[lags]) & (est.rho[lags] <= hi[lags])), (
            j, est.rho[lags], rho_pred[lags])
        # the lag-0 autocovariance is the variance: within the normal approximation of its spread
        var_se = np.sqrt(2 * np.sum(total[:, j] ** 2) / N * 2)
        assert abs(est.r[0] - total[0, j]) < z * var_se, (est.r[0], total[0, j])


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_psd_and_acf_per_effect(case):
    mdl = load(BASE + CASES[case])
    r = residual(mdl, seed=sum(map(ord, case)))
    check_psd(mdl, r)
    check_acf(mdl, r)


@pytest.mark.slow
def test_psd_and_acf_two_outputs_every_linear_effect():
    text = ALL_LINEAR.replace("[sensor.bias_walk]\nstd = [0.001, 0.002]\ninitial_std = 0.001\n", "")
    mdl = load(text)
    r = residual(mdl, seed=17)
    check_psd(mdl, r)
    check_acf(mdl, r)


@pytest.mark.slow
def test_allan_deviation_of_walk_white_and_markov():
    """The exact discrete Allan variance of the model (per effect, summed) against the overlapping
    Allan deviation of a long record, within the estimator's chi-squared bounds."""
    mdl = load(BASE + "[sensor.white]\nstd = 0.01\n[sensor.bias_walk]\nstd = 0.004\n"
               "[sensor.bias_markov]\nstd = 0.003\ntau_s = 5.0")
    r = residual(mdl, seed=3)[:, 0]
    res = oadev(r, 1.0 / mdl.Ts, taus="octave")
    pred = mdl.predictor().allan(res.m)
    total = sum(v for v in pred.values() if v is not None)[:, 0]
    conf = 1 - LEVEL / res.m.size
    lo, hi = res.bounds(conf)
    # the bounds are on the true deviation given the estimate: the prediction must lie inside
    inside = (np.sqrt(total) >= lo) & (np.sqrt(total) <= hi)
    assert np.all(inside), (res.m[~inside], res.dev[~inside], np.sqrt(total)[~inside])
    # the walk dominates at long tau and the white noise at short tau, as the model says
    assert pred["sensor.bias_walk"][-1, 0] > 10 * pred["sensor.white"][-1, 0]
    assert pred["sensor.white"][0, 0] > 10 * pred["sensor.bias_walk"][0, 0]


@pytest.mark.slow
@pytest.mark.parametrize("truth,wrong", [
    ("[actuator.ar1]\nstd = 0.2\ntau_s = 0.3", "[actuator.white]\nstd = 0.2"),       # color missed
    ("[sensor.white]\nstd = 0.01", "[sensor.white]\nstd = 0.0095"),                 # 10 % in power
    ("[sensor.white]\nstd = 0.002\n[sensor.tone]\namplitude = 0.01\nfrequency_hz = 7.0",
     "[sensor.white]\nstd = 0.002"),                                                 # a line missed
])
def test_checks_fail_on_a_wrong_model(truth, wrong):
    """Negative control: the same checks reject a model that is wrong in one effect."""
    r = residual(load(BASE + truth), seed=5)
    with pytest.raises(AssertionError):
        check_psd(load(BASE + wrong), r)


@pytest.mark.slow
def test_acf_check_fails_on_a_wrong_model():
    r = residual(load(BASE + "[actuator.ar1]\nstd = 0.2\ntau_s = 0.3\n[sensor.white]\nstd = 0.003"), seed=6)
    with pytest.raises(AssertionError):
        check_acf(load(BASE + "[actuator.white]\nstd = 0.2\n[sensor.white]\nstd = 0.003"), r)
