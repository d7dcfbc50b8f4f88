"""Closed forms (issue 2): Van Loan, ZOH, sigma_e^2 = (1 - rho^2) sigma_n^2, Var(b_k) = Var(b_0) + k Q_b,
Delta^2/12 where the uniform model holds and where it does not, exact Allan variance forms."""

import numpy as np
import pytest
from scipy import stats
from scipy.integrate import quad_vec
from scipy.linalg import expm

from noiselab.model import discretize, parse_model
from noiselab.model.linearize import gauss_pwl
from noiselab.model.spectra import allan_from_variogram


def model(body: str, Ts=0.01, disc="zoh", plant="m = 1.0\nc = 0.4\nk = 2.0"):
    return parse_model(f'name = "t"\n[sampling]\nTs = {Ts}\ndiscretization = "{disc}"\n[plant]\n{plant}\n{body}', "test")


DOUBLE_INTEGRATOR = "A = [[0.0, 1.0], [0.0, 0.0]]\nB = [[0.0], [1.0]]\nC = [[1.0, 0.0]]"


@pytest.mark.parametrize("Ts", [1e-3, 0.01, 0.5])
def test_van_loan_double_integrator(Ts):
    """Q_d = q [[Ts^3/3, Ts^2/2], [Ts^2/2, Ts]] for white acceleration of intensity q."""
    q = 0.7
    A = np.array([[0.0, 1.0], [0.0, 0.0]])
    Qc = q * np.array([[0.0, 0.0], [0.0, 1.0]])
    expect = q * np.array([[Ts**3 / 3, Ts**2 / 2], [Ts**2 / 2, Ts]])
    np.testing.assert_allclose(discretize.van_loan(A, Qc, Ts), expect, rtol=1e-12, atol=0)
    # the same through a model file: [process.white] psd on a general plant
    mdl = model(f"[process.white]\npsd = {q}", Ts=Ts, plant=DOUBLE_INTEGRATOR)
    np.testing.assert_allclose(mdl.S_proc @ mdl.S_proc.T, expect, rtol=1e-10, atol=1e-18)
    assert not np.allclose(expect, Qc), "Q_d = Q_c would be the dimensional mistake of section 8"


def test_van_loan_against_quadrature_and_first_order():
    A = np.array([[0.0, 1.0], [-4.0 / 1.2, -0.35 / 1.2]])
    L = np.array([[0.0], [1 / 1.2]])
    Qc = L @ L.T * 0.3
    Ts = 0.05
    integ, _ = quad_vec(lambda s: expm(A * s) @ Qc @ expm(A.T * s), 0.0, Ts, epsabs=1e-16, epsrel=1e-13)
    np.testing.assert_allclose(discretize.van_loan(A, Qc, Ts), integ, rtol=1e-10)
    # Q_d ~ Q_c Ts to first order: the relative error shrinks linearly with Ts
    errs = [np.linalg.norm(discretize.van_loan(A, Qc, h) - Qc * h) / np.linalg.norm(Qc * h) for h in (1e-3, 1e-4)]
    assert errs[1] < errs[0] / 5


def test_zoh_closed_form():
    A = np.array([[0.0, 1.0], [-3.0, -0.5]])
    B = np.array([[0.0], [2.0]])
    Ts = 0.02
    Ad, Bd = discretize.zoh(A, B, Ts)
    np.testing.assert_allclose(Ad, expm(A * Ts), rtol=1e-13)
    np.testing.assert_allclose(Bd, np.linalg.solve(A, (Ad - np.eye(2)) @ B), rtol=1e-10)
    Ae, Be = discretize.euler(A, B, Ts)
    np.testing.assert_allclose(Ae, np.eye(2) + Ts * A)
    np.testing.assert_allclose(Be, Ts * B)


def test_process_std_held_over_the_sample():
    """process.white std is a zero-order-held input: G_d = int e^{As} ds L (zoh), Ts L (euler)."""
    mz = model("[process.white]\nstd = 0.2")
    _, Gd = discretize.zoh(mz.Ac, mz.L, mz.Ts)
    np.testing.assert_allclose(mz.S_proc, 0.2 * Gd)
    me = model("[process.white]\nstd = 0.2", disc="euler")
    np.testing.assert_allclose(me.S_proc, 0.2 * 0.01 * me.L)


