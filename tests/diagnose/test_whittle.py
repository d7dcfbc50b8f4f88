"""The diagnosis' likelihood (service/diagnose/whittle/): the expected tapered periodogram of the
differenced residual, exact for a finite record that starts at rest, checked against Monte Carlo
ensembles; the modal mean response against the predictor's."""

import math

import numpy as np
import pytest

from noiselab.diagnose import whittle as W
from noiselab.model import load_model, parse_model
from noiselab.model.simulate import lsim, propagate

SEED = open(__file__.replace("tests/diagnose/test_whittle.py", "service/scenarios/seed.toml")).read()


def _ensemble(model, N, trials, seed):
    rec = model.simulate(N, seed=seed, trials=trials)
    mean = model.predictor().mean_response(N)
    r = rec.y - mean.y[None]
    I = np.mean([W.periodogram(r[i]) for i in range(trials)], axis=0)
    return I, mean


@pytest.mark.slow
@pytest.mark.parametrize("text", [
    SEED,                                                                        # euler, AR(1), walk, quantization
    SEED.replace('discretization = "euler"', 'discretization = "zoh"')
    + "\n[sensor.bias_markov]\nstd = 0.01\ntau_s = 3.0\n[actuator.lag]\ntau_s = 0.05\n",
], ids=["seed", "zoh-markov-lag"])
def test_expected_periodogram_matches_monte_carlo(text):
    """Mean of the periodogram over 400 records from rest against E I_f: each bin's mean has sd
    E_f / sqrt(400) (I_f is exponential for Gaussian data), so z = (mean - E) / (E / 20) is N(0, 1)
    per bin; over ~1500 bins mean(z^2) = 1 +- 0.04 (2 sd: 0.07) and mean(z) = 0 +- 0.026 (3 sd: 0.08)."""
    model = parse_model(text)
    N, trials = 3000, 400
    I, mean = _ensemble(model, N, trials, seed=5)
    parts = W.expected_parts(model, N - 1, 0, True, ydot_sq=np.mean(mean.ydot**2, axis=0))
    E = sum(parts.values())
    z = (I - E) / (E / np.sqrt(trials))
    assert abs(np.mean(z)) < 0.08
    assert abs(np.mean(z**2) - 1) < 0.1
    # and in 30 bands of ~50 bins: the ratio within 4 sd of the band mean (sd 1 / sqrt(50 * 400))
    edges = np.linspace(0, I.shape[0], 31).astype(int)
    ratio = np.array([I[a:b].mean() / E[a:b].mean() for a, b in zip(edges[:-1], edges[1:])])
    sd = 1 / np.sqrt(np.diff(edges) * trials)
    assert np.all(np.abs(ratio - 1) < 4 * sd + 0.01), ratio


@pytest.mark.slow
def test_from_rest_correction_is_needed_and_right():
    """A lightly damped plant from rest: the first bins are lower than the stationary prediction;
    the from-rest correction accounts for it (the 8 lowest bins pooled: 3200 exponential draws)."""
    model = load_model("seed")
    N, trials = 2000, 400
    I, mean = _ensemble(model, N, trials, seed=9)
    at_rest = sum(W.expected_parts(model, N - 1, 0, True, ydot_sq=np.mean(mean.ydot**2, axis=0)).values())
    stationary = sum(W.expected_parts(model, N - 1, 0, False, ydot_sq=np.mean(mean.ydot**2, axis=0)).values())
    low = slice(0, 8)
    sd = 1 / np.sqrt(8 * trials)
    assert abs(I[low].sum() / at_rest[low].sum() - 1) < 4 * sd
    assert I[low].sum() / stationary[low].sum() < 1 - 6 * sd


def test_walk_and_white_closed_forms():
    """Differenced white noise: E I_f = (1/M)(c_w(0) 2 var - 2 c_w(1) var cos w); a walk: flat q."""
    M = 1001
    var, q = 0.3, 0.02
    w, cw, kappa = W.taper(M)
    f = 2 * np.pi * np.arange(W.n_freqs(M)) / M
    # (1e-9: the two terms cancel to ~1e-4 of each other at the lowest bins)
    np.testing.assert_allclose(W.white_part(var, M)[:, 0], (cw[0] * 2 * var - 2 * cw[1] * var * np.cos(f)) / M,
                               rtol=1e-9)
    np.testing.assert_allclose(W.walk_part(q, M)[:, 0], q)
    assert np.sum(w**2) == pytest.approx(M) and 1.0 < kappa < 1.2


def test_modal_mean_response_equals_the_predictor():
    for name in ("seed", "hidden/sensor.scale_factor", "hidden/actuator.lag"):
        model = load_model(name)
        N = 5000
        u = model.command.values(0, N, model.Ts)
        mean = model.predictor().mean_response(command=u)
        # the reference: the simulation's Schur propagator (complex, unitary), not the modal recursions
        x = propagate(model.Ad, mean.drive @ model.Bd.T)
        ref = (x @ model.Cy.T + mean.drive @ model.Dy.T) * model.out_gain
        y = lsim(model.Ad, model.Bd, model.Cy, model.Dy, mean.drive) * model.out_gain
        np.testing.assert_allclose(y, ref, rtol=1e-9, atol=1e-12 * np.max(np.abs(ref)))
        np.testing.assert_allclose(mean.y, ref, rtol=1e-9, atol=1e-12 * np.max(np.abs(ref)))
        np.testing.assert_allclose(mean.x, x, rtol=1e-9, atol=1e-12 * np.max(np.abs(x)))


