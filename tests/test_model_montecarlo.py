"""Monte Carlo ensembles (fixed seeds) against the predicted mean, P_k and S_y,k (issue 2).

Bounds: for n independent Gaussian trials, (n - 1) s^2 / sigma^2 ~ chi2(n - 1); a sample covariance
has variance (s_xx s_yy + s_xy^2) / (n - 1); a sample mean has variance sigma^2 / n. Every check
uses a two-sided family-wise level of 1e-3 (Bonferroni over the checks in the test).
"""

import numpy as np
import pytest
from scipy import stats

from models_for_tests import ALL_LINEAR, EVERYTHING, load
from service.model import load_model

ALPHA = 1e-3


def chi2_band(pred, n, count):
    a = ALPHA / count
    return (pred * stats.chi2.ppf(a / 2, n - 1) / (n - 1), pred * stats.chi2.ppf(1 - a / 2, n - 1) / (n - 1))


def z_bound(count):
    return stats.norm.ppf(1 - ALPHA / (2 * count))


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
