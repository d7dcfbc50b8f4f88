"""Monte Carlo ensembles (fixed seeds) against the predicted mean, P_k and S_y,k (issue 2).

Bounds: for n independent Gaussian trials, (n - 1) s^2 / sigma^2 ~ chi2(n - 1); a sample covariance
has variance (s_xx s_yy + s_xy^2) / (n - 1); a sample mean has variance sigma^2 / n. Every check
uses a two-sided family-wise level of 1e-3 (Bonferroni over the checks in the test).
"""

from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from helpers.models import ALL_LINEAR, EVERYTHING, load
from noiselab.model import load_model

ALPHA = 1e-3


def chi2_band(pred, n, count):
    a = ALPHA / count
    return (pred * stats.chi2.ppf(a / 2, n - 1) / (n - 1), pred * stats.chi2.ppf(1 - a / 2, n - 1) / (n - 1))


def z_bound(count):
    return stats.norm.ppf(1 - ALPHA / (2 * count))


@pytest.mark.slow
@pytest.mark.parametrize("name,text", [("seed", None), ("all", ALL_LINEAR)])
def test_ensemble_matches_mean_P_and_Sy(name, text):
    mdl = load_model("seed") if text is None else load(text)
    trials, N = 3000, 700
    rec = mdl.simulate(N, seed=2024, trials=trials)
    pr = mdl.predictor()
    cov = pr.covariance(N)
    mean = pr.mean_response(N)
    ks = np.array([1, 5, 40, 200, 699])
    p, n = mdl.p, mdl.plant.n
    count = ks.size * (p + p + n + n * (n - 1) // 2)
    z = z_bound(count)
    # mean of y and S_y,k per output
    for j in range(p):
        yk = rec.y[:, ks, j]
        Sy = cov.Sy[ks, j]
        assert np.all(np.abs(yk.mean(axis=0) - mean.y[ks, j]) < z * np.sqrt(Sy / trials)), j
        lo, hi = chi2_band(Sy, trials, count)
        emp = yk.var(axis=0, ddof=1)
        assert np.all((emp > lo) & (emp < hi)), (j, emp / Sy)
    # P_k of the plant state: variances and covariances
    P = cov.P[ks][:, :n, :n]
    for a in range(n):
        xa = rec.x[:, ks, a]
        lo, hi = chi2_band(P[:, a, a], trials, count)
        emp = xa.var(axis=0, ddof=1)
        zero = P[:, a, a] == 0          # e.g. euler position at k = 1: noise needs two steps to arrive
        assert np.all(emp[zero] < 1e-30)
        assert np.all(((emp > lo) & (emp < hi))[~zero]), (a, emp / P[:, a, a])
        for b in range(a + 1, n):
            xb = rec.x[:, ks, b]
            c = np.mean((xa - xa.mean(0)) * (xb - xb.mean(0)), axis=0) * trials / (trials - 1)
            sd = np.sqrt((P[:, a, a] * P[:, b, b] + P[:, a, b] ** 2) / (trials - 1))
            assert np.all(np.abs(c - P[:, a, b]) < z * sd + 1e-20), (a, b)   # + rounding where sd = 0


@pytest.mark.slow
def test_statistical_linearization_of_the_saturated_actuator():
    """Mean: the ensemble mean follows m_{k+1} = A m_k + B E[sat(u_c + n)] exactly (white n, linear
    plant). Variance: with white actuator noise the clipped drive is iid, N(u) = E[N] + g n + d
    (Bussgang) with white distortion d of variance Var(N) - g^2 s^2, so the prediction is exact."""
    text = """
name = "sat"
[sampling]
Ts = 0.01
[plant]
m = 1.0
c = 0.8
k = 3.0
[command]
kind = "step"
amplitude = 0.6
[actuator.white]
std = 0.3
[actuator.saturation]
limit = 0.75
"""
    mdl = load(text)
    trials, N = 4000, 400
    rec = mdl.simulate(N, seed=7, trials=trials)
    pr = mdl.predictor()
    mean = pr.mean_response(N)
    cov = pr.covariance(N)
    ks = np.array([10, 100, 399])
    count = 2 * ks.size
    z = z_bound(count)
    assert np.all(np.abs(rec.y[:, ks, 0].mean(0) - mean.y[ks, 0]) < z * np.sqrt(cov.Sy[ks, 0] / trials))
    # the clipper is active here (0.6 + 0.3 n > 0.75 for n > 0.5): the mean drive is not u_c
    assert mean.drive[5, 0] < 0.6 - 0.02
    assert np.all(mean.distortion_var[5:] > 0.003)
    emp = rec.y[:, ks, 0].var(0, ddof=1)
    lo, hi = chi2_band(cov.Sy[ks, 0], trials, count)
    assert np.all((emp > lo) & (emp < hi)), emp / cov.Sy[ks, 0]
    # without the distortion term the prediction would be clearly low
    no_d = cov.Sy[ks, 0] - cov.parts["actuator.saturation"][ks, 0]
    assert np.all(emp > no_d * 1.05)


def _ensemble_welch(mdl, k0: int, n: int, trials: int, L: int, seed: int = 11):
    """(predictor, residuals about the predicted mean (trials, n), Welch f, per-trial Welch
    spectra (trials, nf)) of ``trials`` records of k0 + n samples, the first k0 dropped."""
    from scipy.signal import welch

    rec = mdl.simulate(k0 + n, seed=seed, trials=trials)
    pr = mdl.predictor()
    r = rec.y[:, k0:, 0] - pr.mean_response(k0 + n).y[k0:, 0]
    f, P = welch(r, fs=1 / mdl.Ts, nperseg=L, axis=-1, detrend=False)
    return pr, r, f, P


def _band_power(P: np.ndarray, band: np.ndarray):
    """The trials' mean power in the band's bins and its standard error (from the trials' spread)."""
    per_trial = P[:, band].sum(axis=1)
    return per_trial.mean(), per_trial.std(ddof=1) / np.sqrt(P.shape[0])


def _predicted_welch(pr, L: int) -> np.ndarray:
    """The predicted expected Welch spectrum of output 0, all effects summed."""
    return sum(v[:, 0] for v in pr.expected_welch(L).values() if v is not None)


AR1_THROUGH_A_SATURATION = """
name = "ar1sat"
[sampling]
Ts = 0.005
[plant]
A = [[0.0, 1.0], [-16.0, -2.0]]
B = [[0.0], [16.0]]
C = [[1.0, 0.0]]
[command]
kind = "chirp"
amplitude = 0.8
f0_hz = 0.1
f1_hz = 3.0
duration_s = 25
[actuator.ar1]
std = 0.05
rho = 0.98
[actuator.saturation]
limit = 0.7
"""


@pytest.mark.slow
def test_ar1_actuator_noise_through_a_saturation_the_command_reaches_has_the_gains_spectrum():
    """A chirp through the limit switches the clipper's gain g_k (1 inside, 0 beyond) many times
    within the AR(1)'s correlation time (0.25 s): the clipped noise g_k n_k has autocovariance
    R_g(d) R_n(d) over time, wider than the rms gain on n's own spectrum. The prediction (mean gain
    on n's spectrum + the fluctuation's spectrum fitted by damped cosines) against an ensemble's
    Welch spectrum, band by band where the output carries it (below 5 Hz; the plant's resonance is
    at 0.64 Hz), and against the variance.

    Tolerance: the estimate's own spread (4 standard errors, from the trials' band powers) plus
    10 %, the linearization's bound in these bands (the gain's spectrum is fitted by at most four
    blocks: measured 2-8 % here). The rms gain alone (the
    prediction before) is off by 10-82 % in the same bands: asserted to fail where it is clear."""
    mdl = load(AR1_THROUGH_A_SATURATION)
    trials, L = 100, 1000
    pr, r, f, P = _ensemble_welch(mdl, 1000, 10000, trials, L)

    rms_only = mdl.predictor()
    rms_only._gain_shadows = lambda gain: {}           # the rms gain on n's own spectrum
    new, old = _predicted_welch(pr, L), _predicted_welch(rms_only, L)
    assert any("gain switches" in s for s in pr.steady_state().notes)
    bands = ((0.2, 0.6), (0.6, 1.2), (1.2, 2.0), (2.0, 3.0), (3.0, 5.0))
    z = z_bound(len(bands) + 1)
    off_before = []
    for lo, hi in bands:
        s = (f >= lo) & (f < hi)
        emp, se = _band_power(P, s)
        tol = 0.10 * new[s].sum() + z * se
        assert abs(emp - new[s].sum()) < tol, (lo, hi, emp / new[s].sum())
        off_before.append(abs(emp / old[s].sum() - 1.0))
    # before: 22 % high at the lowest band, 82 % low at 3-5 Hz (its spectrum too narrow)
    assert off_before[0] > 0.15 and off_before[-1] > 0.5, off_before
    # the variance: the ensemble's time-averaged one (var of a mean over 10^6 correlated samples:
    # se from the trials' variances)
    v = r.var(axis=1)
    se = v.std(ddof=1) / np.sqrt(trials)
    var_new, var_old = pr.steady_state().var_y[0], rms_only.steady_state().var_y[0]
    assert abs(v.mean() - var_new) < 0.05 * var_new + z * se, v.mean() / var_new
    assert abs(v.mean() / var_old - 1.0) > 0.15, v.mean() / var_old


AR1_SATURATED_WITH_FEEDTHROUGH = """
name = "ar1sat_d"
[sampling]
Ts = 0.005
[plant]
A = [[0.0, 1.0], [-25.0, -4.0]]
B = [[0.0], [25.0]]
C = [[1.0, 0.0]]
D = [[0.05]]
[command]
kind = "sine"
amplitude = 1.0
frequency_hz = 0.5
[sensor.white]
std = 0.0007
[actuator.ar1]
std = 0.1
tau_s = 0.5
[actuator.saturation]
limit = 0.8
"""


@pytest.mark.slow
def test_the_distortion_of_a_colored_noise_through_a_saturation_is_colored():
    """A slow AR(1) (tau 0.5 s = 100 samples) clipped at 0.8 by a 1.0 sine: the distortion
    d_k = f(u_k + n_k) - E[f] - g_k n_k is as slow as the noise near the limit (by Mehler's formula
    its Hermite terms decay as rho(d)^j, j >= 2), not white. A feed-through D = 0.05 puts it on
    the output above the plant's 0.8 Hz resonance, over a sensor noise of 0.0007: taken as white,
    its share of the prediction there is spread up to Nyquist and the prediction reads 1.2-1.9x the
    ensemble's spectrum above 12 Hz (an audit model: a lag was added to its own truth at Delta BIC
    2400). Colored (:meth:`Predictor._distortion_colors`), against an ensemble's Welch spectrum,
    band by band from 5 Hz to Nyquist and in variance.

    Tolerance: 4 standard errors of the trials' band powers plus 5 % (the fit of the distortion's
    autocovariance by four damped cosines and a white part). The white distortion is asserted
    to fail by more than 15 % in the bands above 20 Hz. Below 5 Hz the gain fluctuation's fit
    (four blocks for a pattern that repeats at 1 Hz) ripples by up to 20 % between 1 and 3 Hz,
    as before: those bands are the other test's subject, on a chirp."""
    mdl = load(AR1_SATURATED_WITH_FEEDTHROUGH)
    trials, L = 60, 1000
    pr, r, f, P = _ensemble_welch(mdl, 2000, 12000, trials, L)

    white = mdl.predictor()
    white._distortion_colors = lambda u, dvar: {}        # the distortion as white noise (before)
    new, old = _predicted_welch(pr, L), _predicted_welch(white, L)
    assert any("distortion of input 0's colored noise is colored" in s for s in pr.steady_state().notes)
    bands = ((5.0, 8.0), (8.0, 12.0), (12.0, 20.0), (20.0, 35.0), (35.0, 60.0), (60.0, 100.0))
    z = z_bound(len(bands) + 1)
    for lo, hi in bands:
        s = (f >= lo) & (f < hi)
        emp, se = _band_power(P, s)
        assert abs(emp - new[s].sum()) < 0.05 * new[s].sum() + z * se, (lo, hi, emp / new[s].sum())
        if lo >= 20.0:
            assert abs(emp / old[s].sum() - 1.0) > 0.15, (lo, hi, emp / old[s].sum())
    v = r.var(axis=1)
    se = v.std(ddof=1) / np.sqrt(trials)
    var_new = pr.steady_state().var_y[0]
    assert abs(v.mean() - var_new) < 0.05 * var_new + z * se, v.mean() / var_new


def test_step_and_batch_give_the_same_sample_path_for_every_effect():
    mdl = load(EVERYTHING)
    N = 5000
    rec = mdl.simulate(N, seed=99, block=777)    # odd block size: state carried across blocks
    st = mdl.stepper(seed=99)
    out = [st.step() for _ in range(N)]
    t = np.array([o[0] for o in out])
    x = np.array([o[1] for o in out])
    u = np.array([o[2] for o in out])
    y = np.array([o[3] for o in out])
    np.testing.assert_array_equal(t, rec.t)
    np.testing.assert_array_equal(u, rec.u)
    # the plant runs in Schur coordinates in batch: equal to rounding
    np.testing.assert_allclose(x, rec.x, rtol=0, atol=1e-12 * np.abs(rec.x).max())
    # quantized outputs: identical (a flip would need the two paths to straddle a level, ~1e-13 odds)
    np.testing.assert_array_equal(y, rec.y)
    # and a different seed gives a different path
    assert not np.array_equal(mdl.simulate(N, seed=100).y, rec.y)


def test_block_size_does_not_change_the_path():
    mdl = load(ALL_LINEAR)
    a = mdl.simulate(3000, seed=4, block=3000).y
    b = mdl.simulate(3000, seed=4, block=64).y
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-13)