def test_profile_edge_root_finder_hits_the_chi2_crossing():
    """The profile intervals' root finder (regula falsi, Illinois) on a profile whose edges are
    known: l(x) = -(ln x - m)^2 / (2 s^2) crosses l_max - 3.84 / 2 at ln x = m -+ 1.96 s. It stops at
    |l - target| < 0.02, i.e. |ln x - edge| < 0.02 / |dl/d ln x| = 0.02 s / 1.96; and it must not
    take more refits than a bisection's 8."""
    from noiselab.diagnose.inner import _crossing
    from noiselab.diagnose.thresholds import CHI2_95

    m, s = 0.7, 0.3
    calls = []

    def l_at(x):
        calls.append(x)
        return -((math.log(x) - m) ** 2) / (2 * s**2)

    target = -CHI2_95 / 2
    for direction in (-1, +1):
        calls.clear()
        x_in = math.exp(m)
        x_out = math.exp(m + direction * 5 * s)
        x = _crossing(l_at, x_in, 0.0, x_out, l_at(x_out), target)
        edge = m + direction * math.sqrt(CHI2_95) * s
        assert abs(math.log(x) - edge) < 0.02 * s / math.sqrt(CHI2_95) + 1e-12, (x, math.exp(edge))
        assert len(calls) - 1 <= 8, len(calls)


def _powers_series(F, left, right, K):
    """left F^h right for h < K by repeated products (the definition)."""
    out, X = np.empty((K, left.shape[0], right.shape[1])), right.copy()
    for h in range(K):
        out[h] = left @ X
        X = F @ X
    return out