def test_ar1_innovation_variance_and_tau():
    mdl = model("[actuator.ar1]\nstd = 0.08\nrho = 0.97")
    eff = mdl.effects["actuator.ar1"]
    assert eff.c[0] ** 2 == pytest.approx((1 - 0.97**2) * 0.08**2, rel=1e-15)   # sigma_e^2 = (1-rho^2) sigma_n^2
    tau = model("[actuator.ar1]\nstd = 0.08\ntau_s = 0.25").effects["actuator.ar1"]
    assert tau.rho[0] == pytest.approx(np.exp(-0.01 / 0.25), rel=1e-15)
    # the stationary variance of the simulated noise is std^2: drive = u_c + n with u_c = 0
    rec = mdl.simulate(400_000, seed=5)
    n = rec.drive[20_000:, 0]
    # AR(1): Var of the sample variance ~ 2 s^4 (1 + rho^2) / (N (1 - rho^2))
    N = n.size
    sd = 0.08**2 * np.sqrt(2 * (1 + 0.97**2) / (N * (1 - 0.97**2)))
    assert abs(np.var(n) - 0.08**2) < 4 * sd
    # and the lag-1 correlation is rho (std of the estimate ~ sqrt((1 - rho^2) / N))
    r1 = np.corrcoef(n[:-1], n[1:])[0, 1]
    assert abs(r1 - 0.97) < 4 * np.sqrt((1 - 0.97**2) / N * (1 + 0.97**2) / (1 - 0.97**2))


@pytest.mark.slow
def test_bias_walk_variance_grows_linearly_monte_carlo():
    """Var(b_k) = Var(b_0) + k Q_b (seed section 6.2), Q_b = std^2 Ts, checked on an ensemble."""
    std, init, Ts = 0.002, 0.003, 0.01
    mdl = model(f"[sensor.bias_walk]\nstd = {std}\ninitial_std = {init}", plant="m = 1.0\nc = 1.0\nk = 1.0")
    trials = 4000
    rec = mdl.simulate(1000, seed=11, trials=trials)
    b = rec.y[:, :, 0]          # no other noise, no command: y = b
    ks = np.array([0, 1, 10, 100, 500, 999])
    pred = init**2 + ks * std**2 * Ts
    emp = np.var(b[:, ks], axis=0, ddof=1)
    # (n-1) s^2 / sigma^2 ~ chi2(n-1); two-sided 99.9 % per k, Bonferroni over the k's
    a = 1e-3 / ks.size
    lo = pred * stats.chi2.ppf(a / 2, trials - 1) / (trials - 1)
    hi = pred * stats.chi2.ppf(1 - a / 2, trials - 1) / (trials - 1)
    assert np.all((emp > lo) & (emp < hi)), (emp, lo, hi)
    cov = mdl.predictor().covariance(1000)
    np.testing.assert_allclose(cov.Sy[ks, 0], pred, rtol=1e-12)


def test_quantization_uniform_model_holds_for_a_busy_signal():
    """Delta^2/12 when the signal spans many steps: the error y_q - y has that variance, zero mean,
    and is uncorrelated with the signal."""
    step = 0.001
    base = "[sensor.white]\nstd = 0.02\n"
    m_q = model(base + f"[sensor.quantization]\nstep = {step}")
    m_a = model(base)
    n = 200_000
    yq = m_q.simulate(n, seed=3).y[:, 0]
    ya = m_a.simulate(n, seed=3).y[:, 0]
    e = yq - ya
    assert np.all(np.abs(e) <= step / 2 + 1e-15)
    var = step**2 / 12
    # the variance of a uniform's sample variance: (Delta^4/80 - Delta^4/144) / n
    sd = np.sqrt((step**4 / 80 - step**4 / 144) / n)
    assert abs(np.var(e) - var) < 4 * sd
    assert abs(np.mean(e)) < 4 * np.sqrt(var / n)
    assert abs(np.corrcoef(e, ya)[0, 1]) < 4 / np.sqrt(n)
    st = m_q.predictor().steady_state()
    assert st.contributions["sensor.quantization"][0] == pytest.approx(var)
    assert not any("quantization" in note for note in st.notes)


def test_quantization_uniform_model_fails_for_a_slow_signal_locked_to_the_grid():
    """A slow, noise-free signal smaller than a step: the quantizer outputs 0 for most samples, the
    error is minus the signal, signal dependent, and its variance is not Delta^2/12. The predictor
    says the uniform model may not hold."""
    step = 0.01
    mdl = model(f'[command]\nkind = "sine"\namplitude = 0.002\nfrequency_hz = 0.05\n'
                f"[sensor.quantization]\nstep = {step}", plant="m = 1.0\nc = 2.0\nk = 1.0")
    rec = mdl.simulate(100_000, seed=1)
    exact = mdl.predictor().mean_response(100_000).y[:, 0]
    e = rec.y[:, 0] - exact
    assert np.all(rec.y[:, 0] == 0.0)                 # locked: every sample rounds to the same level
    np.testing.assert_allclose(e, -exact, atol=1e-15)  # the error is the signal, not independent noise
    assert abs(np.var(e) / (step**2 / 12) - 1) > 0.5
    notes = mdl.predictor().steady_state().notes
    assert any("quantization" in note and "may not hold" in note for note in notes)


