"""Predictions of the model: mean response, covariance, PSD, ACF and Allan variance, per effect.

The linear-Gaussian part is one augmented discrete system (seed sections 4 and 7: colored effects
augment the state). Symbols -> names:

=========  ==========  =================================================================
symbol     name        meaning
=========  ==========  =================================================================
s_k        state       [x (plant + lag), actuator-noise states, sensor-bias states]
F          ``F``       s_{k+1} = F s_k + Gamma e_k, e_k ~ N(0, I), columns owned by effects
Gamma      ``Gam``     noise input, (n_s, n_e)
H, J       ``H, J``    centered y_k = H s_k + J e_k + (white, walk, tone, jitter primitives)
P_k        ``P``       Cov(s_k), P_{k+1} = F P_k F^T + Gamma Gamma^T (seed section 4)
S_y,k      ``Sy``      Cov(y_k) = H P_k H^T + J J^T + R_v + R_q + R_b,k + ... (seed section 4)
R_b,k      walk        R_b,0 + k Q_b (seed sections 4 and 6.2)
=========  ==========  =================================================================

Effects contribute through the hooks of :mod:`.effects.base`. Independent sources add, so every
second-order prediction is a sum over the effects that own noise (``contributions``). Static
actuator nonlinearities enter by statistical linearization around the mean drive (seed section 7):
the mean drive is E[N(u)] and the noise passes with gain g_k = E[N'(u)], u ~ N(u_c,k, s_k^2).
Spectral conventions: PSDs are ONE-SIDED, units^2/Hz, over 0 <= f <= 1/(2 Ts), of the sampled
(discrete-time) process, so aliasing is included: S(f) = 2 Ts |T(e^{i 2 pi f Ts})|^2 for unit
white input. The ACF is the autocovariance R(d) = E[y~_{k+d} y~_k] (units^2) at lag d samples.
The Allan variance treats y as rate data with tau = m Ts: AVAR(m) = E[(ybar_{k+1} - ybar_k)^2]/2
over adjacent m-sample means, computed exactly for the sampled process from the variogram
gamma(d) = E[(y_{k+d} - y_k)^2]/2:  AVAR(m) = -(1/m^2) sum_{d=1}^{2m-1} c_m(d) gamma(d), with
c_m(d) = 2m - 3d (d <= m), -(2m - d) (m < d < 2m) (the autocorrelation of the Allan filter).
For white noise this gives var/m; for a walk of increment variance q, q (2 m^2 + 1) / (6 m), the
discrete form of K^2 tau / 3 (NIST SP 1065, Table 6).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import block_diag, solve_discrete_lyapunov
from scipy.special import ndtr

from ..memo import Memo
from .effects import CATALOGUE
from .simulate import lsim

_SQRT2PI = np.sqrt(2.0 * np.pi)


# -- Gaussian expectations of piecewise-linear maps (statistical linearization) ---------------------
def pwl_pieces(fn, b: np.ndarray):
    """A piecewise-linear map ``fn`` with kinks ``b`` (sorted, unique): the points
    ext = [b_0 - pad, b, b_-1 + pad], fn(ext) and the slopes of the K + 1 pieces. The map is linear
    beyond its outer kinks, so any step past them gives the outer slopes; pad = max(1, max |b|) is
    one that float64 does not lose (b +- 1 rounds to b beyond 2^53, and the slope would be 0 / 0)."""
    pad = max(1.0, float(np.max(np.abs(b))))
    ext = np.concatenate([[b[0] - pad], b, [b[-1] + pad]])
    fv = fn(ext)
    return ext, fv, np.diff(fv) / np.diff(ext)


def gauss_pwl(fn, knots: np.ndarray, mu: np.ndarray, sigma: np.ndarray, *, second: bool = False):
    """E[f(U)] and E[f'(U)] (and E[f(U)^2] with ``second``) for U ~ N(mu, sigma^2), f piecewise
    linear with kinks at ``knots``.

    Exact, in closed form on each linear piece a + s u over [lo, hi] (z = (u - mu)/sigma, alpha and
    beta the standardized ends): int phi = dPhi, int z phi = phi(alpha) - phi(beta),
    int z^2 phi = dPhi + alpha phi(alpha) - beta phi(beta). sigma = 0 gives f(mu), f'(mu), f(mu)^2.
    Neighbouring pieces share their ends: the normal's cdf and pdf are taken once per knot, the
    knots along the first axis (rows of the whole record: a reduction over a short last axis costs
    numpy more than the arithmetic).
    """
    b = np.unique(np.asarray(knots, float))
    ext, fv, slope = pwl_pieces(fn, b)
    slope = slope[:, None]                                  # K+1 pieces
    # each piece's intercept from its end nearer 0: from a far end (a saturation at 1e20 beside a
    # dead zone of 0.01) f - s x cancels to rounding of 1e20 and the dead zone's offset is lost
    near = np.where(np.abs(ext[:-1]) <= np.abs(ext[1:]), 0, 1) + np.arange(ext.size - 1)
    icpt = fv[near, None] - slope * ext[near, None]
    mu, sg = np.broadcast_arrays(np.asarray(mu, float), np.asarray(sigma, float))
    shape = mu.shape
    mu, sg = mu.ravel(), sg.ravel()
    pos = sg > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (b[:, None] - mu) / sg                          # the knots standardized (K, n)
    degenerate = not pos.all()
    if degenerate:                                          # sigma = 0: a step at the knot
        z = np.where(pos, z, np.where(b[:, None] <= mu, -np.inf, np.inf))
    phi = np.exp(-0.5 * z * z) / _SQRT2PI                   # 0 at +-inf
    zero = np.zeros((1, mu.size))
    dP = np.diff(np.concatenate([zero, ndtr(z), zero + 1.0]), axis=0)     # (K+1, n) per piece
    dphi = np.diff(np.concatenate([zero, phi, zero]), axis=0)             # phi(beta) - phi(alpha)
    gain = (slope * dP).sum(axis=0)
    mean = (icpt * dP).sum(axis=0) + mu * gain - sg * (slope * dphi).sum(axis=0)
    if not second:
        return mean.reshape(shape)[()], gain.reshape(shape)[()]
    with np.errstate(invalid="ignore"):
        zphi = z * phi
    if degenerate:
        zphi = np.where(np.isfinite(z), zphi, 0.0)
    e_z2 = dP - np.diff(np.concatenate([zero, zphi, zero]), axis=0)       # int z^2 phi
    lin = icpt + slope * mu                                 # a + s u = lin + s sigma z on the piece
    sq = (lin * lin * dP - 2.0 * sg * (lin * slope) * dphi + (slope * slope) * (sg * sg) * e_z2).sum(axis=0)
    return mean.reshape(shape)[()], gain.reshape(shape)[()], sq.reshape(shape)[()]


@dataclass
class LinearSystem:
    F: np.ndarray
    Gam: np.ndarray
    H: np.ndarray
    J: np.ndarray
    Hd: np.ndarray          # rows giving ydot (for jitter): ydot~ = Hd s + Jd e
    Jd: np.ndarray
    owners: dict            # effect id -> column indices of e
    n_x: int                # plant (+ lag) states at the top of s
    plant_block: slice      # rows/cols of s that are plant states (without lag)
    n_act: int = 0          # actuator-noise states after the plant's (shadows included)


@dataclass
class MeanResponse:
    t: np.ndarray           # (N,) s
    x: np.ndarray           # (N, n_x) mean continuous-stage state
    drive: np.ndarray       # (N, m) mean plant input E[N(u_c + n_a)]
    gain: np.ndarray        # (N, m) statistical-linearization gain of the actuator nonlinearities
    drive_var: np.ndarray   # (N, m) variance of the actuator noise before the nonlinearities
    distortion_var: np.ndarray  # (N, m) variance of the nonlinearities' distortion d (Bussgang)
    ydot: np.ndarray        # (N, p) mean derivative of the plant output
    y: np.ndarray           # (N, p) predicted mean measurement


@dataclass
class Covariance:
    P: np.ndarray                       # (N, n_s, n_s) state covariance P_k
    Sy: np.ndarray                      # (N, p) variance of y_k (diagonal of S_y,k)
    parts: dict = field(default_factory=dict)   # effect id -> (N, p) its share of Sy


@dataclass
class Steady:
    var_y: np.ndarray | None            # (p,) stationary variance of the centered measurement
    P: np.ndarray | None                # (n, n) plant state covariance, None if not stable
    contributions: dict                 # effect id -> (p,) or None
    bias_var_rate: np.ndarray           # (p,) growth of Var(y) per second from the bias walk
    stable: bool
    notes: list
    ydot_var: np.ndarray | None = None  # (p,) stationary Var(ydot) (the jitter's noise-driven slope)
    walk_var_rate: np.ndarray | None = None   # (p,) growth of Var(y) per second where the plant integrates


def mean_key(model, gain: bool = True) -> str:
    """The part of a model the mean response depends on: plant, sampling, command and the mean
    effects; actuator noise only through the nonlinearities' statistical linearization.
    ``gain=False``: without the sensor gain (the scale factor)."""
    d = model.to_dict()
    if not gain:
        d.get("sensor", {}).pop("scale_factor", None)
    nonlin = any(hasattr(e, "knots") for e in model.effects.values())
    for g in ("process", "sensor", "actuator"):
        sub = d.get(g, {})
        for s in list(sub):
            eid = f"{g}.{s}"
            if CATALOGUE[eid].fit.kind != "mean" and not (nonlin and g == "actuator"):
                sub.pop(s)
    d.pop("description", None)
    d.pop("name", None)
    return repr(d)


def free_response_fit(model, y: np.ndarray, ym: np.ndarray, yd: np.ndarray, k0: int,
                      gain: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """For a record that does not start at rest under a command (cut mid-stream, or the longest
    run after a gap): the mean response of its command starts from zero at sample 0, the plant (and
    an actuator lag) did not. The unknown mean state at sample ``k0`` is fitted to y - ym on
    samples k0.. by least squares, one regressor per state (the free response Cy Ad^j e_i, times
    ``gain`` per output: the sensor gain when ym has it), and its free response is added to the
    mean ym and to its slope yd (Cy Ac Ad^j x). Returns new arrays (N, p); before k0 they are ym
    and yd. The burn before k0 leaves the modes that decay slowly; without it a fast plant's
    transient, 10 % of the command's response after the burn, stayed far above a small noise."""
    y = np.asarray(y, float).reshape(len(y), -1)
    N, p = y.shape
    n = N - k0
    ym, yd = np.array(ym, float), np.array(yd, float)
    if model.n_x == 0 or n <= model.n_x:
        return ym, yd
    g = np.ones(p) if gain is None else np.broadcast_to(np.asarray(gain, float), (p,))
    C = np.vstack([model.Cy, model.Cy @ model.Ac])
    # the free response only where it is not yet rounding (a stable plant's: up to rho^K = 1e-16)
    rho = float(np.max(np.abs(np.linalg.eigvals(model.Ad))))
    K = n if rho >= 1.0 - 1e-12 else min(n, int(np.ceil(np.log(1e-16) / np.log(max(rho, 1e-300)))) + 1)
    imp = np.zeros((K + 1, 1))
    imp[0] = 1.0
    basis = np.empty((K, 2 * p, model.n_x))
    for i in range(model.n_x):      # x_1 = e_i from an impulse through Bd = e_i: then Cy Ad^j e_i
        basis[:, :, i] = lsim(model.Ad, np.eye(model.n_x)[:, i:i + 1], C, np.zeros((2 * p, 1)), imp)[1:]
    basis *= np.concatenate([g, g])[None, :, None]
    Phi = basis[:, :p].reshape(K * p, model.n_x)
    x0 = np.linalg.lstsq(Phi, (y[k0:k0 + K] - ym[k0:k0 + K]).ravel(), rcond=1e-10)[0]
    ym[k0:k0 + K] += basis[:, :p] @ x0
    yd[k0:k0 + K] += basis[:, p:] @ x0
    return ym, yd


SHADOW_BLOCKS = 4         # at most so many blocks for a colored source's gain fluctuation (Predictor._gain_shadows)
DISTORTION_TERMS = 20     # Hermite terms of a colored noise's distortion (Predictor._distortion_colors)

# The model's own mean response over its horizon, shared between models that differ only in what
# it does not depend on (:func:`mean_key`): a diagnosis builds thousands of models that differ in a
# noise parameter, and each one's steady state needs the mean when the model has a quantizer, a
# jitter or a nonlinearity (on 10^6 samples of the seed: 2325 steady states, 5.9 s of 42 s in the
# mean responses, under the profiler). Read-only arrays, shared by threads (a :class:`Memo`: they
# may compute one twice, never wrongly). Only means of at most _OWN_MEAN_BYTES are kept: the horizon
# is 60 s of samples (at most HORIZON_MAX), about 100 MB of mean response at Ts = 57 us and below.
_OWN_MEAN = Memo(9, flush=True)
_OWN_MEAN_BYTES = 16 << 20
# The gain fluctuation's and the distortion's damped-cosine fits of a nonlinear model, by the same
# key as _OWN_MEAN (they depend on nothing else): (shadow, dcolor) of Predictor._colors. Not to be
# changed by callers.
_COLORS = Memo(65, flush=True)
# The horizon averages of a model whose horizon is longer than HORIZON_MAX (:meth:`Predictor._own_averages`),
# by the key of _OWN_MEAN and the horizon's length: small, but seconds to compute at Ts = 1 us.
_OWN_AVERAGES = Memo(9, flush=True)


HORIZON_MAX = 1 << 20
"""The most samples of the model's own mean response held at once (the 60 s horizon fits for
Ts >= 57 us): it keeps several arrays of that length. A longer horizon's averages of the mean
response (the jitter's slope, the quantizer's spread) are taken over all of it in blocks of this
length (:meth:`Predictor._own_averages`); the nonlinearities' linearization (rms gain, distortion
and their spectral fits, which must share one window) and the quantizer's motion take the first
HORIZON_MAX samples."""


@dataclass(frozen=True)
class HorizonAverages:
    """Averages of the model's own mean response over the horizon's samples k = burn..n-1, per
    output, for the steady state's signal-dependent terms."""
    burn: int                       # samples left out at the start (the plant's transient)
    ydot2: np.ndarray               # mean of E[ydot_k]^2 (the jitter's slope)
    y_var: np.ndarray               # variance of E[y_k] over the samples (the quantizer's spread)
    span_s: float                   # time from the first sample averaged to the last, s


class Predictor:
    """Predictions for one model. ``horizon_s`` sets how long a command history is averaged over
    for signal-dependent approximations (jitter, nonlinear actuator gains), at most
    :data:`HORIZON_MAX` samples."""

    def __init__(self, model, horizon_s: float = 60.0):
        self.model = model
        self.span = max(int(np.ceil(horizon_s / model.Ts)), 2)     # the horizon, samples
        self.horizon = min(self.span, HORIZON_MAX)                   # of it held at once
        m = model
        self._act_src = [e for e in m.effects.values() if hasattr(e, "drive_linear")]
        self._nonlin = [e for e in m.effects.values() if hasattr(e, "knots")]
        self._sen_lin = [e for e in m.effects.values() if hasattr(e, "sensor_linear")]
        blocks = [e.drive_linear() for e in self._act_src]
        self._act_blocks = blocks            # per source: (F, G, C, D)
        mm = m.m
        self._Fa = block_diag(*[b[0] for b in blocks]) if blocks else np.zeros((0, 0))
        self._Ga = [b[1] for b in blocks]
        self._Ca = np.hstack([b[2] for b in blocks]) if blocks else np.zeros((mm, 0))
        self._Da = [b[3] for b in blocks]
        if self._Fa.shape != (self._Ca.shape[1],) * 2:     # block_diag of 0x0 blocks
            self._Fa = np.zeros((self._Ca.shape[1],) * 2)
        self._steady_cache = None

    # -- actuator drive statistics ----------------------------------------------------------------
    def drive_noise_var(self, n: int) -> np.ndarray:
        """Var of the actuator noise n_a,k (before nonlinearities), k = 0..n-1, per channel (n, m):
        diag(C_a Pa_k C_a^T + D D^T) with Pa_0 = 0 (the noise states start at zero) and
        Pa_k = sum_{i<k} F^i G G^T F^i^T, the transient of Pa_{k+1} = F Pa_k F^T + G G^T.

        Computed by doubling, Pa_{s+j} = Pa_s + F^s Pa_j F^s^T (log2 of the transient length in
        batched products, each term a sum of PSD matrices: no cancellation), up to the sample where
        ||F^s||_2^2 < 1e-17; from there on Pa_k equals Pa_s to ~1e-17 relative (Pa_j <= Pa_inf in
        the Loewner order, so F^s Pa_j F^s^T <= ||F^s||^2 Pa_inf) and the rest is filled with it."""
        m = self.model.m
        DD = sum((D @ D.T for D in self._Da), np.zeros((m, m)))
        GG = block_diag(*[G @ G.T for G in self._Ga]) if self._Ga else np.zeros((0, 0))
        F, Ca = self._Fa, self._Ca
        out = np.empty((n, m))
        if n == 0:
            return out
        if F.shape[0] == 0 or not np.any(GG):
            out[:] = np.diag(DD)
        else:
            na = F.shape[0]
            Pa = np.zeros((1, na, na))
            size, S, Fp = 1, GG.copy(), F.copy()       # S = Pa_size, Fp = F^size
            while size < n:
                take = min(size, n - size)
                if Pa.shape[0] < size + take:
                    grown = np.empty((size + take, na, na))
                    grown[:size] = Pa[:size]
                    Pa = grown
                # Pa_{size+j} = Pa_size + F^size Pa_j F^size^T, j = 0..take-1
                Pa[size:size + take] = S + Fp @ Pa[:take] @ Fp.T
                settled = np.linalg.norm(Fp, 2) ** 2 < 1e-17
                if take == size:
                    S = S + Fp @ S @ Fp.T                  # Pa_{2 size}
                    Fp = Fp @ Fp
                size += take
                if settled:
                    break
            K = min(size, n)
            v = np.einsum("ij,kjl,il->ki", Ca, Pa[:K], Ca) + np.diag(DD)
            out[:K] = v
            if K < n:
                out[K:] = np.einsum("ij,jl,il->i", Ca, S, Ca) + np.diag(DD)
        return out

    def _nonlinear(self, u: np.ndarray) -> np.ndarray:
        for e in self._nonlin:
            u = e.apply(u)
        return u

    def _channel_map(self, j: int):
        """(f, knots): input channel j's nonlinearities composed, as a map of one array, and their kinks."""
        knots = np.concatenate([e.knots()[j] for e in self._nonlin])

        def fj(v):
            arr = np.zeros((v.size, self.model.m))
            arr[:, j] = v
            return self._nonlinear(arr)[:, j]
        return fj, knots

    def drive_stats(self, u_c: np.ndarray, var: np.ndarray):
        """Mean drive E[N(u_c + n)], gain g = E[N'(u_c + n)] and distortion variance
        Var(N) - g^2 var, for n ~ N(0, var), per channel (Bussgang: N(u) = E[N] + g n + d with d
        uncorrelated with n)."""
        if not self._nonlin:
            return u_c.copy(), np.ones_like(u_c), np.zeros_like(u_c)
        mean = np.empty_like(u_c)
        gain = np.empty_like(u_c)
        dvar = np.empty_like(u_c)
        sd = np.sqrt(np.broadcast_to(var, u_c.shape))
        for j in range(self.model.m):
            fj, knots = self._channel_map(j)
            mean[:, j], gain[:, j], sq = gauss_pwl(fj, knots, u_c[:, j], sd[:, j], second=True)
            dvar[:, j] = np.maximum(sq - mean[:, j] ** 2 - gain[:, j] ** 2 * sd[:, j] ** 2, 0.0)
        return mean, gain, dvar

    # -- mean (seed section 3) ------------------------------------------------------------------------
    def mean_response(self, n: int | None = None, command: np.ndarray | None = None) -> MeanResponse:
        """m_{k+1} = A_d m_k + B_d E[drive_k]; E[y_k] = (1+s_f)(C m_k + D E[drive_k]) (seed sec. 3).
        ``command`` (N, m) is a recorded command; default: the model's own command generator."""
        mdl = self.model
        if command is None:
            n = self.horizon if n is None else n
            u = mdl.command.values(0, n, mdl.Ts)
        else:
            u = np.asarray(command, float).reshape(len(command), -1)
            n = u.shape[0]
        var = self.drive_noise_var(n)
        drive, gain, dvar = self.drive_stats(u, var)
        # the states by modal real recursions (Schur propagator when A_d's eigenvectors are ill-conditioned)
        x = lsim(mdl.Ad, mdl.Bd, np.eye(mdl.n_x), np.zeros((mdl.n_x, 0)), drive) if mdl.n_x else np.zeros((n, 0))
        y = (x @ mdl.Cy.T + drive @ mdl.Dy.T) * mdl.out_gain
        ydot = (x @ (mdl.Cy @ mdl.Ac).T + drive @ (mdl.Cy @ mdl.Bc).T) * mdl.out_gain
        return MeanResponse(t=np.arange(n) * mdl.Ts, x=x, drive=drive, gain=gain, drive_var=var,
                            distortion_var=dvar, ydot=ydot, y=y)

    def _own_mean(self) -> MeanResponse:
        """:meth:`mean_response` of the model's own command over the horizon, shared through
        :data:`_OWN_MEAN` (read-only: not for callers that change it)."""
        key = (mean_key(self.model), self.horizon)
        got = _OWN_MEAN.get(key)
        if got is None:
            got = self.mean_response()
            arrays = [v for v in vars(got).values() if isinstance(v, np.ndarray)]
            for v in arrays:
                v.setflags(write=False)
            if sum(v.nbytes for v in arrays) <= _OWN_MEAN_BYTES:
                _OWN_MEAN.put(key, got)
        return got

    def _own_averages(self, mean: MeanResponse) -> HorizonAverages:
        """The averages (:class:`HorizonAverages`) of the model's own mean response over the whole
        horizon, ``mean`` being its first :attr:`horizon` samples (:meth:`_own_mean`).

        Each is (1 / (n - b)) sum_{k=b}^{n-1} f(m_k) of the mean response m_k (b: the burn). Within
        HORIZON_MAX that is taken on ``mean`` itself. Beyond, the horizon is gone through in blocks of
        HORIZON_MAX samples, each block's mean response started from the state the recursion
        m_{k+1} = A_d m_k + B_d E[drive_k] reaches at its start, so every block holds the very
        samples the whole horizon's recursion gives; the sums add over blocks (the variance by
        Chan's pairwise update of count, mean and squared deviations). So the average is the one
        over the full horizon, to rounding, in the memory of one block: taken over the first
        HORIZON_MAX samples alone, a slow command's average covered part of its period (a 0.03 Hz
        sine at Ts = 20 us: the first 21 s of its 33 s period, the jitter's variance 39 % high). The
        time is that of the horizon's samples, at most 6e7 (60 s at the model files' least Ts, 1 us:
        ~7 s for the seed's plant)."""
        mdl = self.model
        n, settle = self.span, _settle_samples(mdl)
        burn = min(n // 2, settle)
        if n == mean.t.size:
            return HorizonAverages(burn, np.mean(mean.ydot[burn:] ** 2, axis=0), np.var(mean.y[burn:], axis=0),
                                   float(mean.t[-1] - mean.t[burn]))

        def compute():
            ydot2 = np.zeros(mdl.p)
            count, y_mean, y_m2 = 0, np.zeros(mdl.p), np.zeros(mdl.p)
            block, k0 = mean, 0
            while True:
                a = max(burn - k0, 0)
                if a < block.t.size:
                    y = block.y[a:]
                    ydot2 += np.sum(block.ydot[a:] ** 2, axis=0)
                    nb, mb = y.shape[0], np.mean(y, axis=0)
                    m2b = np.sum((y - mb) ** 2, axis=0)
                    delta, total = mb - y_mean, count + nb
                    y_m2 = y_m2 + m2b + delta**2 * count * nb / total
                    y_mean = y_mean + delta * nb / total
                    count = total
                k_next = k0 + block.t.size
                if k_next >= n:
                    break
                x_next = mdl.Ad @ block.x[-1] + mdl.Bd @ block.drive[-1] if mdl.n_x else np.zeros(0)
                block = self._mean_block(k_next, min(HORIZON_MAX, n - k_next), x_next)
                k0 = k_next
            return HorizonAverages(burn, ydot2 / count, y_m2 / count, float((n - 1) * mdl.Ts - burn * mdl.Ts))
        return _OWN_AVERAGES.get_or_compute((mean_key(mdl), n), compute)

    def _mean_block(self, k0: int, n: int, x0: np.ndarray) -> MeanResponse:
        """:meth:`mean_response` of the model's own command at samples k0..k0+n-1, the state
        starting from ``x0`` (the recursion's state at k0), the drive noise's variance at those k
        (:meth:`_drive_noise_var_from`)."""
        mdl = self.model
        u = mdl.command.values(k0, n, mdl.Ts)
        var = self._drive_noise_var_from(k0, n)
        drive, gain, dvar = self.drive_stats(u, var)
        # the forced response from rest (as mean_response) plus the free one of x0: A_d^j x0
        x = lsim(mdl.Ad, mdl.Bd, np.eye(mdl.n_x), np.zeros((mdl.n_x, 0)), drive) \
            + _powers_apply(mdl.Ad, x0[:, None], n)[:, :, 0] if mdl.n_x else np.zeros((n, 0))
        y = (x @ mdl.Cy.T + drive @ mdl.Dy.T) * mdl.out_gain
        ydot = (x @ (mdl.Cy @ mdl.Ac).T + drive @ (mdl.Cy @ mdl.Bc).T) * mdl.out_gain
        return MeanResponse(t=(k0 + np.arange(n)) * mdl.Ts, x=x, drive=drive, gain=gain, drive_var=var,
                            distortion_var=dvar, ydot=ydot, y=y)

    def _drive_noise_var_from(self, k0: int, n: int) -> np.ndarray:
        """:meth:`drive_noise_var` at k = k0..k0+n-1 (n, m), for k0 past the first block: with
        Pa_inf = sum_{i>=0} F^i G G^T F^i^T (the Lyapunov solution; the actuator sources are
        stable, AR(1) with rho < 1), Pa_k = sum_{i<k} F^i G G^T F^i^T = Pa_inf - F^k Pa_inf F^k^T,
        so diag(C_a Pa_k C_a^T) = diag(C_a Pa_inf C_a^T) - diag(W_k Pa_inf W_k^T), W_k = C_a F^k.
        The difference's rounding, relative to Pa_k, is ~eps Pa_inf / Pa_k = eps / (1 - rho^(2k)),
        ~eps tau / (2k) for a correlation time of tau samples: below 1e-7 for k >= HORIZON_MAX and
        every tau a model file allows (at most 1e15 Ts)."""
        m = self.model.m
        DD = np.diag(sum((D @ D.T for D in self._Da), np.zeros((m, m))))
        GG = block_diag(*[G @ G.T for G in self._Ga]) if self._Ga else np.zeros((0, 0))
        F, Ca = self._Fa, self._Ca
        if F.shape[0] == 0 or not np.any(GG):
            return np.broadcast_to(DD, (n, m)).copy()
        Pinf = solve_discrete_lyapunov(F, GG)
        W = Ca @ np.linalg.matrix_power(F, k0)                    # (m, na)
        Wk = _powers_apply(F.T, W.T, n)                           # (n, na, m): (W F^j)^T
        return np.diag(Ca @ Pinf @ Ca.T) - np.einsum("kam,ab,kbm->km", Wk, Pinf, Wk) + DD

    # -- the augmented linear system -------------------------------------------------------------------
    def linear_system(self, g: np.ndarray | None = None, dstd: np.ndarray | None = None,
                      shadow: dict | None = None, dcolor: list | None = None) -> LinearSystem:
        """The augmented system for nonlinearity gain ``g`` and distortion std ``dstd`` (per input).
        The distortion d of the static nonlinearities enters the input channel as white noise of
        std ``dstd``, owned by the nonlinearity (exact for white actuator noise, whose distortion
        is iid); of a colored noise, the colored part is ``dcolor``.

        ``shadow`` ({index of an actuator source: (mean gain (m,), [shadow block (F, G, C, D)])},
        :meth:`_gain_shadows`): a colored source whose gain switches within its correlation time,
        g_k n_k = gbar n_k + (g_k - gbar) n_k. The first part keeps the source's own dynamics at
        the mean gain, the second (uncorrelated with it over time) is the shadow blocks (their
        variance in their G), all owned by the source.

        ``dcolor`` ([block (F, G, C, D)], :meth:`_distortion_colors`): the colored part of the
        distortion of a colored source, owned by the nonlinearity beside its white part ``dstd``."""
        mdl = self.model
        g = np.ones(mdl.m) if g is None else np.asarray(g, float)
        G = np.diag(g)
        shadow = shadow or {}
        # per actuator block (its own states, then its shadow's): (F, G, C, D, gain matrix)
        act = []
        for i, (Fi, Ga, Ci, Da) in enumerate(self._act_blocks):
            if i in shadow:
                gbar, comps = shadow[i]
                act.append([(Fi, Ga, Ci, Da, np.diag(gbar))] + [(*blk, np.eye(mdl.m)) for blk in comps])
            else:
                act.append([(Fi, Ga, Ci, Da, G)])
        act_ids = [e.id for e in self._act_src]
        if self._nonlin and dcolor:
            act.append([(*blk, np.eye(mdl.m)) for blk in dcolor])
            act_ids.append(self._distortion_owner())
        blocks = [b for bl in act for b in bl]
        na = sum(b[0].shape[0] for b in blocks)
        sen = [e.sensor_linear() for e in self._sen_lin]
        Fs = block_diag(*[s[0] for s in sen]) if sen else np.zeros((0, 0))
        ns_ = Fs.shape[0]
        nx = mdl.n_x
        n_s = nx + na + ns_
        F = np.zeros((n_s, n_s))
        F[:nx, :nx] = mdl.Ad
        a0 = 0
        for Fi, _, Ci, _, Gi in blocks:
            k = Fi.shape[0]
            F[:nx, nx + a0:nx + a0 + k] = mdl.Bd @ Gi @ Ci
            F[nx + a0:nx + a0 + k, nx + a0:nx + a0 + k] = Fi
            a0 += k
        F[nx + na:, nx + na:] = Fs
        cols, owners, Jc, Jdc = [], {}, [], []
        gain = mdl.out_gain[:, None]
        CyBc = mdl.Cy @ mdl.Bc
        start = 0

        def add(eid, col_block, j_block, jd_block):
            nonlocal start
            k = col_block.shape[1]
            owners[eid] = np.concatenate([owners.get(eid, np.zeros(0, np.int64)), np.arange(start, start + k)])
            start += k
            cols.append(col_block)
            Jc.append(j_block)
            Jdc.append(jd_block)

        a0 = 0
        for eid, bl in zip(act_ids, act):
            for _, Ga, _, Da, Gi in bl:
                k, ka = Da.shape[1], Ga.shape[0]
                col = np.zeros((n_s, k))
                col[:nx] = mdl.Bd @ Gi @ Da
                col[nx + a0:nx + a0 + ka] = Ga
                a0 += ka
                add(eid, col, gain * (mdl.Dy @ Gi @ Da), gain * (CyBc @ Gi @ Da))
        if self._nonlin and dstd is not None:
            Dd = np.diag(np.asarray(dstd, float))
            col = np.zeros((n_s, mdl.m))
            col[:nx] = mdl.Bd @ Dd
            add(self._distortion_owner(), col, gain * (mdl.Dy @ Dd), gain * (CyBc @ Dd))
        if "process.white" in mdl.effects and mdl.S_proc.shape[1]:
            col = np.zeros((n_s, mdl.S_proc.shape[1]))
            col[:nx] = mdl.S_proc
            z = np.zeros((mdl.p, col.shape[1]))
            add("process.white", col, z, z)
        s0 = 0
        for e, (Fi, Gi, Hi) in zip(self._sen_lin, sen):
            col = np.zeros((n_s, Gi.shape[1]))
            col[nx + na + s0:nx + na + s0 + Gi.shape[0]] = Gi
            s0 += Gi.shape[0]
            z = np.zeros((mdl.p, col.shape[1]))
            add(e.id, col, z, z)
        Gam = np.hstack(cols) if cols else np.zeros((n_s, 0))
        H = np.zeros((mdl.p, n_s))
        H[:, :nx] = gain * mdl.Cy
        H[:, nx + na:] = np.hstack([s[2] for s in sen]) if sen else np.zeros((mdl.p, 0))
        Hd = np.zeros((mdl.p, n_s))
        Hd[:, :nx] = gain * (mdl.Cy @ mdl.Ac)
        a0 = 0
        for Fi, _, Ci, _, Gi in blocks:
            k = Fi.shape[0]
            H[:, nx + a0:nx + a0 + k] = gain * (mdl.Dy @ Gi @ Ci)
            Hd[:, nx + a0:nx + a0 + k] = gain * (CyBc @ Gi @ Ci)
            a0 += k
        J = np.hstack(Jc) if Jc else np.zeros((mdl.p, 0))
        Jd = np.hstack(Jdc) if Jdc else np.zeros((mdl.p, 0))
        return LinearSystem(F, Gam, H, J, Hd, Jd, owners, nx, slice(0, mdl.plant.n), na)

    def _colors(self, mean: MeanResponse, burn: int, dstd: np.ndarray):
        """(:meth:`_gain_shadows`, :meth:`_distortion_colors`) of the own mean after ``burn``,
        shared through :data:`_COLORS` by the models that share the mean response (a diagnosis
        varies the other effects' parameters thousands of times; these fits were a third of a
        nonlinear model's steady state)."""
        mdl = self.model
        # the fitting functions in the key too: a predictor given other ones (a test's "before")
        # does not take the shared fits
        fits = tuple(getattr(f, "__func__", f) for f in (self._gain_shadows, self._distortion_colors))
        key = (mean_key(mdl), self.horizon, fits)

        def compute():
            u = mdl.command.values(0, mean.t.size, mdl.Ts)[burn:].reshape(-1, mdl.m)
            return self._gain_shadows(mean.gain[burn:]), self._distortion_colors(u, dstd**2)
        return _COLORS.get_or_compute(key, compute)

    def _source_acf(self, i: int, D: int) -> np.ndarray:
        """Autocovariance (D + 1, m) of actuator source i per input channel at lags 0..D:
        C F^(d-1) (F Pa C^T + G D^T) for d >= 1, C Pa C^T + D D^T at 0 (Pa its stationary covariance)."""
        Fi, Ga, Ci, Da = self._act_blocks[i]
        Rn = np.zeros((D + 1, self.model.m))
        Rn[0] = np.diag(Da @ Da.T)
        if Fi.shape[0] == 0:
            return Rn
        Pa = solve_discrete_lyapunov(Fi, Ga @ Ga.T)
        Rn[0] += np.diag(Ci @ Pa @ Ci.T)
        X = Fi @ Pa @ Ci.T + Ga @ Da.T
        if D:
            Rn[1:] = np.diagonal(np.einsum("ij,djk->dik", Ci, _powers_apply(Fi, X, D)), axis1=1, axis2=2)
        return Rn

    def _distortion_colors(self, u: np.ndarray, dvar: np.ndarray) -> dict:
        """The color of the nonlinearities' distortion where the actuator noise is colored.

        With n_k Gaussian, std s and correlation rho(d) (all sources of the channel) and f the
        channel's piecewise-linear map, Mehler's formula gives
        Cov(f(u_k + n_k), f(u_l + n_l)) = sum_(j>=1) c_j(k) c_j(l) rho^j / j!, c_j(k) the Hermite
        coefficients of z -> f(u_k + s z). The j = 1 term is the gain's (g_k g_l R_n: the rms
        gain and :meth:`_gain_shadows`); the rest is the distortion's. Two Stein steps give, at the
        kinks x_i (slope change Delta_i, z_ik = (x_i - u_k) / s),
        c_j(k) = s sum_i Delta_i phi(z_ik) He_(j-2)(z_ik), j >= 2, so the distortion's
        autocovariance over the command is D(d) = sum_(j>=2) mean_k[c_j(k) c_j(k+d)] rho(d)^j / j!
        (normalized Hermite functions up to DISTORTION_TERMS; the remainder of its variance
        decays as the last term's). For white noise rho(d) = 0 at d >= 1 and D is white; for an
        AR(1) slower than the sample D(d) follows it (rho^2, rho^3, ...), far from white. D is
        fitted by damped cosines and a white part (:func:`_damped_cosines`), per channel.
        ``u`` (N, m): the command after the transient; ``dvar`` (m,): the mean distortion variance.
        {channel: (white variance, [block (F, G, C, D)])} for the channels with colored noise."""
        out: dict = {}
        N, m = u.shape
        Ts = self.model.Ts
        rads = [float(np.max(np.abs(np.linalg.eigvals(b[0])))) if b[0].shape[0] else 0.0 for b in self._act_blocks]
        colored = [i for i, r in enumerate(rads) if 0.0 < r < 1.0]
        if N < 4 or not colored:
            return out
        rad = max(rads[i] for i in colored)
        # the distortion decays at least as rho^2: lags to 1e-9 of its variance
        D = int(min(N - 1, np.ceil(np.log(1e-9) / (2 * np.log(rad))) + 1))
        Rn = sum((self._source_acf(i, D) for i in range(len(self._act_blocks))), np.zeros((D + 1, m)))
        J = DISTORTION_TERMS
        jj = np.arange(2, J + 1)
        for ch in range(m):
            s2 = Rn[0, ch]
            if s2 <= 0 or dvar[ch] <= 1e-12 * s2 or abs(Rn[1, ch]) < 0.05 * s2:
                continue            # no distortion, or a noise so nearly white that its distortion is white
            s = np.sqrt(s2)
            rho = Rn[:, ch] / s2
            fj, knots = self._channel_map(ch)
            b = np.unique(knots)
            slope = pwl_pieces(fj, b)[2]
            delta = np.diff(slope)                                  # the slope's change at each kink
            # (K, N), clipped at 40 std: phi(40) = exp(-800) is 0 in float64 as it is beyond, and the
            # Hermite functions stay finite (40^19); unclipped, a kink 1e16 std away gives 0 * inf
            z = np.clip((b[:, None] - u[:, ch]) / s, -40.0, 40.0)
            wphi = s * delta[:, None] * np.exp(-0.5 * z * z) / _SQRT2PI
            # c_j / sqrt(j!) = s sum_i Delta_i phi h_(j-2)(z) / sqrt(j (j - 1)), h_n = He_n / sqrt(n!)
            cj = np.empty((J - 1, N))
            h0, h1 = np.ones_like(z), z.copy()
            for n in range(J - 1):
                cj[n] = (wphi * h0).sum(axis=0) / np.sqrt((n + 2) * (n + 1))
                h0, h1 = h1, (z * h1 - np.sqrt(n + 1) * h0) / np.sqrt(n + 2)
            M = _lag_products(cj.T, D)                              # (D + 1, J - 1)
            Dd = (M * rho[:, None] ** jj).sum(axis=1)
            rem = max(float(dvar[ch]) - float(M[0].sum()), 0.0)
            if M[0, -1] > 0:
                Dd += rem * rho ** (J + 1) * M[:, -1] / M[0, -1]
            else:
                Dd[0] += rem
            if Dd[0] <= 0:
                continue
            out[ch] = _damped_cosines(Dd, rad, N, Ts, ch, m, white=True)
        return out

    def _gain_shadows(self, gain: np.ndarray) -> dict:
        """The gain fluctuation's part of each colored actuator source, for :meth:`linear_system`.

        Through a nonlinearity the source n_k reaches the plant as g_k n_k (Bussgang), g_k the
        gain at sample k of the command (0 in a saturation, 1 outside). Over time the product's
        autocovariance is R_g(d) R_n(d), R_g(d) = mean_k g_k g_(k+d) (the gain is the command's,
        independent of the noise): the rms gain on the source's own spectrum is right only at
        d = 0, and too narrow a spectrum when the gain switches within the noise's correlation
        time (a chirp through the limit). Split R_g(d) = gbar^2 + c(d): the mean gain keeps the
        source's own spectrum, and the fluctuation's part h(d) = c(d) R_n(d) is a sum of at most
        :data:`SHADOW_BLOCKS` damped cosines w r^|d| cos(theta d) (a rotating AR(1) of two
        states; theta = 0: an AR(1)), weights w >= 0 fitted to h's spectrum by non-negative least
        squares in relative error on frequencies log-spaced from the horizon's lowest to Nyquist,
        the variance sum w = h(0) held exactly (gbar^2 + c(0) = mean g^2, as with the rms gain).
        Poles r from the source's slowest to about 1/20 (a few samples), theta from 0 to Nyquist.
        Per input channel; any source with states (a white one is exact with the rms gain).
        ``gain`` (N, m) over the model's own command after its transient.
        {source index: (gbar (m,), [block (F, G, C, D)])}."""
        out: dict = {}
        N = gain.shape[0]
        if N < 4:
            return out
        mdl = self.model
        Ts, m = mdl.Ts, mdl.m
        gbar = gain.mean(axis=0)
        dev = gain - gbar
        # the fluctuation is worth more blocks only where the gain switches (:func:`gain_switches`)
        active = gain_switches(gain)
        for i, (Fi, Ga, Ci, Da) in enumerate(self._act_blocks):
            if Fi.shape[0] == 0:
                continue
            rad = float(np.max(np.abs(np.linalg.eigvals(Fi))))
            if not active.any() or not 0.0 < rad < 1.0:
                continue
            D = int(min(N - 1, np.ceil(np.log(1e-9) / np.log(rad)) + 1))
            Rn = self._source_acf(i, D)
            comps = []
            for j in np.flatnonzero(active & (Rn[0] > 0)):
                comps += _damped_cosines(_lag_products(dev[:, j:j + 1], D)[:, 0] * Rn[:, j], rad, N, Ts, j, m)[1]
            if comps:
                out[i] = (gbar, comps)
        return out

    def _distortion_owner(self) -> str:
        """The effect id the distortion is reported under: the (first) nonlinearity."""
        return self._nonlin[0].id

    # -- primitives (non-state effects) ----------------------------------------------------------------
    def _primitives(self, mean: MeanResponse | None = None, jitter_ydot2: np.ndarray | None = None):
        """[(effect id, kind, params)] for white / walk / tone / jitter contributions."""
        out = []
        for e in self.model.effects.values():
            if hasattr(e, "spectral"):
                for prim in e.spectral():
                    out.append((e.id,) + tuple(prim))
        return out

    # -- covariance recursion (seed section 4) -----------------------------------------------------------
    def covariance(self, n: int, command: np.ndarray | None = None) -> Covariance:
        """P_k and S_y,k for k = 0..n-1 from P_0 = 0 (all noise states start at zero, as in the
        simulation); S_y,k includes R_b,k = R_b,0 + k Q_b, the white primitives and the jitter's
        signal-dependent variance std_s^2 E[ydot_k^2]."""
        mean = self.mean_response(n, command)
        n = mean.t.size
        parts: dict = {}
        const = not self._nonlin
        dstd = np.sqrt(mean.distortion_var)
        ls = self.linear_system(None if const else mean.gain[0], None if const else dstd[0])
        n_s = ls.F.shape[0]
        Pj = {eid: np.zeros((n_s, n_s)) for eid in ls.owners}
        P_hist = np.zeros((n, n_s, n_s))
        Sy = {eid: np.zeros((n, self.model.p)) for eid in ls.owners}
        ydot_var = np.zeros((n, self.model.p))
        for k in range(n):
            if not const:
                ls = self.linear_system(mean.gain[k], dstd[k])
            Ptot = np.zeros((n_s, n_s))
            for eid, cols in ls.owners.items():
                Pk = Pj[eid]
                Ptot += Pk
                Jj = ls.J[:, cols]
                Sy[eid][k] = np.einsum("ij,jk,ik->i", ls.H, Pk, ls.H) + np.sum(Jj**2, axis=1)
                Jdj = ls.Jd[:, cols]
                ydot_var[k] += np.einsum("ij,jk,ik->i", ls.Hd, Pk, ls.Hd) + np.sum(Jdj**2, axis=1)
                Gj = ls.Gam[:, cols]
                # P_{k+1} = F P_k F^T + Gamma Gamma^T   (per source; seed section 4)
                Pj[eid] = ls.F @ Pk @ ls.F.T + Gj @ Gj.T
            P_hist[k] = Ptot
        parts.update(Sy)
        k_idx = np.arange(n)
        for eid, kind, *prm in self._primitives():
            if kind == "white":
                parts[eid] = np.broadcast_to(prm[0], (n, self.model.p)).copy()
            elif kind == "walk":
                q, var0 = prm
                parts[eid] = var0 + k_idx[:, None] * q       # R_b,k = R_b,0 + k Q_b
            elif kind == "tone":
                parts[eid] = np.broadcast_to(prm[0] ** 2 / 2.0, (n, self.model.p)).copy()
            elif kind == "jitter":
                parts[eid] = prm[0] * (mean.ydot**2 + ydot_var)
        total = sum(parts.values(), np.zeros((n, self.model.p)))
        return Covariance(P=P_hist, Sy=total, parts=parts)

    # -- steady state ------------------------------------------------------------------------------
    def steady_state(self) -> Steady:
        """Stationary covariance by the discrete Lyapunov equation P = F P F^T + Gamma Gamma^T,
        per source. Signal-dependent terms (jitter, nonlinear gains) are averaged over the
        horizon of the model's own command. The bias walk is reported as a rate, not a variance."""
        if self._steady_cache is not None:
            return self._steady_cache
        # unstable in continuous time, or only as discretized (forward Euler over a Ts beyond
        # 2 / |eigenvalue|: a stiff spring at the seed's 10 ms)
        unstable = (np.any(np.linalg.eigvals(self.model.Ac).real > 0)
                    or np.any(np.abs(np.linalg.eigvals(self.model.Ad)) > 1))
        if unstable:
            # an unstable plant's mean response overflows on the way: its contributions come out
            # None and the callers say the plant is unstable; the overflow warnings are no news
            with np.errstate(over="ignore", invalid="ignore"):
                return self._steady_state()
        return self._steady_state()

    def _steady_state(self) -> Steady:
        mdl = self.model
        notes = []
        # the mean response over the horizon only where a term depends on the signal (the
        # nonlinearities' gains, the jitter's slope, the quantizer's spread): at Ts <= 57 us the
        # horizon is 10^6 samples, seconds and 100s of MB for a model that needs none of it
        needs_mean = bool(self._nonlin) or "sensor.quantization" in mdl.effects or "sensor.jitter" in mdl.effects
        mean = self._own_mean() if needs_mean else None
        avg = self._own_averages(mean) if needs_mean else None
        burn = min(mean.t.size // 2, _settle_samples(mdl)) if needs_mean else 0
        # the gains after the transient (the drive noise's variance grows from zero at the start),
        # over the samples held, the window of their spectral fits (_colors) too
        g = np.sqrt(np.mean(mean.gain[burn:] ** 2, axis=0)) if self._nonlin else None
        dstd = np.sqrt(np.mean(mean.distortion_var[burn:], axis=0)) if self._nonlin else None
        shadow, dcolor = self._colors(mean, burn, dstd) if self._nonlin else ({}, {})
        if self._nonlin:
            notes.append("actuator nonlinearities linearized around the mean drive (seed section 7): "
                         "rms gain " + ", ".join(f"{v:.4g}" for v in g) + ", distortion std "
                         + ", ".join(f"{v:.3g}" for v in dstd)
                         + (" treated as white" if not dcolor else "")
                         + (f", over the first {mean.t.size * mdl.Ts:.4g} s of the command (the samples held at "
                            f"once, HORIZON_MAX) of the {self.span * mdl.Ts:.4g} s horizon"
                            if self.span > mean.t.size else ""))
        for ch, (wvar, comps) in dcolor.items():
            notes.append(f"the distortion of input {ch}'s colored noise is colored too (Hermite terms of the "
                         f"noise's correlation): white std {np.sqrt(wvar):.3g} and {len(comps)} damped cosines")
            dstd[ch] = np.sqrt(wvar)
        for i, (gbar, comps) in shadow.items():
            gf = np.sqrt(np.maximum(g**2 - gbar**2, 0.0))
            notes.append(f"{self._act_src[i].id}: the nonlinearities' gain switches within its correlation "
                         "time: its mean gain " + ", ".join(f"{v:.4g}" for v in gbar) + " on its own "
                         "spectrum, the gain's fluctuation (std " + ", ".join(f"{v:.3g}" for v in gf)
                         + f") on {len(comps)} wider ones (damped cosines fitted to its spectrum)")
        ls = self.linear_system(g, dstd, shadow, [b for _, bl in dcolor.values() for b in bl])
        nx, n_s = ls.n_x, ls.F.shape[0]
        plant_part = slice(0, nx + ls.n_act)
        marginal = False
        walk_y = walk_ydot = np.zeros(mdl.p, bool)     # per output: the walk reaches it (its slope)
        leaked = leak_unit_modes(ls.F[:nx, :nx], mdl.Ac, mdl.Ts)
        if leaked is not None:
            # integrators (A with an eigenvalue 0): the plant's unit modes leak by LEAK per sample, so
            # that every source has a (huge) stationary covariance whose increments are those of the
            # exact walk. Only the plant's own modes: a noise state's near-unit pole is its own model.
            ls.F[:nx, :nx], Vu = leaked
            marginal = True
            # the outputs (and slopes) the walk reaches have no steady-state variance; the others
            # (a motor's speed beside its angle) keep theirs (Vu's columns are orthonormal Schur
            # vectors: unit length)
            walk_y = np.any(np.abs(ls.H[:, :nx] @ Vu) > 1e-9 * np.linalg.norm(ls.H), axis=1)
            walk_ydot = np.any(np.abs(ls.Hd[:, :nx] @ Vu) > 1e-9 * np.linalg.norm(ls.Hd), axis=1)
            if not walk_y.any():
                notes.append("the plant integrates (an eigenvalue of A at 0), but no output sees its walk: "
                             "the outputs keep their steady state")
            else:
                reached = "its output has" if mdl.p == 1 else \
                    "output " + ", ".join(str(j) for j in np.flatnonzero(walk_y)) + f" (of 0..{mdl.p - 1}) has"
                notes.append(f"the plant integrates (an eigenvalue of A at 0): {reached} no steady-state "
                             "variance, only stationary increments (variogram, PSD of the differenced output)")
        rad = np.max(np.abs(np.linalg.eigvals(ls.F[plant_part, plant_part])), initial=0.0)
        stable = bool(rad < 1.0) and not marginal
        marginal = marginal and bool(rad < 1.0)
        contributions: dict = {}
        Ptot = np.zeros((n_s, n_s))
        ydot_var = np.zeros(mdl.p)
        Pj: dict = {}
        Dj: dict = {}           # marginal plants: (I - F) P per source, formed without cancellation
        for eid, cols in ls.owners.items():
            Gj = ls.Gam[:, cols]
            drives_plant = bool(np.any(Gj[plant_part] != 0))
            if drives_plant and not (stable or marginal):
                contributions[eid] = None
                continue
            if marginal:
                Pk, Dj[eid] = lyap_leaky(ls.F, Gj @ Gj.T)
            else:
                Pk = solve_discrete_lyapunov(ls.F, Gj @ Gj.T) if stable else _sensor_lyap(ls, Gj, plant_part)
            Pk = 0.5 * (Pk + Pk.T)
            Pj[eid] = Pk
            Ptot += Pk
            Jj = ls.J[:, cols]
            c = np.einsum("ij,jk,ik->i", ls.H, Pk, ls.H) + np.sum(Jj**2, axis=1)
            if drives_plant and walk_y.any():
                # NaN where the walk reaches: no steady-state variance there (null in the JSON)
                c = None if walk_y.all() else np.where(walk_y, np.nan, c)
            contributions[eid] = c
            ydot_var += np.einsum("ij,jk,ik->i", ls.Hd, Pk, ls.Hd) + np.sum(ls.Jd[:, cols] ** 2, axis=1)
        walk_rate = None
        if marginal:
            # the walk's part of y takes H Pi Gamma w_k per sample (Pi: :func:`unit_projector`)
            HPi = ls.H @ unit_projector(ls.F)
            walk_rate = sum((np.sum((HPi @ ls.Gam[:, c]) ** 2, axis=1) for c in ls.owners.values()),
                            np.zeros(mdl.p)) / mdl.Ts
        slope_ok = stable or (marginal and not walk_ydot.any())
        rate = np.zeros(mdl.p)
        ydot2 = avg.ydot2 if needs_mean else np.zeros(mdl.p)
        for eid, kind, *prm in self._primitives():
            if kind == "white":
                contributions[eid] = np.broadcast_to(prm[0], (mdl.p,)).copy()
            elif kind == "walk":
                rate = rate + prm[0] / mdl.Ts
            elif kind == "tone":
                contributions[eid] = prm[0] ** 2 / 2.0
            elif kind == "jitter":
                contributions[eid] = prm[0] * (ydot2 + ydot_var) if slope_ok or not ydot_var.any() else None
        q = mdl.effects.get("sensor.quantization")
        if q is not None:
            from .effects.sensor_quantization import uniform_model_error
            spread = np.sqrt(avg.y_var + sum(
                v for k, v in contributions.items() if v is not None and k != q.id))
            err = uniform_model_error(spread, q.params["step"])
            if np.any(err > 0.01):
                notes.append("sensor.quantization: the signal spans few steps (std "
                             + ", ".join(f"{s:.3g}" for s in spread) + " vs step "
                             + ", ".join(f"{s:.3g}" for s in q.params["step"])
                             + "): the uniform Delta^2/12 model may not hold")
        if "sensor.jitter" in mdl.effects:
            notes.append("sensor.jitter: first-order Taylor, variance std_s^2 E[ydot^2] averaged over "
                         f"{avg.span_s:.3g} s of the model's command")
        var_y = None if any(v is None for v in contributions.values()) else \
            sum(contributions.values(), np.zeros(mdl.p))
        Pp = Ptot[ls.plant_block, ls.plant_block] if stable else None
        # published whole, the cache last: a predictor shared by threads (the comparison's views) may
        # compute its steady state in two at once, and each reads complete, equal dicts
        self._Pj, self._Dj, self._ls = Pj, Dj, ls
        self._steady_cache = Steady(var_y=var_y, P=Pp, contributions=contributions,
                                    bias_var_rate=rate, stable=stable, notes=notes,
                                    ydot_var=ydot_var if slope_ok else None, walk_var_rate=walk_rate)
        return self._steady_cache

    # -- spectra -------------------------------------------------------------------------------------
    def psd(self, f: np.ndarray) -> tuple[dict, list]:
        """One-sided PSD of the centered measurement per effect at frequencies ``f`` (Hz):
        {effect id: (len(f), p)} in units^2/Hz, and spectral lines [(effect id, f_hz, power)]."""
        st = self.steady_state()
        mdl = self.model
        ls = self._ls
        f = np.asarray(f, float)
        z = np.exp(2j * np.pi * f * mdl.Ts)
        out: dict = {}
        lines = []
        if ls.Gam.shape[1]:
            n_s = ls.F.shape[0]
            M = z[:, None, None] * np.eye(n_s) - ls.F               # (nf, n_s, n_s)
            X = np.linalg.solve(M, np.broadcast_to(ls.Gam, (f.size,) + ls.Gam.shape))
            T = ls.H @ X + ls.J                                       # (nf, p, n_e)
            for eid, cols in ls.owners.items():
                c = st.contributions.get(eid)
                # NaN at an output the plant's walk reaches (no stationary spectrum there)
                out[eid] = None if c is None else \
                    2.0 * mdl.Ts * np.sum(np.abs(T[:, :, cols]) ** 2, axis=2) + np.where(np.isnan(c), np.nan, 0.0)
        for eid, kind, *prm in self._primitives():
            if kind == "white":
                out[eid] = np.broadcast_to(2.0 * mdl.Ts * prm[0], (f.size, mdl.p)).copy()
            elif kind == "jitter":
                c = st.contributions.get(eid)
                out[eid] = None if c is None else np.broadcast_to(2.0 * mdl.Ts * c, (f.size, mdl.p)).copy()
            elif kind == "walk":
                # b_{k+1} = b_k + sqrt(q) eta: S(f) = 2 Ts q / |1 - e^{-i w Ts}|^2
                with np.errstate(divide="ignore"):
                    out[eid] = 2.0 * mdl.Ts * prm[0] / (4.0 * np.sin(np.pi * f * mdl.Ts) ** 2)[:, None]
            elif kind == "tone":
                out[eid] = np.zeros((f.size, mdl.p))
                for j in range(mdl.p):
                    lines.append((eid, float(prm[1][j]), float(prm[0][j] ** 2 / 2.0), j))
        return out, lines

    def acf(self, lags: int | np.ndarray, quantization: bool = True, skip: tuple = ()) -> dict:
        """Autocovariance R(d) per stationary effect, d = 0..lags-1 (samples): {id: (L, p)}.
        The bias walk is nonstationary and has no ACF (see :meth:`variogram`). The quantizer's
        error is correlated over the model's own command (:meth:`quantization_acf`); with
        ``quantization=False`` it is left white (a caller that has the record's motion).
        ``skip``: state sources left out (not computed, no entry). Through a plant that
        integrates a source's R is the leaked model's, ~q / 2e-11 at every lag: use
        :meth:`variogram` for it."""
        L = int(lags) if np.isscalar(lags) else int(np.max(lags)) + 1
        st = self.steady_state()
        mdl = self.model
        ls = self._ls
        d = np.arange(L)
        out: dict = {}
        for eid, cols in ls.owners.items():
            if eid in skip:
                continue
            if eid not in self._Pj:
                out[eid] = None
                continue
            Pk = self._Pj[eid]
            X = np.concatenate([Pk @ ls.H.T, ls.Gam[:, cols] @ ls.J[:, cols].T], axis=1)   # (n_s, 2p)
            F, H = ls.F, ls.H
            # only the states this source reaches (when nothing else is driven by them), and only
            # up to where its slowest mode has decayed below 1e-13 (zero beyond, as in the diagnosis)
            on = np.flatnonzero(np.any(X != 0, axis=1) | np.any(Pk != 0, axis=1))
            on = np.union1d(np.arange(mdl.n_x), on)
            off = np.setdiff1d(np.arange(F.shape[0]), on)
            if off.size == 0 or not np.any(F[np.ix_(off, on)]):
                F, H, X = F[np.ix_(on, on)], H[:, on], X[on]
            rho = float(np.max(np.abs(np.linalg.eigvals(F)), initial=0.0)) if F.size else 0.0
            K = L if rho >= 1 else min(L, int(np.ceil(np.log(1e-13) / np.log(max(rho, 1e-300)))) + 2 + F.shape[0])
            FX = _powers_apply(F, X, K)                                                     # (K, n, 2p)
            p = mdl.p
            Rd = np.zeros((L, p))
            Rd[:K] = np.diagonal(np.einsum("ij,ljk->lik", H, FX[:, :, :p]), axis1=1, axis2=2)
            cross = np.diagonal(np.einsum("ij,ljk->lik", H, FX[:, :, p:]), axis1=1, axis2=2)
            Rd[1:K + 1] += cross[:L - 1]                  # H F^{d-1} Gamma J^T for d >= 1
            Rd[0] += np.sum(ls.J[:, cols] ** 2, axis=1)  # J J^T at d = 0
            out[eid] = Rd
        for eid, kind, *prm in self._primitives():
            if kind in ("white", "jitter"):
                v = prm[0] if kind == "white" else st.contributions.get(eid)
                if v is None:
                    out[eid] = None
                    continue
                R = np.zeros((L, mdl.p))
                R[0] = v
                out[eid] = R
            elif kind == "tone":
                out[eid] = prm[0] ** 2 / 2.0 * np.cos(2 * np.pi * d[:, None] * prm[1] * mdl.Ts)
        if quantization and "sensor.quantization" in mdl.effects and all(v is not None for v in out.values()):
            gam = {eid: R[0] - R for eid, R in out.items()}
            gam.update(self._walk_variograms(L))
            out["sensor.quantization"] = self.quantization_acf(gam, self.motion(max(L, self.horizon)))
        return out

    def _walk_variograms(self, L: int) -> dict:
        """{effect id: d Q_b / 2, d = 0..L-1 (L, p)} of the bias walks."""
        d = np.arange(L)[:, None]
        return {eid: d * prm[0] / 2.0 * np.ones(self.model.p)
                for eid, kind, *prm in self._primitives() if kind == "walk"}

    # -- the quantizer's correlated error (:mod:`.effects.sensor_quantization`) ----------------------------
    def motion(self, n: int, mean_y: np.ndarray | None = None, k0: int = 0) -> np.ndarray:
        """The deterministic part of the signal before the quantizer over n samples: the mean
        response (``mean_y`` from sample ``k0``, default the model's own command after its
        transient) plus the tones (phase 0: only their increments matter, over many periods)."""
        mdl = self.model
        if mean_y is None:
            k0 = _settle_samples(mdl)
            mean_y = self.mean_response(k0 + n).y[k0:]
        mean_y = np.asarray(mean_y, float)
        t = (k0 + np.arange(mean_y.shape[0])) * mdl.Ts
        out = mean_y.copy()
        for eid, kind, *prm in self._primitives():
            if kind == "tone":
                out = out + np.asarray(prm[0], float) * np.sin(2 * np.pi * t[:, None] * np.asarray(prm[1], float))
        return out

    def tone_ids(self) -> set:
        """Ids of the effects that are spectral lines (deterministic in a record: random phase only)."""
        return {eid for eid, kind, *_ in self._primitives() if kind == "tone"}

    def before_quantizer(self, gam: dict) -> np.ndarray:
        """The variogram (L, p) of the random part of the signal before the quantizer: the sum of
        the effects' variograms ``gam`` ({id: (L, p)}) but the quantizer's own and the tones' (the
        tones are deterministic: in :meth:`motion`)."""
        q = "sensor.quantization"
        tones = self.tone_ids()
        L = next(iter(gam.values())).shape[0]
        return sum((v for eid, v in gam.items() if eid != q and eid not in tones and v is not None),
                   np.zeros((L, self.model.p)))

    def quantization_acf(self, gam: dict, motion: np.ndarray | None, cache: Memo | None = None,
                         moments=None, stein: bool = True) -> np.ndarray:
        """R_e(d) of the quantizer's error (L, p) from the other effects' variograms ``gam`` ({id:
        (L, p)}, :meth:`before_quantizer`) and the deterministic ``motion``. ``moments``
        (:meth:`quantizer_moments`): the error's conditional mean is in the mean response; the part
        is then the covariance about it, the error's covariance with the noise included unless
        ``stein`` is False (the likelihood scales the noise's own parts instead)."""
        from .effects.sensor_quantization import quantization_acf
        step = self.model.effects["sensor.quantization"].params["step"]
        cross = None
        if moments is not None and stein:
            # c(d) of the stationary random part: a walk's covariance with the error (2 h times its
            # growing variance) is left out, and so are the tones (deterministic here, in the motion)
            walks = {eid for eid, kind, *_ in self._primitives() if kind == "walk"}
            st = self.steady_state()
            stat = {eid: v for eid, v in gam.items() if eid not in walks}
            keep = set(stat) - {"sensor.quantization"} - self.tone_ids()
            # (a source through a plant that integrates is left out where its walk reaches: NaN)
            sig2 = sum((np.nan_to_num(np.asarray(st.contributions[e], float)) for e in keep
                        if st.contributions.get(e) is not None), np.zeros(self.model.p))
            cross = sig2 - self.before_quantizer(stat)
        return quantization_acf(step, self.before_quantizer(gam), motion, cache, moments, cross)

    def quantizer_moments(self, mu: np.ndarray, k0: int = 0):
        """The quantizer's conditional moments (:func:`.effects.sensor_quantization.conditional_moments`)
        over a record whose mean before the quantizer is ``mu`` (n, p) from sample ``k0``: the
        random part's variance is the stationary one of every other effect plus a bias walk's
        growth from its start. A tone counts as noise of variance A^2 / 2 here (its phase is not
        in the mean response: a large one spreads the signal over the steps and the mean goes),
        while the covariance (:meth:`quantization_acf`) follows it in the motion: an approximation
        for a tone beside a coarse quantizer. A jitter counts at the model's own command's level.
        None without a quantizer or a stationary prediction, or when no output's error depends
        on mu."""
        from .effects.sensor_quantization import conditional_moments
        q = self.model.effects.get("sensor.quantization")
        if q is None:
            return None
        st = self.steady_state()
        if any(v is None or np.any(np.isnan(v)) for v in st.contributions.values()):
            return None
        from .effects.sensor_quantization import mean_matters
        mu = np.asarray(mu, float).reshape(len(mu), -1)
        sig2 = sum((np.asarray(v, float) for e, v in st.contributions.items() if e != q.id), np.zeros(self.model.p))
        walk0 = sum((e.init_std**2 for e in self.model.effects.values() if e.id == "sensor.bias_walk"),
                    np.zeros(self.model.p))
        # the smallest variance (the record's start) decides whether any sample's mean is there
        step = np.broadcast_to(np.asarray(q.params["step"], float), (self.model.p,))
        if not np.any(mean_matters(step, sig2 + walk0)):
            return None
        if np.any(st.bias_var_rate > 0) or np.any(walk0 > 0):
            t = (k0 + np.arange(mu.shape[0]))[:, None] * self.model.Ts
            sig2 = sig2 + walk0 + st.bias_var_rate * t
        mo = conditional_moments(q.params["step"], mu, sig2)
        return mo if mo.active.any() else None

    def expected_welch(self, nperseg: int, window: str = "hann") -> dict:
        """E[Welch estimate] of the centered measurement per stationary effect: {id: (nperseg//2+1, p)}
        at f_j = j / (nperseg Ts), units^2/Hz, one-sided with every bin (DC and Nyquist too)
        doubled, the convention of :func:`service.stats.welch`.

        The predicted spectrum seen through the estimator's window, exact for the sampled process:
        E|sum_n w_n x_n e^{-i w n}|^2 = sum_d R(d) c_w(d) e^{-i w d}, c_w(d) = sum_n w_n w_{n+d}
        (Percival & Walden 1993, eq. 186e), divided by fs sum w^2 and doubled except at DC and
        Nyquist. Leakage at resonances and tones is thus in the prediction, not in the error.
        Segment-mean removal (detrend "constant") biases only the lowest two or three bins.
        The bias walk (nonstationary) has no entry.
        """
        from scipy.signal import get_window

        from ..stats.psd import window_autocorrelation

        L = int(nperseg)
        w = get_window(window, L)
        c = window_autocorrelation(w)                        # c_w(d), d = 0..L-1
        out = {}
        for eid, R in self.acf(L).items():
            if R is None:
                out[eid] = None
                continue
            g = R * c[:, None]
            E = 2.0 * np.fft.rfft(g, axis=0).real - g[0]
            E *= 2.0 * self.model.Ts / np.sum(w**2)
            out[eid] = E
        return out

    def variogram(self, L: int, quantization: bool = True) -> dict:
        """gamma(d) = E[(y_{k+d} - y_k)^2] / 2, d = 0..L-1, per effect {id: (L, p)}; stationary
        effects R(0) - R(d), the bias walk d Q_b / 2. ``quantization``: as in :meth:`acf`."""
        self.steady_state()
        if not self._Dj:
            out = {eid: None if R is None else R[0] - R for eid, R in self.acf(L, quantization).items()}
            out.update(self._walk_variograms(L))
            return out
        # a plant that integrates: the sources through it from (I - F) P (no R(0) at the walk's scale)
        out = {eid: None if R is None else R[0] - R for eid, R in self.acf(L, False, skip=tuple(self._Dj)).items()
               if eid != "sensor.quantization"}
        out.update({eid: self._increments(eid, L) for eid in self._Dj})
        out.update(self._walk_variograms(L))
        if quantization and "sensor.quantization" in self.model.effects:
            R = self.quantization_acf(out, self.motion(max(L, self.horizon)))
            out["sensor.quantization"] = R[0] - R
        return out

    def _increments(self, eid: str, L: int) -> np.ndarray:
        """gamma(d), d = 0..L-1 (L, p), of a source through a plant that integrates:
        R(0) - R(d) = H (I - F^d) P H^T + J J^T - H F^(d-1) Gamma J^T, with
        (I - F^d) P = sum_{j<d} F^j D, D = (I - F) P formed without cancellation."""
        ls = self._ls
        cols = ls.owners[eid]
        H, J, G = ls.H, ls.J[:, cols], ls.Gam[:, cols]
        p = self.model.p
        X = np.concatenate([self._Dj[eid] @ H.T, G @ J.T], axis=1)        # (n_s, 2p)
        FX = _powers_apply(ls.F, X, max(L - 1, 1))                          # F^j X, j = 0..L-2
        HX = np.einsum("ij,ljk->lik", H, FX)
        g = np.zeros((L, p))
        if L > 1:
            g[1:] = np.cumsum(np.diagonal(HX[:, :, :p], axis1=1, axis2=2), axis=0)[:L - 1]
            g[1:] += np.sum(J**2, axis=1) - np.diagonal(HX[:, :, p:], axis1=1, axis2=2)[:L - 1]
        return g

    def allan(self, m: np.ndarray) -> dict:
        """Allan variance per effect at averaging factors ``m`` (tau = m Ts): {id: (len(m), p)},
        exact for the sampled process (formula in the module docstring)."""
        m = np.asarray(m, dtype=np.int64)
        L = int(2 * m.max())
        out = {}
        for eid, gam in self.variogram(L).items():
            out[eid] = None if gam is None else allan_from_variogram(gam, m)
        return out


def allan_from_variogram(gam: np.ndarray, m: np.ndarray) -> np.ndarray:
    """AVAR(m) = -(1/m^2) sum_{d=1}^{2m-1} c_m(d) gamma(d), O(1) per m with prefix sums."""
    d = np.arange(gam.shape[0], dtype=float)[:, None]
    S0 = np.cumsum(gam, axis=0)               # S0[n] = sum_{d<=n} gamma(d) (gamma(0) = 0)
    S1 = np.cumsum(d * gam, axis=0)
    mm = m.astype(float)[:, None]
    a = 2 * mm * S0[m] - 3 * S1[m]
    b = -2 * mm * (S0[2 * m - 1] - S0[m]) + (S1[2 * m - 1] - S1[m])
    return -(a + b) / mm**2


def _lag_products(x: np.ndarray, D: int) -> np.ndarray:
    """mean_k x_k x_(k+d) over the overlap, d = 0..D, per column of x (N, c): (D + 1, c), by FFT."""
    N = x.shape[0]
    n2 = 1 << int(N + D).bit_length()
    spec = np.fft.rfft(x, n2, axis=0)
    return np.fft.irfft(np.abs(spec) ** 2, n2, axis=0)[:D + 1] / (N - np.arange(D + 1))[:, None]


def _nnls(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin ||A x - b||, x >= 0: scipy's active-set NNLS, and where it runs out of iterations
    (it does on some of these fits: near-collinear spectra, the variance row 10^4 above the
    rest) the bounded-variable least squares of lsq_linear."""
    from scipy.optimize import lsq_linear, nnls
    try:
        return nnls(A, b, maxiter=20 * A.shape[1])[0]
    except RuntimeError:
        return lsq_linear(A, b, bounds=(0.0, np.inf), method="bvls").x


def _cosine_sums(w: np.ndarray, c: np.ndarray) -> np.ndarray:
    """sum_(d=1..D) c_d cos(w d) at each frequency w (rad/sample), c = (c_1, ..., c_D). The
    angle-addition split d = q B + r (B ~ sqrt(D)) needs cos and sin at (B + Q) multiples of w per
    frequency, not D: at D in the thousands the table of cos(w d) was most of a fit's time."""
    D = c.size
    B = max(1, int(np.ceil(np.sqrt(D + 1))))
    Q = -(-(D + 1) // B)
    H = np.zeros(Q * B)
    H[1:D + 1] = c
    H = H.reshape(Q, B)
    wr = np.outer(np.arange(B), w)                      # (B, F)
    wq = np.outer(np.arange(Q) * B, w)                  # (Q, F)
    return np.einsum("qf,qf->f", np.cos(wq), H @ np.cos(wr)) - np.einsum("qf,qf->f", np.sin(wq), H @ np.sin(wr))


def gain_switches(gain: np.ndarray) -> np.ndarray:
    """Per input (m,): whether the nonlinearity's gain (N, m) fluctuates over the record: its
    variance a visible share of its mean square, and of the source's own power (the gain is at most
    1: a saturation that clips the whole record leaves gains of 1e-68, whose fluctuation's
    spectrum is all underflow)."""
    c0 = np.var(gain, axis=0)
    return (c0 > 1e-6 * np.mean(gain**2, axis=0)) & (c0 > 1e-12)


def _damped_cosines(h: np.ndarray, rad: float, N: int, Ts: float, j: int, m: int, white: bool = False,
                    nblocks: int = SHADOW_BLOCKS):
    """An autocovariance h(d), d = 0..D, of a noise on input channel j, as at most ``nblocks``
    damped cosines w r^|d| cos(theta d) (a rotating AR(1) of two states; theta = 0: an AR(1)),
    and with ``white`` a white part besides. Weights w >= 0 by non-negative least squares on h's
    spectrum in relative error, at 160 frequencies log-spaced from 1 / (N Ts) to Nyquist, with
    the variance sum w = h(0) held exactly (a row weighted far above the spectrum's). Poles r from
    ``rad`` (the slowest source's) to about 1/20 (a few samples), theta from 0 to Nyquist.
    (white variance, [block (F, G, C, D) of m input channels]); a block's variance is in its G."""
    f = np.geomspace(1.0 / (N * Ts), 0.5 / Ts, 160)
    w = 2 * np.pi * f * Ts
    r = rad ** np.geomspace(1.0, np.log(0.05) / np.log(rad), 7)
    th = np.concatenate([[0.0], 2 * np.pi * Ts * np.geomspace(f[0], 0.45 / Ts, 12)])
    R, T = np.meshgrid(r, th, indexing="ij")
    R, T = R.ravel(), T.ravel()
    # the damped cosines' spectra (unit variance), as columns: (P(w - theta) + P(w + theta)) / 2
    B = 0.5 * ((1 - R**2) / (1 - 2 * R * np.cos(w[:, None] - T) + R**2)
               + (1 - R**2) / (1 - 2 * R * np.cos(w[:, None] + T) + R**2))
    if white:
        B = np.hstack([B, np.ones((f.size, 1))])
    S = h[0] + 2.0 * _cosine_sums(w, h[1:])
    scale = 1.0 / (np.abs(S) + 1e-3 * np.max(np.abs(S)))
    # the variance held: sum w / h(0) = 1 as one row weighted far above the spectrum's (whose
    # relative errors are O(1) per unit of w / h(0))
    big = 1e3 * np.sqrt(f.size)
    Mx = np.vstack([B * scale[:, None], np.full((1, B.shape[1]), big / h[0])])
    rhs = np.append(S * scale, big)
    wt = _nnls(Mx, rhs)
    order = [k for k in np.argsort(wt[:R.size])[::-1][:nblocks] if wt[k] > 0]
    keep = order + ([R.size] if white else [])
    wt_k = _nnls(Mx[:, keep], rhs)
    comps = []
    for k, wk in zip(order, wt_k):
        if wk <= 0:
            continue
        rk, tk = R[k], T[k]
        C = np.zeros((m, 1 if tk == 0 else 2))
        C[j, 0] = 1.0
        Fk = np.array([[rk]]) if tk == 0 else rk * np.array([[np.cos(tk), -np.sin(tk)], [np.sin(tk), np.cos(tk)]])
        Gk = np.sqrt(wk * (1 - rk**2)) * np.eye(Fk.shape[0])
        comps.append((Fk, Gk, C, np.zeros((m, Fk.shape[0]))))
    return (float(wt_k[-1]) if white else 0.0), comps


def _powers_apply(F: np.ndarray, X: np.ndarray, L: int) -> np.ndarray:
    """F^d X for d = 0..L-1 by doubling: log2(L) batched products."""
    out = np.empty((L,) + X.shape)
    out[0] = X
    size, Fp = 1, F.copy()
    while size < L:
        take = min(size, L - size)
        out[size:size + take] = Fp @ out[:take]
        Fp = Fp @ Fp
        size += take
    return out


UNIT_REL = 1e-7        # |lambda| / ||A|| within which a continuous eigenvalue is an integrator's
LEAK = 1e-11            # what the prediction takes from an integrator's eigenvalue per sample


def unit_tol(A: np.ndarray, Ts: float) -> float:
    """|lambda_d - 1| within which a discrete eigenvalue is an integrator's: its continuous
    eigenvalue within UNIT_REL ||A|| of 0 (lambda_d = e^(lambda Ts) ~ 1 + lambda Ts), and never
    below rounding (1e-12)."""
    return max(2.0 * UNIT_REL * float(np.linalg.norm(A, 2)) * Ts, 1e-12)


def leak_unit_modes(F: np.ndarray, A: np.ndarray, Ts: float, leak: float = LEAK):
    """(F with its integrators' eigenvalues set to 1 - ``leak``, an orthonormal basis of their
    invariant subspace (n, u)) when the continuous A has eigenvalues 0 (within UNIT_REL ||A||: a
    pole a million times slower than the plant's fastest dynamics is an integrator to any record)
    that are semisimple (A's nullity, by its singular values at the same tolerance, equals their
    number) and every other eigenvalue of F is inside the unit circle; else None (no integrator,
    an unstable mode, or a chain of integrators, whose increments are not stationary either).
    F is A's discretization (zoh or Euler: an eigenvalue 0 of A is an eigenvalue 1 of F).

    Why a leak: an integrator's output is a random walk plus a stationary part, correlated through
    the noise they share. With the eigenvalue at 1 - eps every source has a stationary covariance
    (its walk part ~ q / (2 eps)), and every statistic the diagnosis uses from it, increments and
    differences (variogram, differenced-output spectrum), is the exact walk's to a relative
    O(eps d) at lag d (1e-5 at 10^6), provided they are formed from (I - F) P
    (:func:`lyap_leaky`), not as differences of covariances at the walk's scale."""
    if F.size == 0:
        return None
    from scipy.linalg import schur
    nA = float(np.linalg.norm(A, 2))
    tolA = UNIT_REL * nA
    uA = int(np.sum(np.abs(np.linalg.eigvals(A)) <= tolA)) if nA > 0 else A.shape[0]
    if uA == 0:
        return None
    null = int(np.sum(np.linalg.svd(A, compute_uv=False) <= tolA)) if nA > 0 else A.shape[0]
    if null != uA:                      # a chain of integrators (a double integrator)
        return None
    T, Z, u = schur(F, output="real", sort=lambda re, im: abs(complex(re, im) - 1.0) <= unit_tol(A, Ts))
    lam = np.linalg.eigvals(T[u:, u:]) if u < F.shape[0] else np.zeros(0)
    if u != uA or np.any(np.abs(lam) >= 1.0):
        return None
    T = T.copy()
    T[:u, :u] = (1.0 - leak) * np.eye(u)
    return Z @ T @ Z.T, Z[:, :u]


def _decouple(F: np.ndarray, leak: float = LEAK):
    """(S, Si, T11, T22, u): F = S diag(T11, T22) S^-1 with the u leaked integrator modes
    (:func:`leak_unit_modes`) in T11 and the others in T22: an ordered real Schur form, decoupled
    by a Sylvester solve (T11 X - X T22 = -T12, S = Z [[I, X], [0, I]])."""
    from scipy.linalg import schur, solve_sylvester
    T, Z, u = schur(F, output="real", sort=lambda re, im: abs(complex(re, im) - 1.0) < 2 * leak)
    n = F.shape[0]
    T11, T12, T22 = T[:u, :u], T[:u, u:], T[u:, u:]
    X = solve_sylvester(T11, -T22, -T12) if 0 < u < n else np.zeros((u, n - u))
    Si = np.eye(n)
    Si[:u, u:] = -X
    Si = Si @ Z.T
    S = Z.copy()
    S[:, u:] += Z[:, :u] @ X
    return S, Si, T11, T22, u


def unit_projector(F: np.ndarray, leak: float = LEAK) -> np.ndarray:
    """The spectral projector onto F's leaked integrator modes: Pi F = F Pi = (1 - leak) Pi, so the
    walk's part of the state, Pi x, takes Pi Gamma w_k per sample (Pi Gamma w_k also carries a
    colored source's whole low-frequency gain: its state's effect on the walk is in Pi)."""
    S, Si, _, _, u = _decouple(F, leak)
    return S[:, :u] @ Si[:u]


def lyap_leaky(F: np.ndarray, Q: np.ndarray, leak: float = LEAK) -> tuple[np.ndarray, np.ndarray]:
    """(P, (I - F) P), P = F P F^T + Q, for an F whose integrator modes were leaked to 1 - ``leak``
    (:func:`leak_unit_modes`), solved with those modes apart (:func:`_decouple`): a direct solve's
    conditioning (~1 / (2 leak)) would spread the walk's error ~1e-16 / leak of its size over the
    stable block. The three blocks are solved each at its own conditioning: only the walk's own
    block is ill-conditioned, and its error stays in it."""
    S, Si, T11, T22, u = _decouple(F, leak)
    n = F.shape[0]
    if u == 0:
        P = solve_discrete_lyapunov(F, Q)
        return P, (np.eye(n) - F) @ P
    Qb = Si @ Q @ Si.T
    Pb = np.zeros((n, n))
    Pb[:u, :u] = solve_discrete_lyapunov(T11, Qb[:u, :u])
    if u < n:
        Pb[u:, u:] = solve_discrete_lyapunov(T22, Qb[u:, u:])
        # P12 = T11 P12 T22^T + Q12, column-major vec: (I - T22 (x) T11) vec P12 = vec Q12
        k = np.eye(u * (n - u)) - np.kron(T22, T11)
        P12 = np.linalg.solve(k, Qb[:u, u:].reshape(-1, order="F")).reshape((u, n - u), order="F")
        Pb[:u, u:] = P12
        Pb[u:, :u] = P12.T
    P = S @ Pb @ S.T
    # (I - F) P = S (I - Tb) Pb S^T with the walk's block (I - T11) P11 = leak P11 ~ q / 2 formed
    # without the cancellation (I - F) P would have at the walk's scale
    IT = np.eye(n)
    IT[:u, :u] -= T11
    IT[u:, u:] -= T22
    D = S @ (IT @ Pb) @ S.T
    return 0.5 * (P + P.T), D


def _sensor_lyap(ls: LinearSystem, Gj: np.ndarray, plant_part: slice) -> np.ndarray:
    """Lyapunov on the sensor-state block only (used when the plant itself is not stable)."""
    n_s = ls.F.shape[0]
    s = slice(plant_part.stop, n_s)
    P = np.zeros((n_s, n_s))
    if s.stop > s.start:
        P[s, s] = solve_discrete_lyapunov(ls.F[s, s], (Gj @ Gj.T)[s, s])
    return P


def _settle_samples(model) -> int:
    """Samples for the plant's transient to decay to ~1e-6 (ln 1e6 ~ 14 time constants)."""
    ev = np.linalg.eigvals(model.Ad)
    ev = np.abs(ev[np.abs(ev - 1.0) > unit_tol(model.Ac, model.Ts)])   # an integrator's never settles: the others
    r = np.max(ev, initial=0.0)
    if r >= 1.0 or r == 0.0:
        return 0
    return int(min(np.ceil(14.0 / -np.log(r)), 10**7))