def test_sums_of_exponentials_equal_the_matrix_powers():
    """Modes.series against left F^h right by products: real and complex modes (a lightly damped
    pair, a slow real pole, a fast one), across blocks of lags (each mode only up to its own
    horizon), two series of one F of different lengths (the powers shared and grown), a mode the
    weights do not reach (dropped), eigenvalues not in LAPACK's adjacent-pair order (the pairing's
    search), and a defective F (plain products)."""
    rng = np.random.default_rng(7)
    r, th = 0.999, 0.05
    blocks = [np.array([[r * math.cos(th), -r * math.sin(th)], [r * math.sin(th), r * math.cos(th)]]),
              np.array([[0.9995]]), np.array([[0.3]]), np.array([[0.98]]),
              np.array([[0.9 * math.cos(1.0), -0.9 * math.sin(1.0)], [0.9 * math.sin(1.0), 0.9 * math.cos(1.0)]])]
    n = sum(b.shape[0] for b in blocks)
    D = np.zeros((n, n))
    i = 0
    for b in blocks:
        D[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    T = np.eye(n) + 0.3 * rng.standard_normal((n, n))
    F = T @ D @ np.linalg.inv(T)
    left, right = rng.standard_normal((2, n)), rng.standard_normal((n, 3))
    m = W.Modes(F)
    assert m.ok and m._adjacent
    scale = np.max(np.abs(_powers_series(F, left, right, 5)))
    for K, block in ((300, 1 << 15), (9000, 1 << 15), (9000, 2048)):    # the last: lags in 5 blocks
        ref = _powers_series(F, left, right, K)
        np.testing.assert_allclose(m.series(left, right, K, block=block), ref, rtol=0, atol=1e-10 * scale)
    # weights that do not reach the fast real mode: it is dropped, the rest unchanged
    Vi_row = np.linalg.inv(m.V)[list(np.abs(m.lam - 0.3)).index(min(np.abs(m.lam - 0.3)))]
    proj = np.eye(n) - np.outer(m.V[:, np.argmin(np.abs(m.lam - 0.3))], Vi_row).real
    right2 = proj @ right
    np.testing.assert_allclose(m.series(left, right2, 400), _powers_series(F, left, right2, 400), rtol=0,
                               atol=1e-10 * scale)
    # the eigenvalues reordered (a conjugate before its partner): the pairing's search gives the same
    perm = np.arange(n)[::-1]
    m2 = W.Modes(F)
    m2.lam, m2.V, m2.Vi, m2.hz = m2.lam[perm], m2.V[:, perm], m2.Vi[perm], m2.hz[perm]
    m2._ridx, m2._cidx = np.flatnonzero(m2.lam.imag == 0), np.flatnonzero(m2.lam.imag > 0)
    m2._adjacent = False
    np.testing.assert_allclose(m2.series(left, right, 3000), _powers_series(F, left, right, 3000), rtol=0,
                               atol=1e-10 * scale)
    # lags beyond every mode's horizon (|lam|^h < DECAY): zeros, written into the caller's array
    # (NaN before: every row is written)
    Ff = np.array([[0.5, 0.2], [0.0, -0.4]])
    mf = W.Modes(Ff)
    got = np.full((200, 2, 3), np.nan)
    assert mf.series(left[:, :2], right[:2], 200, block=64, out=got) is got
    np.testing.assert_allclose(got, _powers_series(Ff, left[:, :2], right[:2], 200), rtol=0, atol=1e-13)
    assert not np.any(got[64:])                  # the blocks after the last mode's horizon: not computed
    with pytest.raises(ValueError, match="C-contiguous"):       # a strided ``out`` would be written to a copy
        mf.series(left[:, :2], right[:2], 200, out=np.full((200, 2, 4), np.nan)[:, :, :3])
    # a defective F (a Jordan block): products
    J = np.array([[0.95, 1.0], [0.0, 0.95]])
    mj = W.Modes(J)
    assert not mj.ok
    np.testing.assert_array_equal(mj.series(left[:, :2], right[:2], 50), _powers_series(J, left[:, :2], right[:2], 50))


def test_the_parts_cache_drops_its_oldest_beyond_a_count_or_a_size(monkeypatch):
    """parts_cache: entries beyond PARTS_CACHE or beyond PARTS_CACHE_BYTES of arrays go, the oldest
    first (a re-put entry is new again); an entry larger than the whole budget is not kept, and the
    others stay."""
    monkeypatch.setattr(W.parts, "PARTS_CACHE", 4)
    monkeypatch.setattr(W.parts, "PARTS_CACHE_BYTES", 10_000)
    c = W.parts_cache()
    c.update({i: np.zeros(10) for i in range(5)})
    assert c.keys() == [1, 2, 3, 4]                              # the count: 0 went
    c.put(1, np.zeros(10))                                       # 1 used again: now the newest
    c.put("big", np.zeros(1225))
    # 2 goes for the count, then 3 for the bytes: 9800 + 3 x 80 > 10000
    assert c.keys() == [4, 1, "big"]
    assert sum(v.nbytes for _, v in c.items()) <= 10_000
    c.put("huge", np.zeros(2000))
    assert c.keys() == [4, 1, "big"]                             # larger than the budget: not kept, nothing pushed out


@pytest.mark.parametrize("M", [199680, 1_000_000])
def test_group_means_without_the_full_transform_are_exact(M):
    """Groups.spectrum (chirp z transform below F_low, folded blocks above) against the group means
    of the full length-M transform, for short and long a(h); and every source's grouped part against
    the grouped full part, from rest, with a long-memory (tau = T / 3) and a short Gauss-Markov bias."""
    g = W.Groups(M, 0.01)
    assert g.n > 1 and M % g.n == 0 and g.F_low < g.nf          # the fast path is the one tested
    assert np.all(g.sizes[1:] <= np.maximum(1, 0.01 * g.starts[1:]))      # groups at most 1 % wide
    above = g.starts >= g.F_low
    assert np.all(g.starts[above] % g.n == 0)
    rng = np.random.default_rng(3)
    for K in (2, 700, 9000):
        a = rng.standard_normal((K, 2)) * np.exp(-np.arange(K) / (K / 4))[:, None]
        ref = g.mean(W._spectrum(a, M))
        np.testing.assert_allclose(g.spectrum(a), ref, rtol=0, atol=1e-11 * np.max(np.abs(ref)))
    Ts = 0.01
    for tau in (2.0, M * Ts / 3):
        model = parse_model(SEED + f"\n[sensor.bias_markov]\nstd = 0.01\ntau_s = {tau}\n")
        full = W.expected_parts(model, M, 0, True, ydot_sq=np.ones(1))
        grouped = W.expected_parts(model, M, 0, True, ydot_sq=np.ones(1), groups=g)
        assert full.keys() == grouped.keys()
        for k in full:
            ref = g.mean(full[k])
            np.testing.assert_allclose(grouped[k], ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)), err_msg=k)