@pytest.mark.parametrize("sigma_over_step,rho,motion", [(0.6, 0.95, "sine"), (0.8, 0.99, "none"),
                                                          (0.05, 0.0, "ramp")])
def test_quantization_error_autocovariance_monte_carlo(sigma_over_step, rho, motion):
    """R_e(d) of quantization_acf against the quantizer's error simulated directly: x_k = mu_k +
    a Gaussian AR(1) of std sigma (gamma(d) = sigma^2 (1 - rho^d)), or a white dither (rho = 0),
    with a deterministic motion mu (a sine crossing ~7 steps per period; a ramp of 0.13 step per
    sample, whose error with a small dither is a sawtooth). The error e_k = Q(x_k) - x_k is
    correlated at short lags (0.5 to 0.9 at lag 1 here); every lag up to 60 must be within 5
    standard errors (Bartlett's, from the predicted autocovariance) of the prediction."""
    from noiselab.model.effects.sensor_quantization import quantization_acf

    step, n, L = 0.1, 200_000, 61
    rng = np.random.default_rng(7)
    sigma = sigma_over_step * step
    k = np.arange(n)
    mu = {"sine": 0.35 * np.sin(2 * np.pi * k / 997.0), "none": np.zeros(n), "ramp": 0.013 * k}[motion]
    e_ = rng.standard_normal(n) * sigma
    if rho > 0:                                        # stationary AR(1) of std sigma from its first sample
        from scipy.signal import lfilter
        x = lfilter([np.sqrt(1 - rho**2)], [1, -rho], e_[1:], zi=[rho * e_[0]])[0]
        x = np.concatenate([[e_[0]], x])
    else:
        x = e_
    sig = mu + x
    err = step * np.rint(sig / step) - sig
    d = np.arange(L)
    gamma = (sigma**2 * (1 - rho ** d) if rho > 0 else np.where(d > 0, sigma**2, 0.0))[:, None]
    R = quantization_acf([step], gamma, None if motion == "none" else mu[:, None])[:, 0]
    ec = err - err.mean()
    emp = np.array([np.mean(ec[h:] * ec[:n - h]) for h in d])
    # Bartlett: Var(r(h)) ~ (1/n) sum_j [R(j)^2 + R(j+h) R(j-h)], |j| < L, R taken as 0 beyond
    Rf = lambda j: np.where(np.abs(j) < L, R[np.minimum(np.abs(j), L - 1)], 0.0)  # noqa: E731
    j = np.arange(-(L - 1), L)
    se = np.array([np.sqrt(np.sum(Rf(j) ** 2 + Rf(j + h) * Rf(j - h)) / n) for h in d])
    assert abs(R[0] - step**2 / 12) < 1e-15
    assert R[1] / R[0] > 0.3                              # the regime this is about: far from white
    z = (emp - R) / se
    assert np.all(np.abs(z) < 5), np.round(z, 1)


def test_allan_variance_closed_forms():
    """White: var/m. Walk of increment variance q: q (2 m^2 + 1)/(6 m) (the discrete form of
    K^2 tau / 3, NIST SP 1065 Table 6)."""
    m = np.array([1, 2, 3, 10, 100, 1000])
    L = 2 * m.max() + 1
    white = np.full((L, 1), 2.5)
    white[0] = 0
    np.testing.assert_allclose(allan_from_variogram(white, m)[:, 0], 2.5 / m, rtol=1e-12)
    q = 0.3
    walk = (np.arange(L) * q / 2)[:, None]
    np.testing.assert_allclose(allan_from_variogram(walk, m)[:, 0], q * (2 * m**2 + 1) / (6 * m), rtol=1e-10)


def test_gaussian_expectation_of_saturation_closed_form():
    """E[sat(U)] and E[sat'(U)] = P(|U| < L) for U ~ N(mu, s^2) against numerical integration."""
    lim = 1.0
    fn = lambda u: np.clip(u, -lim, lim)
    mu = np.array([-2.0, -0.3, 0.0, 0.8, 1.5])
    s = np.array([0.5, 1.0, 0.2, 2.0, 0.0])
    mean, gain = gauss_pwl(fn, np.array([-lim, lim]), mu, s)
    z = np.linspace(-12, 12, 200_001)
    w = stats.norm.pdf(z)
    for i in range(mu.size):
        if s[i] == 0:
            assert mean[i] == fn(mu[i]) and gain[i] == float(abs(mu[i]) < lim)
            continue
        u = mu[i] + s[i] * z
        assert mean[i] == pytest.approx(np.trapezoid(fn(u) * w, z), abs=1e-9)
        assert gain[i] == pytest.approx(stats.norm.cdf((lim - mu[i]) / s[i]) - stats.norm.cdf((-lim - mu[i]) / s[i]), abs=1e-12)


