"""Allan-family deviations (noiselab.stats.allan) against published values and a peer.

Sources, each kept next to its numbers:
- NBS14 9-point frequency / 10-point phase set and the 1000-point set: NIST SP 1065 (W. J.
  Riley, Handbook of Frequency Stability Analysis, 2008), sec. 12 test suites, 7 significant
  figures; the same numbers are in W. J. Riley, "The Calculation of Time Domain Frequency
  Stability" (wriley.com/paper1ht.htm, table III) and in allantools tests/nbs14/.
- Real OCXO data and Stable32 1.60 tables: tests/data/ocxo/ (see its README for provenance and
  for why the octave tables need Stable32's own input precision reproduced).
- allantools 2024.6 as a peer on random data.
"""

from __future__ import annotations

import math

import allantools
import numpy as np
import pytest
from helpers.allan_reference import BOUNDS_RTOL, half_unit, ocxo_frequency, ocxo_y, read_stable32
from scipy import stats

from noiselab.stats import (
    StatsError,
    adev,
    chi2_bounds,
    edf_greenhall,
    mdev,
    noise_id_lag1,
    oadev,
    oadev_from_phase,
)

# --------------------------------------------------------------------------------------------
# NBS14 test suites


# NIST SP 1065 sec. 12, NBS14 9-point frequency data and its 10-point phase (rounded to 5
# decimals in the publication).
NBS14_FREQ = [892.0, 809.0, 823.0, 798.0, 671.0, 644.0, 883.0, 903.0, 677.0]
NBS14_PHASE = [0.0, 103.11111, 123.22222, 157.33333, 166.44444, 48.55555, -96.33333, -2.22222, 111.88889, 0.0]
# Published deviations at tau = 1, 2 (SP 1065 table for the 9-point set; Riley paper1 table I).
NBS14_10 = {
    "adev": (91.22945, 115.8082),
    "oadev": (91.22945, 85.95287),
    "mdev": (91.22945, 74.78849),
}
# 1000-point set at tau = 1, 10, 100 (SP 1065 table for the 1000-point set; Riley paper1
# table III), with the number of terms.
NBS14_1000 = {
    "adev": ((2.922319e-01, 9.965736e-02, 3.897804e-02), (999, 99, 9)),
    "oadev": ((2.922319e-01, 9.159953e-02, 3.241343e-02), (999, 981, 801)),
    "mdev": ((2.922319e-01, 6.172376e-02, 2.170921e-02), (999, 972, 702)),
}
FUNCS = {"adev": adev, "oadev": oadev, "mdev": mdev}


def nbs14_1000() -> np.ndarray:
    """The 1000-point set: n_0 = 1234567890, n_{i+1} = 16807 n_i mod 2147483647 (the
    'minimal standard' LCG; Riley paper1 and SP 1065), y_i = n_i / 2147483647."""
    n = [1234567890]
    for _ in range(999):
        n.append((16807 * n[-1]) % 2147483647)
    assert n[1:4] == [395529916, 1209410747, 633705974]  # the three values the paper prints
    return np.array(n, dtype=np.float64) / 2147483647.0


@pytest.mark.parametrize("kind", ["adev", "oadev", "mdev"])
def test_nbs14_10_point(kind):
    ref = np.array(NBS14_10[kind])
    r = FUNCS[kind](NBS14_FREQ, 1.0, taus=[1.0, 2.0])
    np.testing.assert_array_equal(r.taus, [1.0, 2.0])
    assert np.all(np.abs(r.dev - ref) <= half_unit(ref, 7))


def test_nbs14_10_point_from_phase():
    ref = np.array(NBS14_10["oadev"])
    r = oadev_from_phase(NBS14_PHASE, 1.0, taus=[1.0, 2.0])
    # the published phase is rounded to 5e-6; each second difference moves by <= 4 * 5e-6,
    # so the deviation by <= 4 * 5e-6 / (sqrt(2) tau)
    phase_rounding = 4 * 5e-6 / (np.sqrt(2.0) * r.taus)
    assert np.all(np.abs(r.dev - ref) <= half_unit(ref, 7) + phase_rounding)
    # and the phase path equals the rate path on the same data
    x = np.concatenate([[0.0], np.cumsum(NBS14_FREQ)])
    from_phase = oadev_from_phase(x, 1.0, taus=[1.0, 2.0]).dev
    np.testing.assert_allclose(from_phase, oadev(NBS14_FREQ, 1.0, taus=[1, 2]).dev, rtol=1e-13)