@pytest.mark.parametrize("tau", [0.3, 5000.0], ids=["short", "record-long"])
def test_expected_periodogram_against_an_extended_precision_sum(tau):
    """E I_f of AR(1) actuator noise through the seed's plant, from rest, against the definition
    evaluated in extended precision (80-bit): E I_f = (1/M) sum_{q,r} w_q w_r Cov(d_q, d_r)
    cos(w_f (q - r)), Cov(y_k, y_l) = H F^(l-k) P_k H^T + H F^(l-k-1) Gamma J^T (l > k), P_k from
    P_0 = 0. tau = 5000 s is 5e5 samples: the record is far from stationary and E is the small
    difference of the stationary part and the from-rest correction, both of the size of the
    output's variance R(0), so rounding is bounded by a few hundred eps of R(0) (or of the terms
    summed, whichever is larger), not of E; and E itself to 1e-6 of its largest value."""
    from noiselab.diagnose.edits import _set
    LD = np.longdouble
    M = 256
    model = _set(load_model("seed"), "actuator.ar1", {"std": 0.08, "tau_s": tau})
    pr = model.predictor()
    pr.steady_state()
    ls = pr._ls
    cols = ls.owners["actuator.ar1"]
    F, G, H, P, _ = W._sub_system(ls, pr._Pj["actuator.ar1"], cols, ls.n_x)
    J = ls.J[:, cols]
    n, N = F.shape[0], M + 1
    Fl, Gl, Hl, Jl = (x.astype(LD) for x in (F, G, H, J))
    Pk = np.zeros((N, n, n), LD)
    for k in range(1, N):
        Pk[k] = Fl @ Pk[k - 1] @ Fl.T + Gl @ Gl.T
    HF = np.zeros((N, n), LD)                     # H F^j
    HF[0] = Hl[0]
    for j in range(1, N):
        HF[j] = HF[j - 1] @ Fl
    cross = np.concatenate([[LD(0)], HF[:-1] @ Gl @ Jl[0]])          # H F^(j-1) Gamma J^T, j >= 1
    k, l = np.meshgrid(np.arange(N), np.arange(N), indexing="ij")
    lo, hi = np.minimum(k, l), np.maximum(k, l)
    C = np.einsum("abi,abi->ab", HF[hi - lo], (Pk @ Hl[0])[lo]) + cross[hi - lo]
    C[np.diag_indices(N)] += Jl[0] @ Jl[0]
    Cd = C[1:, 1:] - C[1:, :-1] - C[:-1, 1:] + C[:-1, :-1]
    w = W.taper(M)[0].astype(LD)
    A = w[:, None] * w[None, :] * Cd
    diag = np.array([np.trace(A, offset=h) for h in range(-(M - 1), M)])   # sum over q - r = -h
    h = np.arange(-(M - 1), M).astype(LD)
    f = np.arange(W.n_freqs(M)).astype(LD)
    E_ref = (np.cos(2 * LD(np.pi) * np.outer(f, h) / M) @ diag / M).astype(float)
    E = W.linear_part(F, G, H, J, P, M, 0, True)[:, 0]
    # rounding: a few hundred eps of the larger of the terms summed (over lags, |sum_{q-r=h} A|) and
    # the output's stationary variance R(0), the size of the parts that cancel (stationary part and
    # from-rest correction; the slow mode's and the plant's exponentials)
    R0 = float(H[0] @ P @ H[0] + J[0] @ J[0])
    scale = max(float(np.sum(np.abs(diag))) / M, R0)
    err = np.max(np.abs(E - E_ref))
    assert err < 256 * np.finfo(float).eps * scale, (err, scale, np.max(E_ref))
    assert err < 1e-6 * np.max(E_ref)


TWOOUT = open(__file__.replace("tests/diagnose/test_whittle.py", "service/scenarios/hidden/null-twoout.toml")).read()
TWOOUT_ALL = TWOOUT.replace("[actuator.white]\nstd = 0.05", "[actuator.ar1]\nstd = 0.05\ntau_s = 0.2") + \
    "\n[sensor.bias_walk]\nstd = [0.001, 0.002]\n[sensor.jitter]\nstd_s = 0.0005\n"


def test_cross_spectra_against_the_definition():
    """Two outputs of one plant (position and a scaled rate) share its noise: the expected
    cross-periodogram E[X_i X_j^*] / M of every source through the plant, from rest, against the
    definition (1/M) sum_{q,r} w_q w_r Cov(d_i,q, d_j,r) e^{-i w_f (q - r)} evaluated from the
    covariance matrix of the whole record (P_k from P_0 = 0); its diagonal is the per-output
    expected periodogram; and the grouped cross-spectra are the group means of the full ones."""
    M = 240
    model = parse_model(TWOOUT_ALL)
    pr = model.predictor()
    pr.steady_state()
    ls = pr._ls
    N = M + 1
    w = W.taper(M)[0]
    f = np.arange(W.n_freqs(M))
    q = np.arange(M)
    ph = np.exp(-2j * np.pi * np.outer(f, q) / M)                 # (nf, M)
    for eid in ("process.white", "actuator.ar1", "sensor.bias_markov"):
        cols = ls.owners[eid]
        F, G, H, P, _ = W._sub_system(ls, pr._Pj[eid], cols, ls.n_x)
        J = ls.J[:, cols]
        n, p = F.shape[0], H.shape[0]
        Pk = np.zeros((N, n, n))
        for k in range(1, N):
            Pk[k] = F @ Pk[k - 1] @ F.T + G @ G.T
        Fp = [np.eye(n)]
        for _ in range(N):
            Fp.append(F @ Fp[-1])
        C = np.zeros((N, N, p, p))                                 # Cov(y_k, y_l)
        for k in range(N):
            for l in range(N):
                if l >= k:
                    C[k, l] = H @ Pk[k] @ Fp[l - k].T @ H.T
                    if l > k:
                        C[k, l] += (H @ Fp[l - k - 1] @ G @ J.T).T
                    else:
                        C[k, l] += J @ J.T
                else:
                    C[k, l] = C[l, k].T
        Cd = C[1:, 1:] - C[1:, :-1] - C[:-1, 1:] + C[:-1, :-1]     # Cov(d_q, d_r) (M, M, p, p)
        A = w[:, None, None, None] * w[None, :, None, None] * Cd
        E_ref = np.einsum("fq,qrij,fr->fij", ph, A, np.conj(ph)) / M
        E = W.linear_part(F, G, H, J, P, M, 0, True, cross=True)
        scale = np.max(np.abs(E_ref))
        np.testing.assert_allclose(E, E_ref, rtol=0, atol=1e-10 * scale, err_msg=eid)
        coherent = np.max(np.abs(E_ref[:, 0, 1])) / np.sqrt(np.max(E_ref[:, 0, 0].real * E_ref[:, 1, 1].real))
        # through the plant the outputs correlate; each sensor's own bias does not
        assert coherent > 0.05 if eid != "sensor.bias_markov" else coherent < 1e-12, (eid, coherent)
        diag = W.linear_part(F, G, H, J, P, M, 0, True)
        np.testing.assert_allclose(np.einsum("fii->fi", E).real, diag, rtol=0, atol=1e-12 * scale)
    # every part, grouped: diagonal = the per-output parts, off-diagonal = group means of the full
    M = 199680
    g = W.Groups(M, 0.01)
    yd = np.array([[1.0, 0.3], [0.3, 0.5]])
    full = W.expected_parts(model, M, 0, True, ydot_sq=yd, cross=True)
    grouped = W.expected_parts(model, M, 0, True, ydot_sq=yd, cross=True, groups=g)
    single = W.expected_parts(model, M, 0, True, ydot_sq=np.diag(yd), groups=g)
    assert full.keys() == grouped.keys() == single.keys()
    for k in full:
        ref = g.mean(full[k])
        np.testing.assert_allclose(grouped[k], ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)), err_msg=k)
        np.testing.assert_allclose(np.einsum("fii->fi", grouped[k]).real, single[k], rtol=0,
                                   atol=1e-9 * np.max(np.abs(ref)), err_msg=k)
    # the jitter (one sampling instant) correlates the outputs; sensor white noise and the walk do not
    assert np.all(grouped["sensor.jitter"][:, 0, 1] != 0)
    assert np.all(grouped["sensor.white"][:, 0, 1] == 0) and np.all(grouped["sensor.bias_walk"][:, 0, 1] == 0)