def test_van_loan_stiff_model_is_exact_not_overflowing():
    """A fast actuator lag (tau = 1 us) with Ts = 10 ms: |A| Ts = 1e4 overflows the plain Van Loan
    exponential; scaled and squared, the lag state's Q_d matches its closed form
    q/tau^2 * tau/2 (1 - e^{-2 Ts/tau}) for the input intensity q."""
    tau, Ts, q = 1e-6, 0.01, 3.0
    A = np.array([[0.0, 1.0, 0.0], [-4.0, -0.3, 1.0], [0.0, 0.0, -1.0 / tau]])
    Qc = np.diag([0.0, 0.0, q / tau**2])
    Qd = discretize.van_loan(A, Qc, Ts)
    assert np.all(np.isfinite(Qd))
    assert Qd[2, 2] == pytest.approx(q / tau**2 * tau / 2 * (1 - np.exp(-2 * Ts / tau)), rel=1e-12)
    mdl = model("[process.white]\npsd = 0.1\n[actuator.lag]\ntau_s = 1e-6")
    assert np.all(np.isfinite(mdl.S_proc)) and mdl.predictor().steady_state().var_y[0] > 0


@pytest.mark.parametrize("sigma_over_step", [0.05, 0.11, 0.3])
def test_quantizer_conditional_moments_closed_form_and_monte_carlo(sigma_over_step):
    """E[Q(mu + n)] - mu for n ~ N(0, s^2) by the level sums of conditional_moments against the
    error's Fourier series (Widrow & Kollar 2008, ch. 5: sum_m (Delta / pi m) (-1)^m
    sin(2 pi m mu / Delta) exp(-2 pi^2 m^2 s^2 / Delta^2)), and the mean variance of the error and
    Stein's h = E[e'(x)] (Cov(n, e) = s^2 h) against 400 000 draws at each of 6 means, within 5
    standard errors of the draws."""
    from noiselab.model.effects.sensor_quantization import _level_sums, conditional_moments

    D, s = 0.1, sigma_over_step * 0.1
    mu = np.array([0.013, 0.037, 0.05 - 1e-4, 0.277, -0.121, 0.5])
    mo = conditional_moments(D, mu[:, None], np.array([s * s]))
    m = np.arange(1, 400)[:, None]
    fourier = np.sum(D / (np.pi * m) * (-1.0) ** m * np.sin(2 * np.pi * m * mu / D)
                     * np.exp(-2 * np.pi**2 * m**2 * s**2 / D**2), axis=0)
    # the sums exactly; the record's moments from their table of phases (to its stated 3e-6 step)
    np.testing.assert_allclose(_level_sums(D, mu, np.full(mu.size, s))[0], fourier, atol=1e-12)
    np.testing.assert_allclose(mo.g[:, 0], fourier, atol=3e-6 * D)
    rng = np.random.default_rng(11)
    n = 400_000
    ve, h, se_v, se_h = [], [], [], []
    for i, mu_i in enumerate(mu):
        x = s * rng.standard_normal(n)
        e = D * np.rint((mu_i + x) / D) - (mu_i + x)
        se = np.std(e) / np.sqrt(n)
        assert abs(np.mean(e) - mo.g[i, 0]) < 5 * se + 1e-12, (i, np.mean(e), mo.g[i, 0])
        ec = e - e.mean()
        ve.append(np.mean(ec**2))
        se_v.append(np.std(ec**2) / np.sqrt(n))
        h.append(np.mean(x * ec) / s**2)
        se_h.append(np.std(x * ec) / s**2 / np.sqrt(n))
    # the record's mean Var(e) and h: means over the 6 samples, bounds from the draws' own spread
    # (a mean at a decision level has Var(e) = Delta^2 / 4, inside a step with little noise ~0)
    assert abs(mo.var_e[0] - np.mean(ve)) < 5 * np.sqrt(np.sum(np.square(se_v))) / 6 + 1e-15
    assert abs(mo.h[0] - np.mean(h)) < 5 * np.sqrt(np.sum(np.square(se_h))) / 6, (mo.h[0], np.mean(h))
    assert mo.active[0]