@pytest.mark.parametrize("kind", ["adev", "oadev", "mdev"])
def test_nbs14_1000_point(kind):
    devs, ns = NBS14_1000[kind]
    ref = np.array(devs)
    r = FUNCS[kind](nbs14_1000(), 1.0, taus=[1.0, 10.0, 100.0])
    np.testing.assert_array_equal(r.n, ns)
    assert np.all(np.abs(r.dev - ref) <= half_unit(ref, 7))


# --------------------------------------------------------------------------------------------
# Stable32 on real OCXO data


def ocxo_y_as_stable32_phase() -> np.ndarray:
    """The rate Stable32 effectively saw for its octave oadev/mdev tables: it read f / 1e7
    (header 'Average = 1.000000e+00') and integrated it to phase x_k = sum_{i<k} f_i/1e7 in
    float64. Differencing that phase (exact: neighbouring floats, Sterbenz) returns the rate
    with the phase's rounding in it; its offset of 1 does not matter to any estimator."""
    x = np.concatenate([[0.0], np.cumsum(ocxo_frequency() / 1e7)])
    return np.diff(x) - 1.0


def stable32_adev_offset_sum(m: int) -> float:
    """adev as Stable32 computed its octave table: m-averages of f / 1e7 by plain sequential
    summation in float64 (a Python loop, like a C loop), then the Allan variance."""
    v = (ocxo_frequency() / 1e7).tolist()
    means = []
    for k in range(len(v) // m):
        acc = 0.0
        for val in v[k * m : (k + 1) * m]:
            acc += val
        means.append(acc / m)
    d = np.diff(np.array(means))
    return float(np.sqrt(0.5 * np.mean(d * d)))


def test_ocxo_oadev_all_tau():
    """273 averaging factors, Stable32 on the fractional frequency: Sigma to its printed
    5 digits, '#' and the identified Alpha exactly."""
    t = read_stable32("stable32_oadev_alltau.txt")
    r = oadev(ocxo_y(), 1.0, taus=t["tau"])
    np.testing.assert_array_equal(r.m, t["m"])
    np.testing.assert_array_equal(r.n, t["n"])
    assert np.all(np.abs(r.dev - t["dev"]) <= half_unit(t["dev"], 5) * (1 + 1e-9))
    assert np.max(np.abs(r.dev / t["dev"] - 1)) < 1e-4
    mismatched = [(int(m), int(a), int(b)) for m, a, b in zip(t["m"], t["alpha"], r.alpha) if a != b]
    assert mismatched == []
    # both identification regimes are exercised: lag-1 ACF (>= 30 averages) and B1/carry
    n_avg = 19982 // t["m"]
    assert np.sum(n_avg >= 30) == 167 and np.sum(n_avg < 30) == 106


@pytest.mark.parametrize("name, func", [("oadev_octave.txt", oadev), ("mdev_octave.txt", mdev)])
def test_ocxo_octave_tables(name, func):
    """Octave tables, on the input Stable32 had (see ocxo_y_as_stable32_phase)."""
    t = read_stable32(name)
    r = func(ocxo_y_as_stable32_phase(), 1.0, taus="octave")
    np.testing.assert_array_equal(r.m, t["m"])  # same octave list, up to N/4
    np.testing.assert_array_equal(r.n, t["n"])
    assert np.all(np.abs(r.dev - t["dev"]) <= half_unit(t["dev"], 5) * (1 + 1e-9))
    np.testing.assert_array_equal(r.alpha, t["alpha"])
    np.testing.assert_allclose(r.lo, t["lo"], rtol=BOUNDS_RTOL)
    np.testing.assert_allclose(r.hi, t["hi"], rtol=BOUNDS_RTOL)
    # and on the exact fractional frequency the table is off by Stable32's precision loss
    exact = func(ocxo_y(), 1.0, taus="octave")
    assert 3e-4 < np.max(np.abs(exact.dev / t["dev"] - 1)) < 2e-3


def test_ocxo_adev_octave_table():
    t = read_stable32("adev_octave.txt")
    r = adev(ocxo_y(), 1.0, taus="octave")
    np.testing.assert_array_equal(r.m, t["m"])  # octave list up to N/5
    np.testing.assert_array_equal(r.n, t["n"])
    np.testing.assert_array_equal(r.alpha, t["alpha"])
    # Stable32 summed values near 1.0 (see stable32_adev_offset_sum). Its own error, measured by
    # redoing its arithmetic, is allowed on top of the printing; the redone arithmetic must
    # itself reproduce the printed table.
    s32 = np.array([stable32_adev_offset_sum(int(m)) for m in t["m"]])
    assert np.all(np.abs(s32 - t["dev"]) <= half_unit(t["dev"], 5) * (1 + 1e-9))
    own_error = np.abs(s32 - r.dev)
    assert np.all(np.abs(r.dev - t["dev"]) <= half_unit(t["dev"], 5) + own_error)
    assert np.max(np.abs(r.dev / t["dev"] - 1)[:-1]) < 1e-4  # all but m = 2048 within 1e-4
    np.testing.assert_allclose(r.lo, t["lo"], rtol=BOUNDS_RTOL)
    np.testing.assert_allclose(r.hi, t["hi"], rtol=BOUNDS_RTOL)


def test_ocxo_bounds_with_stable32_alpha_and_sigma():
    """The bounds from Stable32's own Sigma and Alpha: isolates the EDF + chi-squared step."""
    for name, shape in [
        ("adev_octave.txt", (False, False)),
        ("oadev_octave.txt", (True, False)),
        ("mdev_octave.txt", (True, True)),
    ]:
        t = read_stable32(name)
        edf = [
            edf_greenhall(int(a), 2, int(m), 19983, overlapping=shape[0], modified=shape[1])
            for a, m in zip(t["alpha"], t["m"])
        ]
        lo, hi = chi2_bounds(t["dev"], edf, 0.683)
        np.testing.assert_allclose(lo, t["lo"], rtol=BOUNDS_RTOL)
        np.testing.assert_allclose(hi, t["hi"], rtol=BOUNDS_RTOL)


# --------------------------------------------------------------------------------------------
# allantools as a peer


@pytest.mark.parametrize("kind", ["adev", "oadev", "mdev"])
def test_matches_allantools_on_random_data(kind):
    rng = np.random.default_rng(20240601)
    white = rng.standard_normal(6000)
    y = 3e-9 * white + 1e-11 * np.cumsum(rng.standard_normal(6000)) + 1e-7  # offset, WFM + RWFM
    ours = FUNCS[kind](y, 10.0, taus="all")
    peer = getattr(allantools, kind)
    taus, dev, _, n = peer(y, rate=10.0, data_type="freq", taus=ours.taus)
    np.testing.assert_array_equal(taus, ours.taus)
    np.testing.assert_array_equal(n, ours.n)
    np.testing.assert_allclose(ours.dev, dev, rtol=1e-9, atol=0)


def test_oadev_from_phase_matches_allantools():
    rng = np.random.default_rng(7)
    x = np.cumsum(rng.standard_normal(3001)) * 1e-9 + 1e-12 * np.arange(3001) ** 2
    ours = oadev_from_phase(x, 1.0, taus="octave")
    taus, dev, _, n = allantools.oadev(x, rate=1.0, data_type="phase", taus=ours.taus)
    np.testing.assert_array_equal(n, ours.n)
    np.testing.assert_allclose(ours.dev, dev, rtol=1e-9)


# --------------------------------------------------------------------------------------------
# EDF and confidence intervals


def test_edf_matches_allantools_reference():
    """Greenhall & Riley (2003) EDF against allantools.edf_greenhall, every case it covers."""
    checked = 0
    for n_phase in (40, 513, 20001):
        for m in (1, 2, 3, 7, 16, 33, 34, 100, 128):
            for modified in (False, True):
                for overlapping in (False, True):
                    if modified and not overlapping:
                        continue
                    for alpha in (2, 1, 0, -1, -2):
                        filter_length = 3 * m if modified else 2 * m + 1  # L = m/F + m d
                        if n_phase < filter_length + 1:
                            continue
                        try:
                            ref = allantools.edf_greenhall(
                                alpha, 2, m, n_phase, overlapping=overlapping, modified=modified
                            )
                        except NotImplementedError:
                            continue
                        ours = edf_greenhall(alpha, 2, m, n_phase, overlapping=overlapping, modified=modified)
                        assert ours == pytest.approx(ref, rel=1e-12), (n_phase, m, modified, overlapping, alpha)
                        checked += 1
    assert checked > 250


@pytest.mark.parametrize("d", [1, 2, 3])
@pytest.mark.parametrize("overlapping", [False, True])
def test_edf_white_pm_exact(d, overlapping):
    """Case 4 (unmodified, white PM) against the brute-force chi-squared edf of the estimator:
    for white x the terms z_n = sum_k c_k x_{n S' + k m} are jointly Gaussian with covariance
    from their coefficient vectors; edf = 2 E[V]^2 / Var[V] = M^2 / sum_{n,n'} rho_{nn'}^2.
    Includes few-term cases (K <= d) that allantools does not implement."""
    for m, n_phase in [(1, 12), (2, 11), (3, 40), (5, 23), (4, 4 * d + 2)]:
        stride = 1 if overlapping else m
        coef = np.array([(-1) ** k * math.comb(d, k) for k in range(d + 1)], dtype=float)
        starts = np.arange(0, n_phase - d * m, stride)
        A = np.zeros((starts.size, n_phase))
        for i, s in enumerate(starts):
            A[i, s + m * np.arange(d + 1)] = coef
        cov = A @ A.T
        rho = cov / cov[0, 0]
        brute = starts.size**2 / np.sum(rho**2)
        ours = edf_greenhall(2, d, m, n_phase, overlapping=overlapping, modified=False)
        assert ours == pytest.approx(brute, rel=1e-12), (m, n_phase)


@pytest.mark.parametrize("alpha", [0, -2])
def test_interval_coverage(alpha):
    """68.3 % and 95 % intervals of oadev cover the true sigma at their rate (white FM:
    sigma^2 = s^2/m; random-walk FM y_k = y_{k-1} + w_k: sigma^2 = s^2 (2 m^2 + 1)/(6 m))."""
    rng = np.random.default_rng(100 + alpha)
    runs, n = 400, 1024
    ms = np.array([4, 16])
    truth = 1.0 / np.sqrt(ms) if alpha == 0 else np.sqrt((2 * ms**2 + 1) / (6.0 * ms))
    hits = {0.683: np.zeros(ms.size), 0.95: np.zeros(ms.size)}
    for _ in range(runs):
        w = rng.standard_normal(n)
        y = w if alpha == 0 else np.cumsum(w)
        r = oadev(y, 1.0, taus=ms, alpha=alpha)
        for conf in hits:
            lo, hi = r.bounds(conf)
            hits[conf] += (lo <= truth) & (truth <= hi)
    for conf, h in hits.items():
        # binomial 99.9 % acceptance region for the count of covering runs
        lo_n, hi_n = stats.binom.ppf([0.0005, 0.9995], runs, conf)
        assert np.all((h >= lo_n) & (h <= hi_n)), (conf, h / runs)


# --------------------------------------------------------------------------------------------
# noise identification


@pytest.mark.parametrize(
    "alpha, make",
    [
        (2, lambda w: np.diff(w)),  # white PM: y is the difference of white phase
        (0, lambda w: w[1:]),  # white FM
        (-2, lambda w: np.cumsum(w[1:])),  # random-walk FM
    ],
)
def test_noise_id_pure_power_laws(alpha, make):
    w = np.random.default_rng(5).standard_normal(2**15 + 1)
    y = make(w)
    r = oadev(y, 1.0, taus=2 ** np.arange(0, 9))  # >= 128 averages at every tau: lag-1 ACF
    np.testing.assert_array_equal(r.alpha, alpha)
    # the float estimate of the lag-1 method is within 0.25 of the true exponent on the
    # 2^15-point series (its standard error there is ~0.01)
    assert abs(noise_id_lag1(y)[1] - alpha) < 0.25


# --------------------------------------------------------------------------------------------
# arguments


def test_octave_and_all_stop_at_stable32_limits():
    y = np.zeros(1000) + np.random.default_rng(0).standard_normal(1000)
    assert adev(y, 1.0).m.tolist() == [1, 2, 4, 8, 16, 32, 64, 128]  # <= N/5 = 200
    assert oadev(y, 1.0).m.tolist() == [1, 2, 4, 8, 16, 32, 64, 128]  # <= N/4 = 250
    assert oadev(y, 1.0, taus="all").m.tolist() == list(range(1, 251))
    assert np.allclose(oadev(y, 4.0, taus=[0.25, 1.0]).taus, [0.25, 1.0])


@pytest.mark.parametrize(
    "call, culprit",
    [
        (lambda: oadev([1.0, 2.0, np.nan, 4.0], 1.0), "y"),
        (lambda: oadev(np.ones(100), 0.0), "rate"),
        (lambda: oadev(np.ones(100), 1.0, taus=[1.5]), "taus"),
        (lambda: oadev(np.ones(100), 1.0, taus=[60.0]), "taus"),
        (lambda: oadev(np.ones(100), 1.0, taus="decade"), "taus"),
        (lambda: oadev(np.ones(100), 1.0, conf=1.2), "conf"),
        (lambda: oadev(np.ones(100), 1.0, taus=[1, 2], alpha=[0]), "alpha"),
        (lambda: edf_greenhall(-3, 1, 2, 100, overlapping=True, modified=False), "alpha"),
    ],
)
def test_bad_arguments_name_the_culprit(call, culprit):
    with pytest.raises(StatsError, match=f"^{culprit}:"):
        call()