@pytest.mark.slow
def test_cross_periodogram_matches_monte_carlo():
    """Mean cross-periodogram over 300 records from rest of the two-output plant (with jitter, a walk
    and AR(1) actuator noise) against the summed expected parts, in 20 bands of ~18 bins: the real
    and imaginary parts of the band means of I_01 each within 4 sd (the sd from that part's own
    spread over the records)."""
    model = parse_model(TWOOUT_ALL)
    N, trials = 800, 300
    rec = model.simulate(N, seed=11, trials=trials)
    mean = model.predictor().mean_response(N)
    r = rec.y - mean.y[None]
    Is = np.array([W.periodogram(r[i], cross=True) for i in range(trials)])      # (trials, nf, 2, 2)
    yd = mean.ydot.T @ mean.ydot / N
    E = sum(W.expected_parts(model, N - 1, 0, True, ydot_sq=yd, cross=True).values())
    edges = np.linspace(1, E.shape[0], 21).astype(int)
    for a, b in zip(edges[:-1], edges[1:]):
        band = Is[:, a:b, 0, 1].mean(axis=1)                    # per record
        e = E[a:b, 0, 1].mean()
        sd_re, sd_im = band.real.std() / np.sqrt(trials), band.imag.std() / np.sqrt(trials)
        assert abs(band.mean().real - e.real) < 4 * sd_re, (a, band.mean(), e)
        assert abs(band.mean().imag - e.imag) < 4 * sd_im, (a, band.mean(), e)


@pytest.mark.slow
def test_shared_noise_is_not_counted_twice():
    """Two sensors of one plant (position and a scaled rate) see the same process noise: the
    likelihood-ratio statistic of refitting the true process-noise level must follow chi2_1 (Wilks),
    mean 1, over 60 records of 60 s (the mean's sd sqrt(2 / 60) = 0.18; bounds 0.55-1.45 are
    +-2.5 sd). Summing the two outputs' likelihoods as if independent counts the shared evidence
    twice and inflates it (1.62 on these records with the composite likelihood; 1.07 now)."""
    from noiselab.diagnose.data import Data
    from noiselab.diagnose.hypotheses import Hypotheses

    model = parse_model(TWOOUT)
    stats = []
    for seed in range(60):
        rec = model.simulate(int(round(60 / model.Ts)), seed=400 + seed)
        H = Hypotheses(Data(rec.y, rec.u, model.Ts, True), model)
        l0 = H.inner_fit(model, {}).loglik
        l1 = H.inner_fit(model, {"process.white": ["std"]}).loglik
        assert l1 >= l0 - 1e-6
        stats.append(2 * (l1 - l0))
    assert 0.55 < np.mean(stats) < 1.45, np.mean(stats)