def test_quantizer_conditional_moments_limits():
    """No noise: the mean is the rounding itself; noise above 0.84 step: the uniform model (no mean,
    Delta^2 / 12, h = 0), the output marked inactive."""
    from noiselab.model.effects.sensor_quantization import conditional_moments

    D = 0.5
    mu = np.array([[0.1], [0.37], [1.2]])
    mo = conditional_moments(D, mu, np.array([0.0]))
    np.testing.assert_allclose(mo.g[:, 0], D * np.rint(mu[:, 0] / D) - mu[:, 0], atol=1e-12)
    assert mo.var_e[0] == pytest.approx(0.0, abs=1e-12)
    wide = conditional_moments(D, mu, np.array([(0.9 * D) ** 2]))
    assert not wide.active[0] and np.all(wide.g == 0) and wide.h[0] == 0
    assert wide.var_e[0] == pytest.approx(D * D / 12)


def test_quantizer_covariance_about_its_conditional_mean_monte_carlo():
    """quantization_acf with the conditional moments: the covariance of y - mu - g (the measurement
    about its mean, the quantizer's conditional mean g in it) is the noise's own c(d) plus the part,
    lag 0 exactly mean Var(e) + 2 h c(0). x = mu + a Gaussian AR(1) of std 0.1 step (rho 0.9) with
    mu a slow sine over 4 steps; 200 000 samples; lags 0..20 within 5 standard errors (from 40
    batches' spread: the process is not stationary). Stein's term is negative here (h < 0): the
    quantizer holds the measurement while mu sits near a level."""
    from scipy.signal import lfilter

    from noiselab.model.effects.sensor_quantization import conditional_moments, quantization_acf

    step, n, L, rho = 0.1, 200_000, 21, 0.9
    sigma = 0.1 * step
    rng = np.random.default_rng(5)
    k = np.arange(n)
    mu = 0.2 * np.sin(2 * np.pi * k / 20_000.0)           # its turning points (most time) on levels
    e_ = rng.standard_normal(n) * sigma
    x = np.concatenate([[e_[0]], lfilter([np.sqrt(1 - rho**2)], [1, -rho], e_[1:], zi=[rho * e_[0]])[0]])
    y = step * np.rint((mu + x) / step)
    d = np.arange(L)
    c = (sigma**2 * rho**d)[:, None]
    gamma = sigma**2 - c
    mo = conditional_moments(step, mu[:, None], np.array([sigma**2]))
    Rq = quantization_acf([step], gamma, mu[:, None], None, mo, c)
    assert Rq[0, 0] == pytest.approx(mo.var_e[0] + 2 * mo.h[0] * sigma**2, rel=1e-12)
    assert mo.h[0] < 0                                 # the regime the docstring names: Stein's term negative
    pred = c[:, 0] + Rq[:, 0]
    r = y - mu - mo.g[:, 0]
    B = 40
    rb = r.reshape(B, -1)
    est = np.array([[np.mean(b[: b.size - h] * b[h:]) for h in d] for b in rb])
    emp, se = est.mean(axis=0), est.std(axis=0, ddof=1) / np.sqrt(B)
    z = (emp - pred) / se
    assert np.all(np.abs(z) < 5), np.round(z, 1)


# -- plants that integrate (A with an eigenvalue 0) -----------------------------------------------------
MOTOR = "A = [[0.0, 1.0], [0.0, -4.0]]\nB = [[0.0], [8.0]]\nC = [[1.0, 0.0]]"


def _increments_from_rest(model, k: int, lags) -> dict:
    """{effect id: Var(y_{k+d} - y_k) / 2 at lags d} of the exact (not leaked) system started at rest,
    from the covariance recursion: P_k by doubling, then H (F^d - I) P_k (F^d - I)^T H^T +
    sum_{j<d} H F^j Gamma Gamma^T F^j^T H^T (+ the feedthrough's 2 J J^T when it has one)."""
    ls = model.predictor().linear_system()
    F, H = ls.F, ls.H
    n = F.shape[0]
    out = {}
    for eid, cols in ls.owners.items():
        G, J = ls.Gam[:, cols], ls.J[:, cols]
        P, Fp, m = G @ G.T, F.copy(), 1
        while m < k:                         # P_{2m} = P_m + F^m P_m F^m^T
            P, Fp, m = P + Fp @ P @ Fp.T, Fp @ Fp, 2 * m
        vals = []
        for d in lags:
            A = np.linalg.matrix_power(F, d) - np.eye(n)
            S, Fj = np.zeros((n, n)), np.eye(n)
            for _ in range(d):
                S, Fj = S + Fj @ G @ G.T @ Fj.T, Fj @ F
            v = H @ (A @ P @ A.T + S) @ H.T + 2 * J @ J.T \
                - H @ np.linalg.matrix_power(F, d - 1) @ G @ J.T - J @ G.T @ np.linalg.matrix_power(F, d - 1).T @ H.T
            vals.append(np.diag(v) / 2)
        out[eid] = np.array(vals)
    return out


