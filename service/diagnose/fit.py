"""Which physical effect is missing: fit each candidate from the catalogue, rank, add, repeat.

Likelihood (Whittle, on the Welch estimate of the residual): each Welch bin P_j is about
E_j chi2(nu_j)/nu_j with E_j the model's expected Welch value (exact, from the variogram,
:mod:`service.diagnose.compare`), so the log-likelihood is
    l = sum_j (nu_j / 2) [ -ln E_j - P_j / E_j ]       (constants dropped)
over every other bin (Hann bins two apart are nearly uncorrelated; DC dropped).

Candidates:
* noise sources (process/actuator/sensor white, AR(1), Gauss-Markov bias, bias walk, tone):
  independent sources add, E = E_model + s^2 U(shape), so the scale s^2 is a 1-D maximization and
  a shape parameter (tau, a tone's frequency) a grid; a source already in the model is refitted
  (a wrong parameter), and white actuator noise may be replaced by AR(1) (white that is colored).
* effects that change the mean response (scale factor, lag, saturation, dead zone): the residual
  is recomputed for each parameter on a grid.
* signatures outside the spectrum: values on a grid (quantization), residual power that follows
  the mean response's slope (jitter), a narrow line (tone frequency).
Scores are Delta BIC = 2 Delta l - k ln N (k fitted parameters, N samples): an effect is added
only when its Delta BIC exceeds :data:`THRESHOLD`, then everything is refitted and the search
repeats. 95 % intervals are profile-likelihood intervals (2 Delta l = 3.84) of the scale.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import minimize_scalar

from ..model import ModelError
from ..model.predict import allan_from_variogram
from ..stats import oadev, welch
from .compare import _gamma_parts, allan_edf_model, expected_welch_detrended, transient_samples

THRESHOLD = 10.0          # Delta BIC for "strong evidence" (Kass & Raftery 1995)
CHI2_95 = 3.841


@dataclass
class Candidate:
    effect: str
    params: dict
    score: float                     # Delta BIC against the current model
    interval: dict = field(default_factory=dict)   # param -> (lo, hi) 95 %
    mode: str = "add"                # add | refit | replace:<effect id>
    evidence: str = ""
    loglik: float = float("nan")


class Data:
    """The residual spectrum of a record against a model, reused across candidates."""

    def __init__(self, t, y, u, burn: int, L: int):
        self.t, self.y, self.u, self.burn, self.L = t, y, u, burn, L
        self.N = y.shape[0] - burn


def _residual(model, data: Data) -> np.ndarray:
    pr = model.predictor()
    mean = pr.mean_response(command=data.u) if data.u is not None else pr.mean_response(data.y.shape[0])
    return (data.y - mean.y)[data.burn:]


def _welch_bins(r: np.ndarray, Ts: float, L: int):
    est = welch(r, 1.0 / Ts, nperseg=L)
    sel = np.arange(1, est.f.size, 2)
    return est.f[sel], est.psd[sel], est.dof[sel], sel


def _expected(model, L: int, j: int, sel, m_long=None) -> dict:
    """Per effect: expected Welch values at the selected bins, then (when ``m_long`` is given) the
    Allan variances at the long averaging factors appended: both are linear in each effect."""
    from scipy.signal import get_window

    from .compare import _welch_kernel

    need = L if m_long is None or not len(m_long) else max(L, int(2 * max(m_long)) + 1)
    gam = _gamma_parts(model, need)
    ids = list(gam)
    G = np.column_stack([gam[e][:L, j] for e in ids])            # (L, effects)
    K = _welch_kernel(L, "hann")[sel]
    w = get_window("hann", L)
    E = (-2.0 * K[:, 1:] @ G[1:L]) * (2.0 * model.Ts / np.sum(w**2))   # expected_welch_detrended, batched
    parts = {}
    for i, eid in enumerate(ids):
        e = E[:, i]
        if m_long is not None and len(m_long):
            e = np.concatenate([e, allan_from_variogram(gam[eid][:, j:j + 1], np.asarray(m_long))[:, 0]])
        parts[eid] = e
    return parts


def _loglik(P, E, nu) -> float:
    E = np.maximum(E, 1e-300)
    return float(np.sum(nu / 2 * (-np.log(E) - P / E)))


class Fitter:
    def __init__(self, model, data: Data):
        self.model = model
        self.data = data
        self.Ts = model.Ts
        self.p = model.p
        self.r = _residual(model, data)
        self.bins = []
        for j in range(self.p):
            f, P, nu, sel = _welch_bins(self.r[:, j], self.Ts, data.L)
            # the long averaging times the Welch segments cannot resolve, from the Allan variance
            # (dof under the model, as in the analysis): drift and long correlation show there
            res = oadev(self.r[:, j], 1.0 / self.Ts, taus="octave")
            keep = res.m > data.L // 4
            m_long = res.m[keep].astype(np.int64)
            if m_long.size:
                g = sum(gg[:, j] for gg in _gamma_parts(model, max(data.L, int(2 * m_long.max()) + 1 + self.r.shape[0])).values())
                nu_a = allan_edf_model(g, m_long, self.r.shape[0], 5 * transient_samples(model) + 10)
                P = np.concatenate([P, res.dev[keep] ** 2])
                nu = np.concatenate([nu, nu_a])
            self.bins.append((f, P, nu, sel, m_long))
        self.parts = [_expected(model, data.L, j, b[3], b[4]) for j, b in enumerate(self.bins)]
        self.base = [sum(pt.values()) for pt in self.parts]
        self.l0 = sum(_loglik(b[1], e, b[2]) for b, e in zip(self.bins, self.base))

    # -- sources: E = base (minus the refitted effect's own part) + s^2 U --------------------------
    def _unit(self, eid: str, shape: dict) -> list[np.ndarray]:
        """Expected Welch of effect ``eid`` alone with unit scale (std = 1 or amplitude = 1)."""
        key = "amplitude" if eid == "sensor.tone" else "std"
        params = {key: 1.0, **shape}
        m = self.model.without_effect(eid) if eid in self.model.effects else self.model
        m = m.with_effect(eid, params)
        return [_expected(m, self.data.L, j, self.bins[j][3], self.bins[j][4])[eid] for j in range(self.p)]

    def _fit_scale(self, U, drop: str | None):
        base = [b - (pt.get(drop, 0.0) if drop else 0.0) for b, pt in zip(self.base, self.parts)]

        def ll(log_s2):
            s2 = np.exp(log_s2)
            return sum(_loglik(b[1], e + s2 * u, b[2]) for b, e, u in zip(self.bins, base, U))

        scale = max(float(np.median(np.concatenate([b[1] / np.maximum(u, 1e-300) for b, u in zip(self.bins, U)]))), 1e-300)
        lo, hi = np.log(scale) - 30, np.log(scale) + 5
        res = minimize_scalar(lambda x: -ll(x), bounds=(lo, hi), method="bounded", options={"xatol": 1e-4})
        best, lbest = res.x, -res.fun
        l_none = sum(_loglik(b[1], e, b[2]) for b, e in zip(self.bins, base)) if drop else self.l0
        # profile interval of s^2 (2 Delta l = 3.84), by bisection on each side in log space
        target = lbest - CHI2_95 / 2

        def edge(a, b):
            fa = ll(a) - target
            if fa > 0:
                return a
            for _ in range(50):
                mid = 0.5 * (a + b)
                if ll(mid) - target > 0:
                    b = mid
                else:
                    a = mid
            return 0.5 * (a + b)

        ci = (np.exp(edge(lo, best)), np.exp(edge(hi, best)))
        return np.exp(best), lbest, l_none, ci

    def source(self, eid: str, shapes: list[dict], mode: str = "add") -> Candidate | None:
        drop = eid if mode == "refit" else None
        best = None
        for shape in shapes:
            try:
                U = self._unit(eid, shape)
            except ModelError:
                continue
            s2, lb, l_none, ci = self._fit_scale(U, drop)
            if best is None or lb > best[1]:
                best = (s2, lb, l_none, ci, shape)
        if best is None:
            return None
        s2, lb, l_none, ci, shape = best
        key = "amplitude" if eid == "sensor.tone" else "std"
        k = 1 + len(shape)
        base_l = self.l0 if mode == "add" else self.l0
        score = 2 * (lb - base_l) - (k if mode == "add" else 0) * np.log(self.data.N)
        params = {key: float(np.sqrt(s2)), **shape}
        return Candidate(eid, params, float(score), {key: (float(np.sqrt(ci[0])), float(np.sqrt(ci[1])))},
                         mode=mode, loglik=lb)

    # -- effects that change the mean response: recompute the residual --------------------------------
    def generic(self, eid: str, values: list[dict]) -> Candidate | None:
        best = None
        for params in values:
            try:
                m = self.model.without_effect(eid).with_effect(eid, params) if eid in self.model.effects \
                    else self.model.with_effect(eid, params)
                f = Fitter(m, self.data)
            except (ModelError, ValueError):
                continue
            if best is None or f.l0 > best[1]:
                best = (params, f.l0)
        if best is None:
            return None
        k = len(best[0])
        score = 2 * (best[1] - self.l0) - k * np.log(self.data.N)
        return Candidate(eid, best[0], float(score), mode="add" if eid not in self.model.effects else "refit",
                         loglik=best[1])


# -- signatures outside the likelihood ---------------------------------------------------------------
def quantization_step(y: np.ndarray) -> float | None:
    """The grid step when the values lie on a grid (quantized data), else None."""
    v = np.unique(np.round(y.ravel(), 12))
    if v.size < 3 or v.size > 0.5 * y.size:
        return None
    d = np.diff(v)
    step = float(np.min(d))
    if step <= 0:
        return None
    k = d / step
    if np.all(np.abs(k - np.round(k)) < 1e-6 * np.maximum(k, 1)):
        return step
    return None


def tone_peaks(r: np.ndarray, Ts: float, max_peaks: int = 3) -> list[float]:
    """Frequencies of narrow lines: Hann periodogram bins over 20 x their local median, refined by
    parabolic interpolation; the threshold keeps chance peaks (exponential, P = e^-x) of a
    smooth spectrum below 1e-3 over all bins."""
    n = r.size
    w = np.hanning(n)
    X = np.abs(np.fft.rfft((r - r.mean()) * w)) ** 2
    from scipy.ndimage import median_filter
    med = median_filter(X, size=101, mode="nearest")
    ratio = X / np.maximum(med, 1e-300)
    thr = np.log(X.size / 1e-3)
    cands = np.flatnonzero(ratio[2:-2] > thr) + 2
    out = []
    for i in cands[np.argsort(-ratio[cands])]:
        if any(abs(i - j) < 5 for j in out):
            continue
        out.append(i)
        if len(out) >= max_peaks:
            break
    freqs = []
    for i in out:
        a, b, c = np.log(X[i - 1:i + 2] + 1e-300)
        delta = 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else 0.0
        freqs.append(float((i + delta) / (n * Ts)))
    return freqs


def jitter_fit(model, data: Data, r: np.ndarray) -> Candidate | None:
    """Residual power that follows the slope: r_k^2 = a + b ydot_k^2, b = std_s^2 (OLS, per output)."""
    pr = model.predictor()
    mean = pr.mean_response(command=data.u) if data.u is not None else pr.mean_response(data.y.shape[0])
    yd = mean.ydot[data.burn:]
    x = (yd**2).sum(axis=1)
    z = (r**2).sum(axis=1)
    if np.std(x) == 0:
        return None
    X = np.column_stack([np.ones_like(x), x])
    coef, *_ = np.linalg.lstsq(X, z, rcond=None)
    resid = z - X @ coef
    # standard error with the residual's correlation: inflate by the effective sample size
    n_eff = data.N / max(1.0, 1 + 2 * _rho_sum(resid))
    cov = np.linalg.inv(X.T @ X) * np.var(resid) * data.N / n_eff
    b, se = coef[1], np.sqrt(cov[1, 1])
    if b <= 0:
        return None
    zst = b / se
    score = zst**2 - np.log(data.N)
    std = float(np.sqrt(b))
    lo, hi = max(b - 1.96 * se, 0.0), b + 1.96 * se
    return Candidate("sensor.jitter", {"std_s": std}, float(score), {"std_s": (float(np.sqrt(lo)), float(np.sqrt(hi)))},
                     evidence=(f"the residual variance grows with the square of the signal's slope (t = {zst:.1f}): "
                               f"sampling-time jitter of about {std * 1e3:.3g} ms rms"))


def _rho_sum(x: np.ndarray, L: int = 50) -> float:
    x = x - x.mean()
    v = np.dot(x, x)
    if v == 0:
        return 0.0
    return float(sum(np.dot(x[:-k], x[k:]) / v for k in range(1, min(L, x.size // 4))))


# -- evidence sentences -----------------------------------------------------------------------------------
def _fmt(v) -> str:
    return f"{v:.3g}"


def evidence(c: Candidate, model) -> str:
    p = c.params
    if c.evidence:
        return c.evidence
    if c.effect == "sensor.bias_walk":
        return (f"at long averaging times the Allan deviation climbs with slope +1/2 and the PSD rises as 1/f^2: "
                f"a bias random walk of about {_fmt(p['std'])} per sqrt(s)")
    if c.effect == "actuator.ar1":
        what = "the actuator noise is colored, not white" if c.mode.startswith("replace") else \
            "extra low-frequency power enters through the plant"
        return (f"{what}: excess power below 1/(2 pi tau) = {_fmt(1 / (2 * np.pi * p['tau_s']))} Hz shaped by the plant, "
                f"an AR(1) actuator noise of std {_fmt(p['std'])} with tau = {_fmt(p['tau_s'])} s")
    if c.effect == "sensor.bias_markov":
        return (f"a flat excess below {_fmt(1 / (2 * np.pi * p['tau_s']))} Hz that the plant does not shape: a "
                f"Gauss-Markov bias of std {_fmt(p['std'])}, tau = {_fmt(p['tau_s'])} s (bias instability)")
    if c.effect == "sensor.white":
        return f"a white floor at high frequency above the model's: sensor white noise of std {_fmt(p['std'])}"
    if c.effect == "process.white":
        return f"excess power shaped by the plant's resonance: process (force) noise of std {_fmt(p['std'])} per sample"
    if c.effect == "actuator.white":
        return f"excess power shaped like the plant's input response: white actuator noise of std {_fmt(p['std'])}"
    if c.effect == "sensor.tone":
        return f"a narrow spectral line at {_fmt(p['frequency_hz'])} Hz: periodic interference of amplitude {_fmt(p['amplitude'])}"
    if c.effect == "sensor.quantization":
        return f"every value lies on a grid of step {_fmt(p['step'])}: the sensor is quantized"
    if c.effect == "sensor.scale_factor":
        return (f"the residual follows the predicted response itself: a scale-factor error of {100 * p['error']:+.3g} %")
    if c.effect == "actuator.lag":
        return (f"the response lags and loses amplitude at high frequency: first-order actuator dynamics with "
                f"tau = {_fmt(p['tau_s'])} s")
    if c.effect == "actuator.saturation":
        return (f"the response is flattened where the command is large (odd harmonics of the command): the "
                f"actuator saturates at about {_fmt(p['limit'])}")
    if c.effect == "actuator.deadzone":
        return f"small commands have no effect (a dead zone of about {_fmt(p['width'])})"
    return f"{c.effect} with {p}"