@pytest.mark.parametrize("p", [2, 3])
def test_small_inverses_in_closed_form(p):
    """The inner problem's closed-form 2 x 2 and 3 x 3 inverses and ln det against LAPACK, on random
    Hermitian positive definite matrices spanning 12 decades of scale and near-singular ones
    (one direction 1e-6 of the others' power: coherence 1 - 1e-6)."""
    from noiselab.diagnose.inner import _inv_logdet

    rng = np.random.default_rng(0)
    X = rng.standard_normal((500, p, p + 1)) + 1j * rng.standard_normal((500, p, p + 1))
    E = X @ np.conj(X.transpose(0, 2, 1)) * np.exp(rng.uniform(-14, -2, 500))[:, None, None]
    v = X[:50, :, 0]                                           # nearly coherent: v v^H + 1e-6 |v|^2 I
    E[:50] = v[:, :, None] * np.conj(v[:, None, :]) + 1e-6 * np.sum(np.abs(v) ** 2, axis=1)[:, None, None] * np.eye(p)
    Ei, ld = _inv_logdet(E)
    np.testing.assert_allclose(Ei, np.linalg.inv(E), rtol=1e-7)
    np.testing.assert_allclose(ld, np.linalg.slogdet(E)[1], rtol=1e-9, atol=1e-9)


# -- the sandwich (Godambe) variance of the jitter -------------------------------------------------------
@pytest.mark.parametrize("case", ["one output", "two outputs"])
def test_score_contributions_sum_to_the_score(case):
    """The per-sample terms of the Whittle score (whitened, for the sandwich variance) sum to the
    inner problem's score at any v: sum_q phi_aq = g_a + sum_b G_b tr(E_b^-1 U_ab), to 1e-9."""
    import dataclasses

    from noiselab.diagnose.data import Data
    from noiselab.diagnose.hypotheses import Hypotheses
    from noiselab.diagnose.sandwich import score_contributions
    if case == "one output":
        model = load_model("hidden/process.white")
        free = {"process.white": ["psd"], "actuator.white": ["std"], "sensor.white": ["std"]}
    else:
        model = parse_model(TWOOUT)
        free = {"process.white": ["std"], "actuator.white": ["std"]}
    rec = model.simulate(int(round(40 / model.Ts)), seed=5)
    H = Hypotheses(Data(rec.y, rec.u, model.Ts, True), model)
    fit = H.inner_fit(model, free)
    assert len(fit.v) == len(free)
    for scale in (1.0, 1.7):
        f = dataclasses.replace(fit, v=fit.v * np.linspace(scale, 1 / scale, len(fit.v)))
        g = f.inner.value(f.v)[1]
        E = f.inner._E(f.v)
        phi = score_contributions(H, f)
        for a in range(len(f.v)):
            if f.inner.multi:
                const = np.sum(f.inner.Gb * np.einsum("bii->b", np.linalg.solve(E, f.inner.U[a])).real)
            else:
                const = np.sum(f.inner.G * f.inner.U[a] / E)
            assert abs(np.sum(phi[a]) - (g[a] + const)) < 1e-9 * abs(const), (a, np.sum(phi[a]), g[a] + const)


def _spread_and_factor(eid, seeds, duration):
    from noiselab.diagnose.data import Data
    from noiselab.diagnose.edits import _scale_name, _set
    from noiselab.diagnose.hypotheses import Hypotheses
    from noiselab.diagnose.sandwich import godambe_factor
    truth, nominal = load_model(f"hidden/{eid}"), load_model(f"hidden/{eid}-nominal")
    name = _scale_name(truth.effects[eid])[0]
    value = float(np.max(truth.effects[eid].params[name]))
    v, model_var, c = [], [], []
    for seed in seeds:
        rec = truth.simulate(int(round(duration / truth.Ts)), seed=seed)
        H = Hypotheses(Data(rec.y, rec.u, truth.Ts, True), nominal)
        fit = H.inner_fit(_set(nominal, eid, {name: value}), {eid: [name]})
        v.append(fit.v[0])
        model_var.append(1 / fit.inner._info(fit.v)[0, 0])
        c.append(godambe_factor(H, fit, 0))
    return np.var(v, ddof=1) / np.mean(model_var), np.array(c)


@pytest.mark.slow
def test_jitter_sandwich_variance_matches_its_spread():
    """The jitter's likelihood (a Whittle part that takes its modulated power as stationary, plus a
    modulation term reading the same squared residuals) overstates its information about 2x under
    the pair's sine command. Over 150 records of 60 s, the spread of the fitted variance over the
    model-based variance (sd of that ratio: sqrt(2 / 149) = 12 % of it) must equal the mean
    sandwich factor within 3 of its sd, and exceed 1 by more than 3 sd of a ratio of 1 (the plain
    likelihood's intervals were too narrow: 5 of 20 missed, rms z 1.48)."""
    ratio, c = _spread_and_factor("sensor.jitter", range(1000, 1150), 60.0)
    rel = math.sqrt(2 / 149)
    assert abs(np.mean(c) - ratio) < 3 * rel * ratio, (np.mean(c), ratio)
    assert ratio > 1 + 3 * rel and np.mean(c) > 1 + 3 * rel, (ratio, np.mean(c))