@pytest.mark.parametrize("body, plant", [
    ("[process.white]\nstd = 0.005\n[sensor.white]\nstd = 0.002", MOTOR),
    ("[actuator.ar1]\nstd = 0.05\ntau_s = 0.3\n[actuator.lag]\ntau_s = 0.05\n[sensor.white]\nstd = 0.002", MOTOR),
    # a feedthrough D: the actuator noise reaches y directly too (J != 0: J J^T and H Gamma J^T terms)
    ("[actuator.white]\nstd = 0.05\n[actuator.ar1]\nstd = 0.05\ntau_s = 0.3\n[sensor.white]\nstd = 0.002",
     MOTOR + "\nD = [[0.05]]"),
], ids=["process", "ar1-lag", "feedthrough"])
def test_an_integrators_variogram_is_the_exact_walks(body, plant):
    """A DC motor's position (a pole at 0): no steady state, but stationary increments. The predicted
    variogram (the integrator leaked by 1e-11 per sample) against the exact system's increments
    from rest at k = 2^17 (where the stable modes have settled to 1e-300): to 1e-6 relative at lags
    1 to 4000 samples (the leak's own error is ~1e-11 d, the rounding ~1e-16 / 1e-11 of the walk's
    per-sample increment; measured: 2e-8 at lag 3999, the leak's d LEAK / 2)."""
    m = model(body, plant=plant)
    st = m.predictor().steady_state()
    assert not st.stable and st.P is None and st.var_y is None
    assert st.contributions["sensor.white"] == pytest.approx([4e-6])
    lags = [1, 2, 10, 100, 1000, 3999]
    got = m.predictor().variogram(4000, quantization=False)
    ref = _increments_from_rest(m, 2**17, lags)
    for eid, r in ref.items():
        np.testing.assert_allclose(got[eid][lags], r, rtol=1e-6, err_msg=eid)
    # the walk's growth of Var(y) per second is the variogram's long-lag slope (every source's)
    g = sum(got[eid][:, 0] for eid in ref)
    assert 2 * (g[3999] - g[3998]) / 0.01 == pytest.approx(st.walk_var_rate[0], rel=1e-6)
    if "process.white" in m.effects:
        # closed form: (b / a)^2 sigma^2 Ts for a per-sample force held over the sample (position
        # increments (b / a) sigma Ts per sample in the long run)
        assert st.walk_var_rate == pytest.approx([(8.0 / 4.0) ** 2 * 0.005**2 * 0.01], rel=1e-9)


def test_an_integrator_the_output_does_not_see_leaves_a_steady_state():
    """The same motor measured by its velocity: the position's walk is not in y, so y has a steady
    state, the first-order closed form: v_{k+1} = e^{-a Ts} v_k + (b / a)(1 - e^{-a Ts}) w_k with
    w_k of std sigma held over the sample, Var(v) = g^2 sigma^2 / (1 - e^{-2 a Ts})."""
    m = model("[process.white]\nstd = 0.005", plant=MOTOR.replace("C = [[1.0, 0.0]]", "C = [[0.0, 1.0]]"))
    st = m.predictor().steady_state()
    a, b, s, Ts = 4.0, 8.0, 0.005, 0.01
    g = (b / a) * (1 - np.exp(-a * Ts))
    assert st.var_y == pytest.approx([g**2 * s**2 / (1 - np.exp(-2 * a * Ts))], rel=1e-9)
    assert st.walk_var_rate == pytest.approx([0.0], abs=1e-20)


def test_an_integrator_one_output_sees_leaves_the_others_steady_state():
    """The motor measured by its angle and its speed: the angle has no steady state (null), the
    speed keeps the first-order closed form of the test above, per output; the sensor noise keeps
    its variance at both; the walk's rate is the angle's alone. (Before: one flag per model, the
    plant's sources null at both outputs.)"""
    m = model("[process.white]\nstd = 0.005\n[sensor.white]\nstd = 0.002",
              plant=MOTOR.replace("C = [[1.0, 0.0]]", "C = [[1.0, 0.0], [0.0, 1.0]]"))
    st = m.predictor().steady_state()
    a, b, s, Ts = 4.0, 8.0, 0.005, 0.01
    g = (b / a) * (1 - np.exp(-a * Ts))
    v_speed = g**2 * s**2 / (1 - np.exp(-2 * a * Ts))
    assert np.isnan(st.contributions["process.white"][0])
    assert st.contributions["process.white"][1] == pytest.approx(v_speed, rel=1e-9)
    assert st.contributions["sensor.white"] == pytest.approx([0.002**2] * 2, rel=1e-12)
    assert np.isnan(st.var_y[0]) and st.var_y[1] == pytest.approx(v_speed + 0.002**2, rel=1e-9)
    assert st.walk_var_rate == pytest.approx([(b / a) ** 2 * s**2 * Ts, 0.0], rel=1e-9, abs=1e-20)
    assert st.P is None and not st.stable