def test_a_damped_cosine_fit_that_stalled_scipys_nnls_still_holds_the_variance(monkeypatch):
    """An autocovariance met in a diagnosis (tests/data: the distortion of an AR(1) behind a
    saturation, a variant of an audit model) on which scipy 1.17's nnls at its default iteration
    limit raised RuntimeError, which ended the diagnosis with a traceback. The fit goes on (more
    iterations, else bounded-variable least squares): its weights are non-negative, hold the
    variance h(0), and the blocks' spectrum follows h's within 5 % up to Nyquist (measured 1.6 %).
    Checked as scipy runs it here, and with nnls made to fail always (the fallback alone, whatever
    a later scipy does on this problem)."""
    import scipy.optimize
    from noiselab.model.spectra import _damped_cosines

    path = Path(__file__).resolve().parents[1] / "data" / "distortion_acf_nnls_maxiter.txt"
    h = np.loadtxt(path)
    rad = float(path.read_text().split("rad ")[1].split(",")[0])
    d = np.arange(h.size)
    w = np.linspace(0.0, np.pi, 50)

    def spec(a):
        return a[0] + 2 * np.cos(np.outer(w, d[1:])) @ a[1:]

    def check():
        white, comps = _damped_cosines(h, rad, 1500, 0.02, 0, 1, white=True)
        assert white >= 0 and comps
        var, acf = white, np.zeros(h.size)
        acf[0] = white
        for F, G, _, _ in comps:
            ev = np.linalg.eigvals(F)[0]
            wk = G[0, 0] ** 2 / (1 - abs(ev) ** 2)
            var += wk
            acf += wk * abs(ev) ** d * np.cos(np.angle(ev) * d)
        assert var == pytest.approx(h[0], rel=1e-6)
        assert np.max(np.abs(spec(acf) / spec(h) - 1)) < 0.05

    check()

    def stalls(A, b, **kw):
        raise RuntimeError("Maximum number of iterations reached.")
    monkeypatch.setattr(scipy.optimize, "nnls", stalls)
    check()