@pytest.mark.slow
def test_sandwich_factor_is_one_for_stationary_noise():
    """Where the Whittle likelihood is right (stationary sensor white noise), the sandwich factor
    averages 1: 30 records of 60 s, mean within 3 sd of the mean (from the factors' own spread).
    Block sums of the unwhitened terms drift upward with the number of blocks (1.3 at 256: the long
    kernel of U / E^2 at low frequencies), which this catches."""
    _, c = _spread_and_factor("sensor.white", range(1000, 1030), 60.0)
    assert abs(np.mean(c) - 1) < 3 * np.std(c, ddof=1) / math.sqrt(len(c)), (np.mean(c), np.std(c))


@pytest.mark.slow
def test_jitter_level_unbiased_under_a_prbs_command():
    """Under a PRBS command the slope's power is not spread evenly over the record, and the tapered
    periodogram weights the middle of the record more: the jitter's expected power must use the
    taper-weighted mean of ydot^2 (:func:`whittle.slope_power`). Over 16 records of 120 s of the
    two-output null plant's position sensor with 1 ms of jitter, the mean fitted std_s over the truth
    must be 1 within 3 sd of that mean (the plain mean gave 1.025, 10 sd off)."""
    from noiselab.diagnose.data import Data
    from noiselab.diagnose.hypotheses import Hypotheses
    text = (TWOOUT.replace("C = [[1.0, 0.0], [0.0, 0.2]]", "C = [[1.0, 0.0]]")
            .replace("std = [0.002, 0.001]", "std = 0.002").replace("std = [0.002, 0.003]", "std = 0.002"))
    truth = parse_model(text + "\n[sensor.jitter]\nstd_s = 0.001\n")
    ratio = []
    for seed in range(16):
        rec = truth.simulate(int(round(120 / truth.Ts)), seed=70 + seed)
        fit = Hypotheses(Data(rec.y, rec.u, truth.Ts, True), truth).inner_fit(truth, {"sensor.jitter": ["std_s"]})
        ratio.append(fit.model.effects["sensor.jitter"].params["std_s"] / 0.001)
    sd = np.std(ratio, ddof=1) / math.sqrt(len(ratio))
    assert abs(np.mean(ratio) - 1) < 3 * sd, (np.mean(ratio), sd)


@pytest.mark.parametrize("free", [("sensor.jitter",), ("sensor.jitter", "process.white"), ("process.white",),
                                  ("process.white", "actuator.white")], ids=lambda f: "+".join(f))
def test_inner_likelihood_at_the_model_values_is_the_fixed_models(free):
    """The inner problem scales each free source's part from a reference value (E = E0 + sum v_a U_a).
    At the model's own values it must give the fixed model's likelihood, whatever is free. The
    jitter's part holds std_s^2 Var(ydot), which the other sources' variances set: taken from the
    references (a process noise of unit std), it was 4x too large on a two-output plant and the
    joint refit of jitter and process noise stopped 114 below the right model's log-likelihood."""
    from noiselab.diagnose.data import Data
    from noiselab.diagnose.edits import _scale_name, _unit_scale
    from noiselab.diagnose.hypotheses import Hypotheses
    from noiselab.diagnose.intervals import _extra
    from noiselab.model.effects import CATALOGUE
    model = parse_model(TWOOUT + "\n[sensor.jitter]\nstd_s = 0.001\n")
    rec = model.simulate(int(round(60 / model.Ts)), seed=3)
    H = Hypotheses(Data(rec.y, rec.u, model.Ts, True), model)
    fixed = H.inner_fit(model, {})
    fit = H.inner_fit(model, {e: [_scale_name(model.effects[e])[0]] for e in free})
    v = []
    for e in fit.scale_ids:
        name, power = _scale_name(model.effects[e])
        unit = _unit_scale(CATALOGUE[e].fit, model.Ts) if name != "psd" else 1.0
        v.append((float(np.max(model.effects[e].params[name])) / unit) ** power)
    at_model = fit.inner.value(np.array(v))[0] + _extra(H, fit)
    assert abs(at_model - fixed.loglik) < 1e-6, (at_model, fixed.loglik)
    assert fit.loglik >= fixed.loglik - 1e-6


MOTOR = """name = "motor"
[sampling]
Ts = 0.01
[plant]
A = [[0.0, 1.0], [0.0, -4.0]]
B = [[0.0], [8.0]]
C = [[1.0, 0.0], [0.0, 0.1]]
[process.white]
std = 0.005
[actuator.ar1]
std = 0.02
tau_s = 0.5
[sensor.white]
std = [0.0005, 0.0002]
"""