@pytest.mark.parametrize("plant, Ts", [
    (DOUBLE_INTEGRATOR, 0.01), (DOUBLE_INTEGRATOR, 1e-6),
    (DOUBLE_INTEGRATOR.replace("[[0.0, 1.0], [0.0, 0.0]]", "[[0.0, 1e-4], [0.0, 0.0]]"), 0.01),
], ids=["Ts-0.01", "Ts-1e-6", "weak-coupling"])
def test_a_double_integrator_has_no_stationary_increments(plant, Ts):
    """A chain of two integrators (a position from a force) is no walk: refused whatever Ts and the
    coupling's size (the test is on A's nullity, not on how close F is to I)."""
    m = model("[process.white]\nstd = 0.005\n[sensor.white]\nstd = 0.002", Ts=Ts, plant=plant)
    st = m.predictor().steady_state()
    assert not st.stable and st.walk_var_rate is None
    assert st.contributions["process.white"] is None
    assert m.predictor().variogram(10, quantization=False)["process.white"] is None


@pytest.mark.parametrize("A, Ts", [("[[-0.005]]", 1e-4), ("[[-5e-4]]", 1e-3)])
def test_a_slow_stable_pole_is_no_integrator(A, Ts):
    """A pole 2000 to 20000 s slow is slow, not zero: its variance is the first-order closed form."""
    m = model("[process.white]\nstd = 0.1", Ts=Ts, plant=f"A = {A}\nB = [[1.0]]\nC = [[1.0]]")
    st = m.predictor().steady_state()
    a = -float(A.strip("[]"))
    g = (1 - np.exp(-a * Ts)) / a
    assert st.stable and st.walk_var_rate is None
    assert st.var_y == pytest.approx([g**2 * 0.01 / (1 - np.exp(-2 * a * Ts))], rel=1e-6)


def test_a_steady_state_that_shares_its_mean_response_equals_one_computed_alone():
    """The model's own mean response is shared between models that differ only in what it does
    not depend on (``predict._OWN_MEAN``, keyed by ``predict.mean_key``): a steady state through the
    shared mean equals one computed with the share emptied, whether the change is in a noise or a
    jitter (shared), a mean effect or the command (not shared: their means differ). A shared mean's
    arrays are read-only; one over the share's size bound is not kept."""
    from noiselab.model import load_model
    from noiselab.model import predict as P
    from noiselab.model.model import dumps_toml
    seed = load_model("seed")
    louder = seed.to_dict()
    louder["command"]["amplitude"] = 2.0
    louder["sensor"]["jitter"] = {"std_s": 1e-3}          # its part follows the mean's slope
    variants = [seed, seed.with_params("actuator.ar1", {"std": 0.3, "rho": 0.9}),
                seed.with_params("actuator.saturation", {"limit": 0.5}),
                seed.with_params("sensor.scale_factor", {"error": 0.2}),
                seed.with_params("sensor.jitter", {"std_s": 1e-3}),
                parse_model(dumps_toml(louder), "louder")]
    P._OWN_MEAN.clear()
    shared = [m.predictor().steady_state() for m in variants]     # in turn: each may reuse a mean
    keys = [P.mean_key(m) for m in variants]
    assert keys[0] == keys[1] == keys[4] and len(set(keys)) == 4    # the noises (the jitter's too) share
    for m, got in zip(variants, shared):
        P._OWN_MEAN.clear()
        same = m.with_params("sensor.white", m.effects["sensor.white"].param_dict())   # a new predictor
        alone = same.predictor().steady_state()
        assert np.array_equal(got.var_y, alone.var_y)
        for eid, v in got.contributions.items():
            assert np.array_equal(v, alone.contributions[eid]), eid
        assert got.notes == alone.notes
    mean = seed.predictor()._own_mean()
    with pytest.raises(ValueError):
        mean.y[0] = 1.0
    # a mean larger than the share's bound is used, not kept (a fine sample period's horizon)
    P._OWN_MEAN.clear()
    fine = seed.to_dict()
    fine["sampling"]["Ts"] = 1e-4               # 600 000 samples of 60 s: about 38 MB of arrays
    fine_model = parse_model(dumps_toml(fine), "fine")
    assert fine_model.predictor().steady_state().var_y is not None
    assert not P._OWN_MEAN


# -- the horizon's averages beyond the samples held at once ---------------------------------------------
SLOW_SINE = """
[command]
kind = "sine"
amplitude = 0.8
frequency_hz = 0.03
[sensor.white]
std = 0.001
[sensor.jitter]
std_s = {jitter}
"""
NONLINEAR = """
[actuator.ar1]
std = 0.1
tau_s = 0.3
[actuator.saturation]
limit = 0.7
[sensor.quantization]
step = 0.005
"""


@pytest.mark.parametrize("extra", ["", NONLINEAR], ids=["linear", "nonlinear"])
def test_a_horizon_longer_than_the_samples_held_averages_over_all_of_it(extra, monkeypatch):
    """At Ts = 20 us the 60 s horizon is 3e6 samples, beyond the HORIZON_MAX (2^20) the mean response
    holds at once. The averages of the mean response over it (the jitter's E[ydot^2], the
    quantizer's spread) are still the full horizon's: equal to those of a predictor holding all 3e6
    samples, up to rounding, and so is every contribution of a linear model. Taken over the first
    2^20 samples alone, the 0.03 Hz command's average covered 21 s of its 33 s period and the
    jitter's variance came out 39 % high. (A nonlinear model's linearization, whose spectral fits
    need the samples themselves, stays on the samples held.)

    Tolerance: the two are the same recursion and the same sums, in blocks or in one go; only
    rounding differs, which the plant's slow pole (|lambda| = 1 - 2.9e-6 per sample) carries over
    ~1 / (1 - |lambda|) = 3.4e5 samples: ~3e5 * 1e-16 ~ 4e-11 per step's error, ~1e-9 accumulated.
    rtol 1e-6 is far below any change of the averaging window (percent for a partial period)."""
    from noiselab.model import predict

    Ts = 2e-5
    text = SLOW_SINE.format(jitter=Ts / 4) + extra

    def predictor(cap):
        monkeypatch.setattr(predict, "HORIZON_MAX", cap)
        for memo in (predict._OWN_MEAN, predict._COLORS, getattr(predict, "_OWN_AVERAGES", predict._COLORS)):
            memo.clear()
        pr = model(text, Ts=Ts, plant="m = 1.2\nc = 0.35\nk = 4.0").predictor()
        assert pr.horizon == min(3_000_000, cap)
        return pr

    held, whole = predictor(1 << 20), predictor(1 << 30)
    if not extra:
        st_held, st_whole = held.steady_state(), whole.steady_state()
        assert st_held.contributions.keys() == st_whole.contributions.keys()
        for eid, v in st_whole.contributions.items():
            np.testing.assert_allclose(st_held.contributions[eid], v, rtol=1e-6, atol=0, err_msg=eid)
        assert st_held.notes == st_whole.notes
    else:
        a_held, a_whole = held._own_averages(held._own_mean()), whole._own_averages(whole._own_mean())
        assert a_held.burn == a_whole.burn and a_held.span_s == a_whole.span_s
        np.testing.assert_allclose(a_held.ydot2, a_whole.ydot2, rtol=1e-6, atol=0)
        np.testing.assert_allclose(a_held.y_var, a_whole.y_var, rtol=1e-6, atol=0)


def test_the_horizon_averages_take_the_memory_of_one_block(monkeypatch):
    """The averages over a horizon beyond HORIZON_MAX go through it in blocks of HORIZON_MAX samples:
    with HORIZON_MAX = 2^15 the 3e6-sample horizon at Ts = 20 us peaks at a few MB (a block's mean
    response, ~100 bytes a sample), where holding the whole horizon takes ~300 MB; and its jitter
    variance is still the whole horizon's."""
    import tracemalloc

    from noiselab.model import predict

    Ts = 2e-5
    mdl = model(SLOW_SINE.format(jitter=Ts / 4), Ts=Ts, plant="m = 1.2\nc = 0.35\nk = 4.0")
    monkeypatch.setattr(predict, "HORIZON_MAX", 1 << 15)
    for memo in (predict._OWN_MEAN, predict._COLORS, getattr(predict, "_OWN_AVERAGES", predict._COLORS)):
        memo.clear()
    tracemalloc.start()
    try:
        small = mdl.predictor().steady_state()
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 32e6, peak
    monkeypatch.setattr(predict, "HORIZON_MAX", 1 << 30)
    predict._OWN_MEAN.clear()
    whole = mdl.predictor().steady_state()
    np.testing.assert_allclose(small.contributions["sensor.jitter"], whole.contributions["sensor.jitter"],
                               rtol=1e-6, atol=0)