def test_an_integrators_expected_periodogram_against_the_definition():
    """A DC motor (position and a scaled velocity): a pole at 0, so no stationary covariance; the
    prediction leaks it by 1e-11 per sample and forms every term from (I - F) P. Against the
    definition with the exact F from rest, E I_f = (1/M) sum_{q,r} w_q w_r Cov(d_q, d_r)
    cos(w_f (q - r)) with P_k from P_0 = 0 (its walk grows without bound): per source and output,
    to 1e-7 of the largest value (the leak's own error is ~1e-11 M)."""
    M = 256
    model = parse_model(MOTOR)
    pr = model.predictor()
    pr.steady_state()
    ls = pr._ls
    exact = pr.linear_system()                     # the same system, the integrator not leaked
    assert not np.allclose(ls.F, exact.F, rtol=0, atol=1e-13) and np.allclose(ls.F, exact.F, atol=1e-10)
    parts = W.expected_parts(model, M, 0, True, cross=True)
    N = M + 1
    for eid, cols in exact.owners.items():
        F, G, H, J = exact.F, exact.Gam[:, cols], exact.H, exact.J[:, cols]
        n, p = F.shape[0], H.shape[0]
        Pk = np.zeros((N, n, n))
        for k in range(1, N):
            Pk[k] = F @ Pk[k - 1] @ F.T + G @ G.T
        HF = np.zeros((N, p, n))                   # H F^j
        HF[0] = H
        for j in range(1, N):
            HF[j] = HF[j - 1] @ F
        # Cov(y_l, y_k) for l >= k: H F^(l-k) P_k H^T + H F^(l-k-1) Gamma J^T (l > k) + J J^T (l = k)
        C = np.zeros((N, N, p, p))
        for k in range(N):
            for l in range(k, N):
                c = HF[l - k] @ Pk[k] @ H.T
                c = c + (HF[l - k - 1] @ G @ J.T if l > k else J @ J.T)
                C[l, k], C[k, l] = c, c.T
        Cd = C[1:, 1:] - C[1:, :-1] - C[:-1, 1:] + C[:-1, :-1]          # Cov(d_q, d_r)
        w = W.taper(M)[0]
        A = w[:, None, None, None] * w[None, :, None, None] * Cd
        q = np.arange(M)
        f = np.arange(W.n_freqs(M))
        ph = np.exp(-2j * np.pi * np.outer(f, q) / M)                  # (nf, M)
        E_ref = np.einsum("fq,qrij,fr->fij", ph, A, np.conj(ph)) / M
        E = parts[eid]
        scale = np.max(np.abs(E_ref))
        assert np.max(np.abs(E - E_ref)) < 1e-7 * scale, (eid, np.max(np.abs(E - E_ref)) / scale)


def test_the_levels_covariance_is_the_autocovariance_summed():
    """The stationary parts' mean over N samples (:func:`.whittle.level_density`, closed form)
    against the predictor's autocovariances summed, (1/N) [R(0) + 2 sum_{h=1}^{N-1} (1 - h/N) R(h)],
    for the seed's nominal model (process and actuator noise through a lightly damped plant,
    sensor white noise, the quantizer's Delta^2/12) and with a Gauss-Markov bias and an AR(1)
    actuator noise; the walk's rate and initial variance passed through. At N = 1000 the finite
    record's term is 30 % of the variance, at 50000 under 1 %."""
    base = open(__file__.replace("tests/diagnose/test_whittle.py", "service/scenarios/seed-nominal.toml")).read()
    for text in (base, base.replace("[actuator.white]\nstd = 0.08", "[actuator.ar1]\nstd = 0.08\nrho = 0.95")
                 + "\n[sensor.bias_markov]\nstd = 0.02\ntau_s = 4.0\n[sensor.bias_walk]\nstd = 0.003\ninitial_std = 0.01\n"):
        model = parse_model(text)
        R = sum(model.predictor().acf(60000).values())[:, 0]
        for N in (1000, 50000):
            C, q, b0 = W.level_density(model, N, at_rest=False)
            h = np.arange(1, N)
            assert C.shape == (1, 1)
            assert C[0, 0] == pytest.approx((R[0] + 2 * np.sum((1 - h / N) * R[1:N])) / N, rel=1e-6)
        walk = "bias_walk" in text
        assert q[0] == pytest.approx(0.003**2 * 0.01 if walk else 0.0)
        assert b0[0] == pytest.approx(0.01**2 if walk else 0.0)


@pytest.mark.slow
def test_the_level_of_a_record_from_rest_has_the_predicted_spread():
    """The residual's mean over records of the model from rest against V = C (from rest) + the
    walk's Var(b_0) + q (N - 1)(2N - 1) / 6N: z = m / sqrt(V) over 400 records has mean(z^2) = 1
    with sd sqrt(2 / 400) = 0.071 (3 sd: 0.21; the stationary form, without the start at rest,
    is 7 % too large at N = 5000 for this plant), and l_level is the N(0, V) log-density."""
    base = open(__file__.replace("tests/diagnose/test_whittle.py", "service/scenarios/seed-nominal.toml")).read()
    for text in (base, base + "\n[sensor.bias_walk]\nstd = 0.002\ninitial_std = 0.005\n"):
        model = parse_model(text)
        N, trials = 5000, 400
        rec = model.simulate(N, seed=11, trials=trials)
        m = (rec.y - model.predictor().mean_response(N).y[None]).mean(axis=1)[:, 0]
        C, q, b0 = W.level_density(model, N)
        V = C[0, 0] + b0[0] + q[0] * (N - 1) * (2 * N - 1) / (6.0 * N)
        z2 = m**2 / V
        assert abs(np.mean(z2) - 1) < 0.21, np.mean(z2)
        l = W.level_loglik(np.array([m[0]]), C, q, b0, N)
        assert l == pytest.approx(-0.5 * (z2[0] + math.log(2 * math.pi * V)))
