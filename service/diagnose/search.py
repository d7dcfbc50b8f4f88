"""Which physical effect is missing: fit every candidate of the catalogue, rank, add, repeat.

A *hypothesis* is a model plus the set of its parameters that are free (fitted to the data); the
parameters of the user's model stay at the user's values unless a candidate frees them (``refit``:
the effect is there but a value is wrong). Every hypothesis is scored by one likelihood:

    l = l_Whittle(residual spectrum | the hypothesis' noise spectrum)      (:mod:`.whittle`)
        + l_grid   (values on a grid: quantization)
        + l_mod    (residual power that follows the slope: jitter)
        + l_ramp   (the first and last tenth of the record, which the periodogram's taper weighs
                    down: the mean response there, by whitened least squares; :class:`.whittle.Ramps`)

A record from rest adds l_level (:func:`.whittle.level_loglik`): its residual's mean against the
spread the hypothesis predicts for it. Differencing removes the record's level, and with it what
a step command says about a mean effect (a saturation, a dead zone, a scale factor set the level
the output settles at: under a step the level pins a saturation's limit ~10x more tightly than
the differenced likelihood does). It enters the search over a mean effect's parameter and that
parameter's profile interval (``Fit.objective``), not the comparison between hypotheses: under
slow noise (a walk, a Gauss-Markov bias of long tau) the mean is not independent of the
differenced record, and in the comparison its marginal density took a hidden walk for a
Gauss-Markov bias.

Hypotheses are compared by Delta BIC = 2 Delta l - k ln n (k free parameters added, n the
number of samples times outputs; Schwarz 1978). A candidate is added when its Delta BIC exceeds
:data:`THRESHOLD` (10: "very strong" evidence, Kass & Raftery 1995), then every parameter freed so
far is refitted jointly and the search repeats, so a second hidden effect is found with the first
one's parameters adjusted to it (an AR(1) that first took a bias walk's low-frequency power gives
it back). How each effect is fitted is declared by the effect itself (``Effect.fit``,
:class:`service.model.effects.base.FitSpec`):

* ``noise`` sources (white, AR(1), Gauss-Markov, bias walk, process noise): the expected
  periodogram is linear in each source's variance, so the variances are fitted together by
  L-BFGS-B on their logarithms (the profile over the shape parameters, e.g. a correlation time,
  by a grid then golden-section search);
* ``mean`` effects (scale factor, lag, saturation, dead zone) change the predicted response to the
  recorded command: the residual is recomputed for each value of their parameter;
* ``line`` (tone): a deterministic sinusoid in a record; peaks of I_f / E_f beyond what the
  exponential distribution allows over all bins (P < 1e-3) that also stand out from the data's
  spectrum around them (:func:`tone_peaks`) are candidates (except at a line of the
  recorded command or one of its first :data:`HARMONICS` harmonics: the mean response's error), the frequency refined by
  maximizing the periodogram, amplitude and phase by least squares; 3 parameters;
* ``grid`` (quantization): every value on a grid of step Delta. Under any continuous model the
  chance that a value falls within 1e-6 Delta of a grid point is 2e-6, so l_grid = n ln(1/2e-6);
* ``modulated`` (jitter): its power is white on average, like sensor noise, but follows the
  square of the slope: the squared differenced residual z_q is modelled as Gamma (chi-squared 1)
  with mean a + b x_q (x_q the predicted slope squared, b = std_s^2, a fixed by the average level),
  a quasi-likelihood divided by the dependence factor 1 + 2 sum rho_d(h)^2.

95 % intervals are profile-likelihood intervals (2 Delta l = 3.84). The jitter's is adjusted by its
sandwich (Godambe) variance (:func:`godambe_factor`): its Whittle part takes a modulated noise as
stationary and its modulation term reads the same squared residuals, so the plain likelihood
overstates what they say about std_s (about 2x in variance under a sine command).
"""

from __future__ import annotations

import hashlib
import math
import os
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import scipy.fft as sfft

from .. import parallel
from ..memo import Memo
from ..model import ModelError
from ..model.effects import CATALOGUE
from ..model.predict import free_response_fit, gain_switches, mean_key as _mean_key
from ..model.simulate import lsim
from . import whittle as W

THRESHOLD = 10.0          # Delta BIC to add an effect
REL_BW = 0.01             # frequency groups: at most 1 % of their frequency wide (Whittle on group means)
CHI2_95 = 3.841           # chi2_1 95 % point: two-sided profile intervals
CHIBAR2_95 = 2.706        # 95 % point of 1/2 chi2_0 + 1/2 chi2_1: a parameter whose null value is on
                          # its boundary (Self & Liang 1987), as in the nested pairs Search.choice ranks
MAX_SHIFTS = 4            # a local shape search may move its bracket this many times (Hypotheses._search)
LINE_SHARE = 0.01         # a command line carries at least 1 % of the command's power (Data.command_lines),
COMB_LINES = 20           # ... and a command with more such lines is a comb (a repeated chirp): none
HARMONICS = 7             # a residual line at up to the 7th harmonic of a command line is the mean response's
WORKERS = 2               # candidates fitted concurrently on long records (a forked process or threads)
PARALLEL_MIN = 50_000     # samples x outputs from which they are
MORE_ROUNDS = 2           # extra rounds a joint search may take while a round still gains > 1 in l
SCREEN_N = 1 << 18        # records of at least 2 SCREEN_N samples are screened on their first SCREEN_N
RAMPS = True              # the taper ramps' time-domain term (:class:`.whittle.Ramps`)
LEVEL = True              # a record from rest: its mean in the mean effects' fit (:func:`.whittle.level_loglik`)
GRID_TOL = 1e-6           # values within GRID_TOL * step of the grid count as on it
QUANT_LAGS = 8192         # lags of the quantizer's correlated error kept in the likelihood, unless ...
QUANT_TAIL = 1e-4         # ... it is still above this (relative) in their last quarter: then every lag
QUANT_ROUNDS = 3          # refits of the variances with the quantizer's part from the fitted ones


# -- the data ---------------------------------------------------------------------------------------------
@dataclass
class Data:
    """What the diagnosis works on: y (N, p), the recorded command u (N, m) or None, and whether the
    record starts at rest (sample 0 of a noiselab stream). ``k0``: first sample analysed (0 at
    rest; else after the nominal model's transient)."""

    y: np.ndarray
    u: np.ndarray | None
    Ts: float
    at_rest: bool
    k0: int = 0
    notes: list = field(default_factory=list)
    ramps: object = None          # the taper ramps' term (:class:`.whittle.Ramps`), set by the first Hypotheses
    stable: bool = False          # the plant is stable (a stationary level: ``Evaluator.level_term``), set there too

    def __post_init__(self):
        self.y = np.asarray(self.y, float).reshape(len(self.y), -1)
        # the transforms are O(M log M) only for smooth M: drop up to ~0.1 % of the samples at the end
        n_all = self.y.shape[0]
        M = smooth_len(n_all - self.k0 - 1)
        if self.k0 + 1 + M < n_all:
            self.notes.append(f"the last {n_all - self.k0 - 1 - M} samples are left out of the spectral fit "
                              f"(a transform length of {M} samples is fast)")
            self.y = self.y[:self.k0 + 1 + M]
            if self.u is not None:
                self.u = np.asarray(self.u, float)[:self.k0 + 1 + M]
        self.N, self.p = self.y.shape
        self.M = self.N - self.k0 - 1
        self.nf = W.n_freqs(self.M)
        self.n_bic = self.N * self.p
        self.t = np.arange(self.N) * self.Ts
        # a command that varies, or (a record from rest) one that is not zero: a constant command
        # from sample 0 is a step at t = 0 for a plant at rest (the default step, time_s = 0)
        self.has_command = self.u is not None and self.u.size > 0 and bool(
            np.any(np.ptp(self.u, axis=0) > 0) or (self.at_rest and np.any(self.u != 0)))
        # not from rest under a command: the mean state at k0 is fitted (:meth:`Evaluator.mean`)
        self.free_start = not self.at_rest and self.u is not None and bool(np.any(self.u != 0))
        self.umax = float(np.max(np.abs(self.u))) if self.u is not None and self.u.size else 0.0
        # per input (a limit searched per input ranges over its own command's)
        self.umax_in = np.max(np.abs(self.u), axis=0) if self.u is not None and self.u.size else np.zeros(0)
        self.T = self.N * self.Ts
        self.groups = W.Groups(self.M, REL_BW)
        self.starts, self.sizes = self.groups.starts, self.groups.sizes
        # Whittle weights: bins per group; the DC bin (group 0, alone) is real: chi-squared 1, half weight
        self.weights = self.sizes.copy()
        self.weights[0] = 0.5
        self.grid = quantization_grid(self.y)
        self._lines = None

    def command_lines(self) -> np.ndarray:
        """Frequencies (Hz) of the recorded command's spectral lines (a sine, a square wave's
        harmonics): bins 100x above the median of their 20 neighbours and above 1e-8 of the
        largest, local maxima, that carry at least :data:`LINE_SHARE` of the command's power (with
        their two neighbours: an off-bin line leaks into them); none when more than
        :data:`COMB_LINES` do. A periodic broadband command (a chirp repeated every
        ``duration_s``, a maximal-length PRBS) is a comb of hundreds to thousands of weak lines up
        to the Nyquist frequency: their harmonics' zones would cover every frequency, so that no
        interference tone could be found (a square wave keeps its first odd harmonics). Empty
        without a command. Set once computed whole (a thread that asks meanwhile computes them
        too, never reads an unfinished value)."""
        if self._lines is None:
            lines = np.zeros(0)
            if self.has_command:
                from scipy.ndimage import median_filter
                x = self.u[self.k0:] - np.mean(self.u[self.k0:], axis=0)
                P = np.sum(np.abs(sfft.rfft(np.ascontiguousarray(x.T), axis=-1)) ** 2, axis=0)
                P[0] = 0.0
                med = median_filter(P, size=21, mode="nearest")
                peak = np.zeros(P.size, bool)
                peak[1:-1] = (P[1:-1] >= P[:-2]) & (P[1:-1] >= P[2:])
                idx = np.flatnonzero(peak & (P > 100 * med) & (P > 1e-8 * P.max()))
                share = (P[idx] + P[idx - 1] + P[np.minimum(idx + 1, P.size - 1)]) / max(float(P.sum()), 1e-300)
                idx = idx[share >= LINE_SHARE]
                if idx.size <= COMB_LINES:
                    lines = idx / (x.shape[0] * self.Ts)
            self._lines = lines
        return self._lines

    def group(self, A: np.ndarray) -> np.ndarray:
        """Means over the frequency groups (nb, ...)."""
        return self.groups.mean(A)


def smooth_len(n: int) -> int:
    """The largest m <= n whose prime factors are 2, 3, 5 and 7."""
    m = n
    while m > 1:
        k = m
        for q in (2, 3, 5, 7):
            while k % q == 0:
                k //= q
        if k == 1:
            return m
        m -= 1
    return max(n, 1)


def quantization_grid(y: np.ndarray) -> list:
    """Per output: the step of the grid every value lies on (to GRID_TOL), or None."""
    out = []
    for j in range(y.shape[1]):
        v = np.unique(y[:, j])
        step = None
        if v.size >= 3:
            d = np.diff(v)
            d0 = float(d.min())
            big = float(np.max(np.abs(v)))
            if d0 > 1e-9 * max(big, 1e-300):
                small = d[d < 1.5 * d0]
                s = float(np.median(small))
                k = v / s
                if np.max(np.abs(k - np.rint(k))) < GRID_TOL:
                    step = float(f"{s:.10g}")
        out.append(step)
    return out


# -- mean response and residual ----------------------------------------------------------------------------
def mean_response(model, data: Data, gain: bool = True):
    """E[y_k] and E[ydot_k] (N, p) for the recorded command (seed section 3, fast modal form);
    ``gain=False``: before the sensor gain."""
    pr = model.predictor()
    N = data.N
    u = np.asarray(data.u if data.u is not None else model.command.values(0, N, model.Ts), float)
    drive = mean_drive(pr, u)
    C = np.vstack([model.Cy, model.Cy @ model.Ac])
    D = np.vstack([model.Dy, model.Cy @ model.Bc])
    yy = lsim(model.Ad, model.Bd, C, D, drive)
    if not gain:
        return yy[:, :model.p], yy[:, model.p:]
    g = model.out_gain
    return yy[:, :model.p] * g, yy[:, model.p:] * g


def mean_drive(pr, u: np.ndarray) -> np.ndarray:
    """E[N(u_c,k + n_k)] (seed section 7), as :meth:`Predictor.drive_stats` but fast on long
    records: once the actuator noise variance has settled, the expectation is a fixed smooth
    function of u_c, tabulated on a fine grid (with the nonlinearities' kinks as grid points) and
    interpolated; without actuator noise it is N(u_c) itself."""
    if not pr._nonlin:
        return u.copy()
    N, m = u.shape
    var = pr.drive_noise_var(N)
    settled = np.flatnonzero(np.any(np.abs(var - var[-1]) > 1e-9 * np.abs(var[-1]), axis=1))
    k1 = int(settled[-1]) + 1 if settled.size else 0
    out = np.empty_like(u)
    if k1:
        out[:k1] = pr.drive_stats(u[:k1], var[:k1])[0]
    if k1 < N:
        if not np.any(var[-1] > 0):
            out[k1:] = pr._nonlinear(u[k1:])
            return out
        for j in range(m):
            col = u[:, j]
            lo, hi = float(col.min()), float(col.max())
            knots = np.concatenate([e.knots()[j] for e in pr._nonlin])
            grid = np.unique(np.concatenate([np.linspace(lo, hi, 16385), knots[(knots > lo) & (knots < hi)]]))
            ug = np.zeros((grid.size, m))
            ug[:, j] = grid
            vg = np.broadcast_to(var[-1], (grid.size, m))
            mean_g = pr.drive_stats(ug, vg)[0][:, j]
            # interpolated in sorted order (np.interp's search is ~15x slower on an oscillating
            # command, whose neighbours rarely share a cell); the order is the record's, cached
            order = _sort_order(col)
            vals = np.empty(N)
            vals[order] = np.interp(col[order], grid, mean_g)
            out[k1:, j] = vals[k1:]
    return out


_ORDERS = Memo(5, flush=True)


def _sort_order(col: np.ndarray) -> np.ndarray:
    """argsort of a command column, cached by content (the recorded command is the same in every
    evaluation of a diagnosis): keyed by a digest of all its bytes (~2 ms at 10^6 samples, against
    ~60 ms for the sort)."""
    key = (col.size, hashlib.blake2b(np.ascontiguousarray(col).tobytes(), digest_size=16).digest())
    return _ORDERS.get_or_compute(key, lambda: np.argsort(col, kind="stable"))


def tone_ls(r: np.ndarray, f: float, Ts: float, k0: int):
    """Least-squares sinusoid a sin + b cos at f over samples k >= k0: (a, b)."""
    k = np.arange(r.size)
    w = 2 * np.pi * f * Ts
    s, c = np.sin(w * k[k0:]), np.cos(w * k[k0:])
    X = np.column_stack([s, c])
    coef, *_ = np.linalg.lstsq(X, r[k0:], rcond=None)
    return float(coef[0]), float(coef[1])


def refine_frequency(r: np.ndarray, f0: float, Ts: float, k0: int, width: float) -> float:
    """The frequency near f0 (within +-width Hz) that maximizes |sum r_k e^{-i w k}|^2."""
    x = r[k0:] - r[k0:].mean()
    # sum_k x_k e^{-i w k} with k = a B + b: e^{-i w a B} summed over rows of x (A, B) e^{-i w b}
    # (two short exponentials per frequency instead of one as long as the record)
    B = 1024
    A = -(-x.size // B)
    xp = np.zeros(A * B)
    xp[:x.size] = x
    xp = xp.reshape(A, B)
    kb = np.arange(B)
    ka = np.arange(A) * float(B)

    def power(f):
        w = 2 * np.pi * f * Ts
        zb = np.exp(-1j * w * kb)
        rows = xp @ zb.real + 1j * (xp @ zb.imag)
        return -abs(np.dot(np.exp(-1j * w * ka), rows)) ** 2

    a, b = f0 - width, f0 + width
    gr = (math.sqrt(5) - 1) / 2
    c, d = b - gr * (b - a), a + gr * (b - a)
    fc, fd = power(c), power(d)
    for _ in range(24):          # the bracket to 1e-5 of its width: a phase error of 1e-4 rad over the record
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - gr * (b - a)
            fc = power(c)
        else:
            a, c, fc = c, d, fd
            d = a + gr * (b - a)
            fd = power(d)
    return 0.5 * (a + b)


# -- one evaluation: residual spectrum and noise spectrum of a hypothesis -----------------------------------
class Evaluator:
    """Caches what does not change between evaluations (mean responses, parts of fixed effects),
    shared by the threads that fit one record's candidates (:class:`service.memo.Memo`)."""

    def __init__(self, data: Data):
        self.data = data
        self._mean = Memo(17, flush=True)
        self._parts = W.parts_cache()
        self._pgram = Memo(9, flush=True)
        self._slope = Memo(17, flush=True)
        self._ramp = Memo(65, flush=True)
        self._level = Memo(65, flush=True)
        self._quant = Memo(9, flush=True)
        self._qmo = Memo(17, flush=True)
        self.evals = 0

    def quant_moments(self, model):
        """The quantizer's conditional moments over this record under ``model``
        (:meth:`Predictor.quantizer_moments`: they depend on its noise, not only on the mean
        effects) and a key for them; (None, None) when the error does not depend on the mean."""
        q = model.effects.get("sensor.quantization")
        if q is None:
            return None, None
        # the sensor's white noise bounds the noise before the quantizer from below: above 0.84 step
        # no output's error depends on the mean (the common case, e.g. the seed's 10 steps)
        w = model.effects.get("sensor.white")
        if w is not None and not _quant_mean_possible(q.params["step"], w.params["std"]):
            return None, None
        key = repr(model.to_dict())

        def compute():
            k0 = self.data.k0
            try:
                # over the analysed samples (its averages are the analysis'); g is 0 before them
                mo = model.predictor().quantizer_moments(self.mean(model)[0][k0:], k0)
            except (ValueError, np.linalg.LinAlgError):
                mo = None
            if mo is not None and k0:
                mo.g = np.concatenate([np.zeros((k0, mo.g.shape[1])), mo.g])
            return mo, None if mo is None else key
        return self._qmo.get_or_compute(key, compute)

    def residual_key(self, model, free_tone: bool) -> tuple:
        """:func:`_residual_key`, and the quantizer's moments when its mean depends on the noise."""
        return _residual_key(model, free_tone), self.quant_moments(model)[1]

    def mean(self, model):
        """E[y] and E[ydot]: cached without the sensor gain (a scale factor's trials share one
        response), the gain applied per model."""
        def compute():
            got = mean_response(model, self.data, gain=False)
            if self.data.free_start:
                # fitted to the record as it is (the sensor gain in it): the start state is fitted
                # per mean response, not per gain, and a gain's part of a decaying transient is small
                got = free_response_fit(model, self.data.y, *got, self.data.k0)
            return got
        y, yd = self._mean.get_or_compute(_mean_key(model, gain=False), compute)
        g = model.out_gain
        return (y, yd) if np.all(g == 1.0) else (y * g, yd * g)

    def parts(self, model, ydot_sq):
        """Per effect, the expected periodogram averaged over the frequency groups."""
        d = self.data
        return W.expected_parts(model, d.M, d.k0, d.at_rest, ydot_sq=ydot_sq, cache=self._parts, groups=d.groups,
                                cross=d.p > 1)

    def quant_part(self, model):
        """The quantizer's part of E I_f with its error correlated as the model predicts over this
        record (:mod:`service.model.effects.sensor_quantization`: it depends on the other sources
        and on the record's mean response), or None where the plant has no stationary prediction.
        The mean response's factors are cached by the steps, the tones and the rms increments of
        the mean response (below)."""
        from ..model.effects.sensor_quantization import white_enough
        d = self.data
        pr = model.predictor()
        # white noises bound the variogram at lags >= 1 from below: often white already. Decided from
        # the parameters alone, before any steady state: on the 10^6-sample seed record 1,516 calls
        # all ended here, and the Lyapunov solutions they did first cost 4.4 s of CPU
        white = sum((np.broadcast_to(prm[0], (d.p,)) for eid, kind, *prm in pr._primitives()
                     if kind == "white" and eid != "sensor.quantization"), np.zeros(d.p))
        step = model.effects["sensor.quantization"].params["step"]
        mo = self.quant_moments(model)[0]
        if mo is None and white_enough(step, white):
            return None

        def variogram(K):
            gam = pr.variogram(K, quantization=False)
            return None if any(v is None for v in gam.values()) else gam

        K = int(min(d.M, QUANT_LAGS))
        gam = variogram(K)
        if gam is None or K < 2 or (mo is None and white_enough(step, np.min(pr.before_quantizer(gam)[1:], axis=0))):
            return None
        # the motion's factors cost transforms of the record's length: shared between mean responses
        # whose increments' rms agree to 3 significant digits at lags 1, 8, 64 and 512 (the searches
        # of a lag or a scale factor try many nearby ones; 1 - C_m changes with them at first order,
        # so the part is off by about 1 % at most)
        tone = model.effects.get("sensor.tone")
        ym = self.mean(model)[0][d.k0:]
        inc = [np.sqrt(np.mean((ym[h:] - ym[:-h]) ** 2, axis=0)) for h in (1, 8, 64, 512) if h < ym.shape[0]]
        key = (tuple(float(f"{v:.3g}") for v in np.concatenate(inc)) if inc else (),
               repr(tone.param_dict()) if tone is not None else None,
               repr(step))
        motion, cache = self._quant.get_or_compute(key, lambda: (pr.motion(ym.shape[0], ym, d.k0), Memo(math.inf)))
        # one output: Stein's term in the part (negative where the quantizer holds the measurement;
        # Inner floors the total); several: carried by the noise parts instead (:func:`_stein`)
        multi = d.p > 1
        R = pr.quantization_acf(gam, motion, cache, mo, stein=not multi)
        if K < d.M and np.any(np.max(np.abs(R[3 * K // 4:]), axis=0) > QUANT_TAIL * np.max(np.abs(R), axis=0)):
            # still correlated at the last lags (a periodic command and a random part under a step:
            # the error holds the command's harmonics): every lag of the record, so that the
            # expected periodogram stays a spectrum (a cut one goes negative)
            R = pr.quantization_acf(variogram(d.M), motion, cache, mo, stein=not multi)
        return W.acf_part(R, d.M, d.groups, cross=multi, floor=multi or mo is None)

    def slope_power(self, model, ydot: np.ndarray) -> np.ndarray:
        """:func:`.whittle.slope_power` of the model's mean slope ``ydot``, cached by its mean response
        (an O(N) pass per evaluation cost 4 s of a 10^6-sample diagnosis)."""
        return self._slope.get_or_compute(_mean_key(model), lambda: W.slope_power(ydot[self.data.k0:], self.data.p > 1))

    def grouped_periodogram(self, model, free_tone: bool):
        """:meth:`residual` and the group means of its periodogram, cached: only the mean effects
        and the tone change them, not the noise parameters most evaluations vary (except through a
        quantizer's conditional mean, :meth:`quant_moments`, when the noise is under a step)."""
        def compute():
            r, yd, fitted = self.residual(model, free_tone)
            # several outputs: the cross-periodogram matrices (the multivariate Whittle likelihood)
            I = W.periodogram(r, self.data.k0, cross=self.data.p > 1)
            return r, yd, fitted, self.data.group(I)
        r, yd, fitted, Ig = self._pgram.get_or_compute(self.residual_key(model, free_tone), compute)
        return r, yd, None if fitted is None else fitted.copy(), Ig

    def ramp_term(self, model, free_tone: bool) -> float:
        """l_ramp (:class:`.whittle.Ramps`) of the residual, cached like its periodogram."""
        ramps = self.data.ramps
        if not ramps:
            return 0.0
        return self._ramp.get_or_compute(
            self.residual_key(model, free_tone),
            lambda: ramps(np.diff(self.grouped_periodogram(model, free_tone)[0][self.data.k0:], axis=0)))

    def level_term(self, res_model, free_tone: bool, model) -> float:
        """l_level (:func:`.whittle.level_loglik`): the mean of ``res_model``'s residual against
        ``model``'s noise; 0 for a record not from rest or a sensor-only model (its absolute level
        is not predicted: :attr:`Model.predicts_level`) or a plant that is not stable (no stationary
        level: an integrator's walk), the same for every hypothesis of a record (they share the plant)."""
        d = self.data
        if not (LEVEL and d.at_rest and d.stable and model.predicts_level):
            return 0.0

        def compute():
            r, yd = self.grouped_periodogram(res_model, free_tone)[:2]
            return np.mean(r[d.k0:], axis=0), np.mean(yd[d.k0:] ** 2, axis=0)
        m, slope_sq = self._level.get_or_compute(("mean",) + self.residual_key(res_model, free_tone), compute)
        return W.level_loglik(m, *W.level_density(model, d.N - d.k0, slope_sq), d.N - d.k0)

    def residual(self, model, free_tone: bool):
        """r (N, p) with the tones removed, and the tone parameters fitted (amplitude per output).
        A quantizer whose error depends on the mean (noise under about 0.84 step) adds its
        conditional mean E[Q(x)] - mu to the mean response (:meth:`quant_moments`)."""
        d = self.data
        ym, yd = self.mean(model)
        mo = self.quant_moments(model)[0]
        r = d.y - ym if mo is None else d.y - ym - mo.g
        tone = model.effects.get("sensor.tone")
        fitted = None
        if tone is not None:
            amp = np.broadcast_to(tone.params["amplitude"], (d.p,)).astype(float)
            freq = np.broadcast_to(tone.params["frequency_hz"], (d.p,)).astype(float)
            r = r.copy()
            fitted = amp.copy()
            for j in range(d.p):
                a, b = tone_ls(r[:, j], freq[j], d.Ts, d.k0)
                A = math.hypot(a, b)
                if free_tone:
                    fitted[j] = A
                    scale = 1.0
                else:
                    scale = amp[j] / A if A > 0 else 0.0
                w = 2 * np.pi * freq[j] * d.Ts * np.arange(d.N)
                r[:, j] -= scale * (a * np.sin(w) + b * np.cos(w))
        return r, yd, fitted


def _quant_mean_possible(step, white_std) -> bool:
    """Whether a white noise of ``white_std`` before a quantizer of ``step`` leaves its error's
    conditional mean on some output (:func:`.sensor_quantization.mean_matters`; other noise only lowers it)."""
    from ..model.effects.sensor_quantization import mean_matters
    return bool(np.any(mean_matters(step, np.asarray(white_std, float) ** 2)))


def _stein(parts: dict, mo, tones=()) -> dict:
    """The expected periodogram's parts with a quantizer's covariance with the noise (Stein's
    lemma: Cov(n_j, e_k) = Cov(n_j, x_k) h_k, :mod:`service.model.effects.sensor_quantization`)
    carried by the noise parts: output j's times 1 + 2 h_j, a cross term between outputs j and k
    times sqrt((1 + 2 h_j)(1 + 2 h_k)) (1 + h_j + h_k to first order; this form keeps the
    cross-spectral matrices positive definite). For several outputs only: with one, the term is in
    the quantizer's part, as in the views (negative where the quantizer holds the measurement; the
    likelihood floors the total), which a matrix's determinant cannot take. h <= -1/2 (a mean
    parked on a level) takes the noise out. ``mo`` None: the parts as they are."""
    if mo is None:
        return parts
    a = np.sqrt(np.maximum(1.0 + 2.0 * np.asarray(mo.h, float), 0.0))
    if np.all(a == 1.0):
        return parts
    out = {}
    for k, v in parts.items():
        if k == "sensor.quantization" or k in tones:
            out[k] = v
        elif v.ndim == 3:
            out[k] = v * np.outer(a, a)[None]
        else:
            out[k] = v * (a * a)
    return out


def _g_moved(a, b, rtol: float = 1e-2) -> bool:
    """Whether two quantizer moments' conditional means differ by more than ``rtol`` of the
    measurement's rms (None: no mean). What it lets pass moves the likelihood by up to about
    N rtol^2 / 2 (N samples), where the residual's rms is the measurement's: an approximation the
    inner fit's rounds accept for their cost (each refresh is a new periodogram)."""
    if a is None or b is None:
        return (a is None) != (b is None)
    scale = np.sqrt(np.mean(b.var_y, axis=0))
    return bool(np.any(np.max(np.abs(a.g - b.g), axis=0) > rtol * scale))


def _residual_key(model, free_tone: bool) -> tuple:
    """What the residual depends on: the mean response and the tone (fitted freely or held)."""
    tone = model.effects.get("sensor.tone")
    return _mean_key(model), repr(tone.param_dict()) if tone is not None else None, free_tone


# -- the likelihood over the free variances (inner problem) ---------------------------------------------------
def _inv_logdet(E: np.ndarray):
    """Inverses and ln det of Hermitian positive definite matrices E (nb, p, p); two and three
    outputs in closed form (batched LAPACK calls on 2 x 2 matrices cost ~10x more)."""
    if E.shape[1] == 2:
        a, d, b = E[:, 0, 0].real, E[:, 1, 1].real, E[:, 0, 1]
        # a model whose outputs share one noise source and nothing else (two outputs of one plant,
        # no sensor noise) predicts a singular E: floored, the data's other direction costs a
        # likelihood of ~1e12 times its power instead of a NaN
        det = np.maximum(a * d - (b.real**2 + b.imag**2), 1e-12 * a * d)
        Ei = np.empty_like(E)
        Ei[:, 0, 0], Ei[:, 1, 1] = d / det, a / det
        Ei[:, 0, 1], Ei[:, 1, 0] = -b / det, -np.conj(b) / det
        return Ei, np.log(det)
    if E.shape[1] == 3:
        # three outputs by E = L D L^H in closed form (4-8x faster than batched inv + slogdet on
        # 3 x 3; the adjugate's determinant loses digits as cond^2, this as cond): pivots d1..d3,
        # each floored like the 2 x 2 determinant; E^-1 = M^H D^-1 M, M = L^-1
        d1 = np.maximum(E[:, 0, 0].real, 1e-300)
        l21, l31 = E[:, 1, 0] / d1, E[:, 2, 0] / d1
        e11, e22 = E[:, 1, 1].real, E[:, 2, 2].real
        d2 = np.maximum(e11 - (l21.real**2 + l21.imag**2) * d1, 1e-12 * e11)
        l32 = (E[:, 2, 1] - l31 * np.conj(E[:, 1, 0])) / d2
        d3 = np.maximum(e22 - (l31.real**2 + l31.imag**2) * d1 - (l32.real**2 + l32.imag**2) * d2, 1e-12 * e22)
        m31 = l21 * l32 - l31                                      # M = [[1, 0, 0], [-l21, 1, 0], [m31, -l32, 1]]
        Ei = np.empty_like(E)
        Ei[:, 2, 2] = 1.0 / d3
        Ei[:, 1, 1] = 1.0 / d2 + (l32.real**2 + l32.imag**2) / d3
        Ei[:, 0, 0] = 1.0 / d1 + (l21.real**2 + l21.imag**2) / d2 + (m31.real**2 + m31.imag**2) / d3
        Ei[:, 0, 1] = -np.conj(l21) / d2 - np.conj(m31) * l32 / d3
        Ei[:, 0, 2] = np.conj(m31) / d3
        Ei[:, 1, 2] = -np.conj(l32) / d3
        Ei[:, 1, 0], Ei[:, 2, 0], Ei[:, 2, 1] = np.conj(Ei[:, 0, 1]), np.conj(Ei[:, 0, 2]), np.conj(Ei[:, 1, 2])
        return Ei, np.log(d1) + np.log(d2) + np.log(d3)
    return np.linalg.inv(E), np.linalg.slogdet(E)[1]


BLIND = 1e-30             # a source whose part is below this share of the data's power: not seen (:class:`Inner`)


class Inner:
    """l(v) = -sum_b G_b sum_j [ln E_bj + I_bj / E_bj] + l_mod(v_jitter), E = E0 + sum_a v_a U_a,
    v_a >= 0, maximized by projected Fisher scoring (the expected information
    sum_b G_b U_a U_b / E^2 is positive definite, so each step is a Newton-like ascent step).

    Several outputs: I_b, E0_b and U_a,b are p x p cross-spectral matrices (complex Hermitian) and
    l(v) = -sum_b G_b [ln det E_b + tr(E_b^-1 I_b)], the multivariate Whittle likelihood (Whittle
    1953; Brillinger 1981 ch. 7): outputs that share noise (two sensors of one plant) are not
    counted as independent evidence. Score tr(E^-1 U_a E^-1 (I - E)), information
    tr(E^-1 U_a E^-1 U_b)."""

    def __init__(self, I, G, E0, U, mod=None, mod_index=None):
        # G: bins per group divided by the taper's kappa (see :func:`.whittle.loglik`)
        self.multi = I.ndim == 3
        self.I, self.G, self.E0 = I, G.reshape((-1,) + (1,) * (I.ndim - 1)), E0
        self.U = np.stack(U) if len(U) else np.zeros((0,) + I.shape)
        self.Uf = self.U.reshape(len(self.U), I.size)   # the sources' parts as rows (bins x p x p)
        self.mod, self.mod_index = mod, mod_index
        tr = (lambda A: np.einsum("...ii->...", A).real) if self.multi else (lambda A: A)
        tot = float(np.sum(self.G * tr(I)))
        # a source these data cannot see (a noise behind a saturation that clips the whole record:
        # its part is 0, or rounding of 1e-40 that need not even be positive definite) would take a
        # variance 1e30 times its reference to carry their power: held where it starts (its part
        # zeroed, no score, no information), not run up to 1e290 where E overflows
        power = np.array([float(np.sum(self.G * tr(u))) for u in self.U])
        blind = ~(power > BLIND * tot)
        if blind.any():
            self.U = self.U.copy()
            self.U[blind] = 0.0
            self.Uf = self.U.reshape(len(self.U), I.size)
        self.blind = blind
        self.vref = np.where(blind, 1.0, tot / np.where(blind, 1.0, power))
        self.hi = np.where(blind, np.inf, self.vref * 1e4)
        level = E0 + np.tensordot(self.vref, self.U, axes=1) if len(self.U) else E0
        # an output's expected power that rounds to <= 0 is set to 1e-12 of its mean over the bins:
        # a part summed from exponentials of nearly equal modes (a long-memory noise through an
        # integrator) can, where the model has next to no power; data there then cost a very low
        # likelihood instead of a NaN. Positive values, however small (the DC bin of a long
        # record), are kept as they are.
        diag = np.einsum("bii->bi", level).real if self.multi else level
        self.floor = 1e-12 * np.mean(np.abs(diag), axis=0) + 1e-150
        if self.multi:
            p = I.shape[1]
            self.Gb = self.G[:, 0, 0]
            # a ridge of 1e-13 of the mean output power (and a floor) keeps E invertible where a
            # source's spectrum is singular (two outputs of one mode, no sensor noise)
            self.ridge = (1e-13 * np.einsum("bii->b", level).real / p + 1e-150)[:, None, None] * np.eye(p)

    def _E(self, v):
        E = self.E0 + (v @ self.Uf).reshape(self.U.shape[1:]) if len(v) else self.E0
        if self.multi:
            E = E + self.ridge
            d = np.einsum("bii->bi", E)              # a view of the new array's diagonals
            low = d.real <= 0
            if low.any():
                d[low] = np.broadcast_to(self.floor, d.shape)[low]
            return E
        # (positive values at least 1e-150: E**2 stays a normal float)
        return np.where(E > 0, np.maximum(E, 1e-150), self.floor)

    def value(self, v):
        v = np.asarray(v, float)
        E = self._E(v)
        if self.multi:
            Ei, logdet = _inv_logdet(E)
            EiI = Ei @ self.I
            l = -float(self.Gb @ (logdet + np.einsum("bii->b", EiI).real))
            R = (EiI - np.eye(E.shape[1])) @ Ei                      # E^-1 (I - E) E^-1
            # tr(U_a R) with U_a and R Hermitian: sum_ij U_ij conj(R_ij)
            g = (self.Uf @ (np.conj(R) * self.Gb[:, None, None]).ravel()).real
        else:
            l = -float(np.sum(self.G * (np.log(E) + self.I / E)))
            R = self.G * (self.I - E) / E**2
            g = self.Uf @ R.ravel()
        if self.mod is not None:
            lm, gm = self.mod(v[self.mod_index])
            l += lm
            g[self.mod_index] += gm
        return l, g

    def _info(self, v):
        E = self._E(v)
        n = len(self.U)
        F = np.empty((n, n))
        if self.multi:
            Ei = _inv_logdet(E)[0]
            # F_ab = sum_b G_b tr(V_a V_b), V_a = E^-1 U_a: one product over (sources, bins x p x p)
            V = np.matmul(Ei[None], self.U)
            Fc = ((V * self.Gb[:, None, None]).reshape(n, -1) @ V.transpose(0, 1, 3, 2).reshape(n, -1).T).real
            F[:] = 0.5 * (Fc + Fc.T)
        else:
            F[:] = (self.Uf * (self.G / E**2).ravel()) @ self.Uf.T
        if self.mod is not None:
            i = self.mod_index
            h = max(abs(v[i]) * 1e-3, self.vref[i] * 1e-9)
            g1 = self.mod(v[i] + h)[1]
            g0 = self.mod(max(v[i] - h, 0.0))[1]
            F[i, i] += max(-(g1 - g0) / (h + min(h, v[i])), 0.0)
        return F

    def optimize(self, v0=None, fixed: dict | None = None):
        """Maximize over v >= 0 (``fixed``: {index: value} held)."""
        n = len(self.U)
        if n == 0:
            return np.zeros(0), self.value(np.zeros(0))[0]
        fixed = fixed or {}
        starts = [np.clip(self.vref * 1e-2, 0, self.hi)]
        if v0 is not None:
            starts.insert(0, np.clip(np.asarray(v0, float), 0, self.hi))
        for s in starts:
            # a source the data cannot see stays at the model's value (its reference without one)
            s[self.blind] = 1.0 if v0 is None else starts[0][self.blind]
        best = None
        for v in starts:
            v = v.copy()
            for i, x in fixed.items():
                v[i] = x
            l, g = self.value(v)
            for _ in range(100):
                free = np.array([i not in fixed and not (v[i] <= 0 and g[i] <= 0) for i in range(n)])
                if not free.any():
                    break
                F = self._info(v)[np.ix_(free, free)]
                try:
                    step_f = np.linalg.solve(F + 1e-12 * np.trace(F) * np.eye(F.shape[0]) / max(F.shape[0], 1), g[free])
                except np.linalg.LinAlgError:
                    step_f = g[free] / np.maximum(np.diag(F), 1e-300)
                step = np.zeros(n)
                step[free] = step_f
                alpha, improved = 1.0, False
                for _ in range(30):
                    vn = np.clip(v + alpha * step, 0.0, self.hi)
                    ln, gn = self.value(vn)
                    if ln >= l - 1e-12 * abs(l):
                        improved = True
                        break
                    alpha *= 0.5
                if not improved:
                    break
                dl = ln - l
                v, l, g = vn, ln, gn
                if dl < 1e-9 * max(1.0, abs(l)) * 1e-3 and alpha == 1.0:
                    break
            if best is None or l > best[1]:
                best = (v, l)
        return best

    def profile(self, a: int, v_hat: np.ndarray, l_hat: float, chi2: float = CHI2_95):
        """95 % profile interval of v_a (the others re-optimized from ``v_hat``): 2 Delta l <=
        ``chi2``. Each end is bracketed in ln v_a from the estimate, the first step two standard
        errors of ln v_a by the expected information (its inverse's diagonal), the step doubled
        until the profile falls below its threshold, then found by :func:`_crossing` (regula falsi
        on the squared distance from the estimate: 3-4 fits where a bisection to the same 0.02 in l
        took about 30). The lower end is 0 where the profile at 0 stays above the threshold (a
        variance the data do not bound away from 0); the upper stops at 1e4 v_hat (above: the data
        do not bound it). A variance fitted at 0: the lower end 0, the upper searched up by
        decades from 1e-6 of the variance that would carry all the data's power."""
        target = l_hat - chi2 / 2

        def prof(va):
            return self.optimize(v_hat, fixed={a: va})[1]

        vh = float(v_hat[a])
        if not vh > 0:
            inside, l_in, outside = 0.0, l_hat, float(self.vref[a]) * 1e-6
            for _ in range(16):
                l_out = prof(outside)
                if not l_out > target or outside >= self.hi[a]:
                    break
                inside, l_in, outside = outside, l_out, outside * 10.0
            if l_out > target:
                return 0.0, outside
            return 0.0, _crossing(prof, inside, l_in, outside, l_out, target, log=inside > 0)
        try:
            se = math.sqrt(max(float(np.linalg.pinv(self._info(v_hat))[a, a]), 0.0)) / vh
        except (np.linalg.LinAlgError, ValueError):
            se = math.nan
        first = min(max(2.0 * se, 0.01), 2.0) if math.isfinite(se) else 0.5
        far = math.log(1e4)

        def edge(direction):
            inside, l_in, d = vh, l_hat, first
            for _ in range(40):
                if d >= far:
                    # as far as the search goes: 0 below (a variance of none), 1e4 v_hat above
                    outside = 0.0 if direction < 0 else vh * 1e4
                    l_out = prof(outside)
                    if l_out > target:
                        return outside
                    return _crossing(prof, inside, l_in, outside, l_out, target, log=direction > 0,
                                     peak=vh if direction > 0 else None)
                outside = vh * math.exp(direction * d)
                l_out = prof(outside)
                if l_out < target:
                    return _crossing(prof, inside, l_in, outside, l_out, target, peak=vh)
                inside, l_in, d = outside, l_out, 2.0 * d
            return inside

        return edge(-1), edge(1)


# -- the jitter's modulation term ---------------------------------------------------------------------------
QUANT_SLOPE_MAX = 7.0      # 2 pi^2 V_d / step^2 above this (e^-7 ~ 1e-3): the error's decorrelation is negligible


class Modulation:
    """The jitter's second signature: the squared differenced residual z_q follows the squared
    slope, z_q = c + b x_q + noise with x_q = ydot_{q+1}^2 + ydot_q^2 (Var(ydot dt) = std_s^2 ydot^2,
    seed section 6.3) and b = std_s^2. The slope is estimated by least squares with a free
    intercept (the level is the Whittle part's business) and its standard error from Var(z_q) =
    2 mu_q^2 (chi-squared 1 times the local variance) inflated by the dependence factor; the term
    is the Gaussian log-likelihood of that slope, relative to b = 0:
    l_mod(b) = [s^2 - (s - b)^2] / (2 se^2).

    ``base`` (M, p), optional: the part of E[z_q] the model already predicts to change with the
    slope (a quantizer's error decorrelates between samples as the signal moves through the steps,
    :meth:`Hypotheses._quant_slope`: for small slopes it grows as ydot^2 too, and a coarse
    quantizer's own modulation was read as a jitter: coarse case 23, a jitter of 0.7 ms added, +529
    in log-likelihood, model error 12). It is subtracted from z_q before the regression: known
    from the model, it leaves the jitter's slope its whole information (a free coefficient for it,
    tried first, absorbed a real jitter of 1.5 ms in 2 of 3 records)."""

    def __init__(self, d: np.ndarray, ydot: np.ndarray, k0: int, unit: float, base: np.ndarray | None = None):
        z = d**2                                                    # (M, p)
        if base is not None:
            if base.shape != z.shape:
                raise ValueError(f"Modulation: base {base.shape} does not match the residual's {z.shape}")
            z = z - base
        self.base = base
        x = self.slope_squares(ydot, k0)
        self.unit = unit                                            # v = b / unit
        num, den = 0.0, 0.0
        self._terms = []                # (output, mean x, sxx, var, mean z, slope): scalars only (Fits keep this)
        for j in range(z.shape[1]):
            xc = x[:, j] - x[:, j].mean()
            sxx = float(np.dot(xc, xc))
            if sxx <= 0:
                continue
            slope = float(np.dot(xc, z[:, j])) / sxx
            mu = z[:, j].mean() + slope * xc + (0.0 if self.base is None else self.base[:, j])   # E[d_q^2]
            mu = np.maximum(mu, 1e-3 * max(float(np.mean(d[:, j] ** 2)), 1e-300))
            var = 2.0 * float(np.sum(xc**2 * mu**2)) / sxx**2 * _dependence(d[:, j])
            num += slope / var                                      # outputs combined by precision
            den += 1.0 / var
            self._terms.append((j, float(x[:, j].mean()), sxx, var, float(z[:, j].mean()), slope))
        self.slope = num / den if den > 0 else 0.0
        self.se2 = 1.0 / den if den > 0 else np.inf

    @staticmethod
    def slope_squares(ydot: np.ndarray, k0: int) -> np.ndarray:
        """x_q = ydot_{q+1}^2 + ydot_q^2 (M, p)."""
        yd2 = ydot[k0:] ** 2
        return yd2[1:] + yd2[:-1]

    def contributions(self, d: np.ndarray, ydot: np.ndarray, k0: int) -> np.ndarray:
        """The score's per-sample terms (M,) for the differenced residual ``d`` it was built from:
        their sum is its derivative in v (plus a constant), each centered on the fitted line (for
        the sandwich variance, :func:`godambe_factor`)."""
        x = self.slope_squares(ydot, k0)
        z = d**2 if self.base is None else d**2 - self.base
        out = np.zeros(d.shape[0])
        for j, xm, sxx, var, zm, slope in self._terms:
            xc = x[:, j] - xm
            mu = zm + slope * xc
            out += self.unit * xc / (sxx * var) * (z[:, j] - mu)
        return out

    def __call__(self, v: float):
        b = v * self.unit
        if not np.isfinite(self.se2):
            return 0.0, 0.0
        l = (self.slope**2 - (self.slope - b) ** 2) / (2 * self.se2)
        g = (self.slope - b) / self.se2 * self.unit
        return float(l), float(g)


def _dependence(d: np.ndarray, H: int = 50) -> float:
    """1 + 2 sum_h rho_d(h)^2: the variance inflation of a mean of d_q^2 for Gaussian d."""
    x = d - d.mean()
    n = x.size
    # lags up to H only: a circular transform padded by more than H is exact there
    L = sfft.next_fast_len(n + H + 1, real=True)
    X = sfft.rfft(x, L)
    ac = sfft.irfft(X.real**2 + X.imag**2, L)[:H + 1]
    if ac[0] <= 0:
        return 1.0
    rho = ac[1:] / ac[0]
    return float(1 + 2 * np.sum(rho**2))


# -- how far apart two fits of one periodogram are -------------------------------------------------------
def lr_spread(A: "Fit", B: "Fit") -> float | None:
    """The standard deviation of 2 (l_A - l_B) over records, under A's spectrum, for two fits of the
    same periodogram (None when their residuals differ, e.g. one moves the mean response): the scale
    on which a likelihood ratio between two non-nested models of equal size tells them apart (Vuong
    1989; here model-based, not from the data).

    Only the periodogram is random in l_A - l_B = -sum_b G_b [ln det E_Ab - ln det E_Bb +
    tr((E_Ab^-1 - E_Bb^-1) I_b)]; for a Gaussian transform X of covariance E_A,
    Var(X^H M X) = tr(M E_A M E_A), and a group's mean of n_b ordinates (G_b = n_b / kappa) has
    1 / G_b of one ordinate's variance: Var(l_A - l_B) = sum_b G_b tr[(1 - E_Bb^-1 E_Ab)^2]."""
    ia, ib = A.inner, B.inner
    if ia is None or ib is None or ia.I.shape != ib.I.shape or not np.array_equal(ia.I, ib.I):
        return None
    EA, EB = ia._E(A.v), ib._E(B.v)
    if ia.multi:
        D = np.eye(EA.shape[1]) - np.linalg.solve(EB, EA)
        var = float(ia.Gb @ np.einsum("bij,bji->b", D, D).real)
    else:
        var = float(np.sum(ia.G * (1.0 - EA / EB) ** 2))
    return 2.0 * math.sqrt(max(var, 0.0))


# -- the sandwich variance of a modulated variance --------------------------------------------------------
def score_contributions(H: "Hypotheses", fit: "Fit") -> np.ndarray:
    """Per-sample terms phi_aq (n, M) of the inner problem's score in each free variance v_a:
    sum_q phi_aq equals the Whittle score sum_b G_b tr(E_b^-1 U_ab E_b^-1 I_b) up to a constant,
    plus the modulation term's.

    With X_f the transform of the tapered differenced residual, the whitened transform
    Y_f = E_f^-1/2 X_f and its series e = irfft(Y): sum_{f < nf} c_f Y_f^H A_f Y_f / M =
    sum_q e_q^T irfft(c A Y)_q, A = E^-1/2 U_a E^-1/2 (c_f = 1/2 inside the half spectrum counts
    its mirror image once; G_b / n_b = 1 / kappa per bin, 1/2 at DC). Whitened, both factors have
    short memory (A lies between 0 and 1 / v_a): unwhitened, U / E^2 grows like 1 / w^2 where a
    differenced spectrum falls like w^2, and the terms would carry that long kernel."""
    d, inner = H.data, fit.inner
    r, ydot = H.ev.grouped_periodogram(fit.model, "sensor.tone" in fit.free)[:2]
    g = np.diff(r[d.k0:], axis=0)
    M = g.shape[0]
    w, _, kappa = W.taper(M)
    X = sfft.rfft(np.ascontiguousarray((g * w[:, None]).T), axis=-1).T      # (M // 2 + 1, p)
    sizes = d.sizes.astype(np.int64)
    E = inner._E(fit.v)
    Y = np.zeros_like(X)
    if inner.multi:
        lam, V = np.linalg.eigh(E)
        Eh = (V / np.sqrt(lam)[:, None, :]) @ np.conj(V.transpose(0, 2, 1))   # E^-1/2 per group
        Y[:d.nf] = np.einsum("fij,fj->fi", np.repeat(Eh, sizes, axis=0), X[:d.nf])
    else:
        Y[:d.nf] = X[:d.nf] / np.repeat(np.sqrt(E), sizes, axis=0)
    e = sfft.irfft(np.ascontiguousarray(Y.T), n=M, axis=-1).T                 # (M, p)
    phi = np.empty((len(fit.v), M))
    for a in range(len(fit.v)):
        Z = np.zeros_like(X)
        if inner.multi:
            A = np.repeat(Eh @ inner.U[a] @ Eh, sizes, axis=0)
            Z[:d.nf] = np.einsum("fij,fj->fi", A, Y[:d.nf])
        else:
            Z[:d.nf] = np.repeat(inner.U[a] / E, sizes, axis=0) * Y[:d.nf]
        Z *= 0.5 / kappa
        phi[a] = np.sum(e * sfft.irfft(np.ascontiguousarray(Z.T), n=M, axis=-1).T, axis=1)
    if inner.mod is not None:
        phi[inner.mod_index] += inner.mod.contributions(g, ydot, d.k0)
    return phi


SANDWICH_BLOCKS = 256     # block sums for the long-run variance of the score (Kuensch 1989)
SANDWICH_BLOCK_MIN = 64   # samples per block at least


def godambe_factor(H: "Hypotheses", fit: "Fit", a: int) -> float:
    """Var(v_a) by the sandwich (Godambe) formula over its model-based value (H^-1)_aa: the factor
    by which a profile-likelihood ratio of v_a overstates its evidence (Chandler & Bate 2007). For
    the jitter, whose Whittle part takes a modulated noise as stationary (its mean power
    varies more: the kurtosis of the modulation) and whose modulation term reads the same squared
    residuals again.

    v_hat - v = H^-1 psi to first order, psi = sum_q phi_q: the influence series
    x_q = sum_i (H^-1)_ai phi_iq (active variances only). Its expected value follows the taper and
    the modulation (w_q^2, x_q, w_q^2 x_q per output: least squares removes it), then the variance
    of its sum is read from :data:`SANDWICH_BLOCKS` block sums (blocks much longer than the
    dependence of a white-like score)."""
    inner = fit.inner
    n = len(fit.v)
    act = [a] + [i for i in range(n) if i != a and fit.v[i] > 0]
    F = inner._info(fit.v)[np.ix_(act, act)]
    try:
        Fi = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return 1.0
    phi = score_contributions(H, fit)
    infl = Fi[0] @ phi[act]
    M = infl.size
    w2 = W.taper(M)[0] ** 2
    cols = [np.ones(M), w2]
    if inner.mod is not None:
        x = Modulation.slope_squares(H.ev.grouped_periodogram(fit.model, "sensor.tone" in fit.free)[1], H.data.k0)
        for j in range(x.shape[1]):
            xj = x[:, j] / max(float(np.mean(x[:, j])), 1e-300)
            cols += [xj, w2 * xj]
    if any(_behind_nonlinearity(fit.model, e) for e in set(fit.scale_ids)):
        # a noise behind a switching gain: the score's mean follows the squared gain (the power
        # passed), a deterministic pattern whose block sums are not the score's spread
        for gj in _gain_squares(fit.model, H.data, M):
            cols += [gj, w2 * gj]
    B = np.stack(cols, axis=1)
    coef = np.linalg.lstsq(B, infl, rcond=None)[0]
    res = infl - B @ coef
    nb = min(SANDWICH_BLOCKS, M // SANDWICH_BLOCK_MIN)
    if nb < 16:
        return 1.0
    L = M // nb
    S = res[:nb * L].reshape(nb, L).sum(axis=1)
    K = float(np.sum(S**2)) * nb / (nb - 1) * M / (nb * L)
    return K / Fi[0, 0]


def gated(model, eid: str, data: "Data") -> bool:
    """Whether ``eid`` is an actuator noise that reaches the plant through a gain that switches over
    the record (a saturation or a dead zone the command reaches part of the time:
    :func:`service.model.predict.gain_switches`): its power arrives modulated, and the stationary
    likelihood takes its periodogram as less spread than it is (the modulation's kurtosis: a noise
    clipped a third of the time has 1.5x the variance in its mean power). Its interval is adjusted
    by :func:`godambe_factor`, as the jitter's. The gain over ``data``'s command (an external
    command's record has one the model's own command does not)."""
    return _behind_nonlinearity(model, eid) and bool(np.any(gain_switches(_gains(model, data))))


def _behind_nonlinearity(model, eid: str) -> bool:
    """An actuator noise of a model with a saturation or a dead zone."""
    return hasattr(model.effects.get(eid), "drive_linear") and any(hasattr(e, "knots") for e in model.effects.values())


def _gains(model, data: "Data") -> np.ndarray:
    """The nonlinearities' Bussgang gain (N, m) over the record's command."""
    pr = model.predictor()
    N = data.N
    u = np.asarray(data.u if data.u is not None else model.command.values(0, N, model.Ts), float).reshape(N, -1)
    return pr.drive_stats(u, pr.drive_noise_var(N))[1]


def _gain_squares(model, data: "Data", M: int) -> list:
    """The squared gain of each input whose gain switches, over the last M samples of the record
    (the differenced residual's), relative to its mean."""
    g = _gains(model, data)[-M:]          # a gain that switches only before the residual starts: none
    return [g[:, j] ** 2 / np.mean(g[:, j] ** 2) for j in np.flatnonzero(gain_switches(g))]


def _scale_chi2(H: "Hypotheses", fit: "Fit", eid: str, a: int) -> float:
    """The profile threshold of variance ``a`` (``eid``'s): 3.84, times the sandwich factor (never
    below 1) for a variance whose likelihood overstates its evidence: the jitter's (modulated by the
    slope) and an actuator noise's behind a switching gain (:func:`gated`)."""
    if CATALOGUE[eid].fit.kind == "modulated" or gated(fit.model, eid, H.data):
        return CHI2_95 * max(godambe_factor(H, fit, a), 1.0)
    return CHI2_95


# -- hypotheses ---------------------------------------------------------------------------------------------
def plant_stable(model) -> bool:
    """Every eigenvalue of the discrete plant inside the unit circle, an integrator's (within
    :func:`service.model.predict.unit_tol` of 1) excluded."""
    from ..model.predict import unit_tol
    Ad = np.asarray(model.Ad, float)
    if Ad.size == 0:
        return True
    return _radius(Ad) < 1.0 - unit_tol(np.asarray(model.Ac, float), model.Ts)


def _unit_scale(spec, Ts):
    return Ts / 10 if spec.unit_scale == "Ts/10" else float(spec.unit_scale)


def _scale_ref(eid: str, sname: str, Ts: float) -> float:
    """The value of ``eid``'s scale ``sname`` at which the inner problem's variance is 1 (its
    catalogue unit; a psd's is 1), unless the model is nonlinear and the scale is not 0
    (:meth:`Hypotheses.inner_fit`: then its value)."""
    return _unit_scale(CATALOGUE[eid].fit, Ts) if sname != "psd" else 1.0


@dataclass
class Fit:
    model: object
    free: dict                      # eid -> list of free parameter names
    loglik: float
    parts: dict = field(default_factory=dict)
    inner: object = None
    v: np.ndarray = None
    scale_ids: list = field(default_factory=list)   # the effect of each of ``v``'s variances
    scale_ch: list = field(default_factory=list)    # ... and its channel (None: all its channels)
    chparts: dict = field(default_factory=dict)     # (effect id, input): that input's part (PER_INPUT)
    level_fn: object = None         # () -> l_level (:meth:`Evaluator.level_term`), outside ``loglik``
    _level: float | None = None

    @property
    def level(self) -> float:
        """l_level, computed when first asked for (only a mean effect's search asks)."""
        if self._level is None:
            self._level = float(self.level_fn()) if self.level_fn is not None else 0.0
        return self._level

    def objective(self, mean: bool) -> float:
        """What a search over a parameter maximizes: ``loglik``, plus ``level`` for a mean
        effect's parameter (:meth:`Hypotheses._search`)."""
        return self.loglik + self.level if mean else self.loglik

    def scaled_parts(self) -> dict:
        """{effect id: its part of the expected periodogram at the fitted values}: ``parts`` are at
        the scaling references, each free variance's part (one output's, for a per-output one)
        times its fitted factor."""
        out = {k: E for k, E in self.parts.items() if k not in self.scale_ids}
        for e, j, vi in zip(self.scale_ids, self.scale_ch or [None] * len(self.scale_ids), np.atleast_1d(self.v)):
            if e in self.parts:
                out[e] = out.get(e, 0.0) + _channel(self.parts[e], j, self.chparts, e) * vi
        return out


class Hypotheses:
    def __init__(self, data: Data, base_model):
        self.data = data
        self.ev = Evaluator(data)
        self.base = base_model
        self._qslope = Memo(5, flush=True)
        if data.ramps is None:
            # the ramps' whitener: from the first model's residual (the nominal), one per record
            data.ramps = False
            data.stable = plant_stable(base_model)
            if RAMPS and data.M >= W.RAMP_MIN:
                r = self.ev.residual(base_model, False)[0]
                data.ramps = W.Ramps(np.diff(r[data.k0:], axis=0), data.at_rest)

    def _quant_slope(self, model) -> np.ndarray | None:
        """The part of E[(e_{q+1} - e_q)^2] of a quantizer's error that changes with the mean's step
        dmu_q = mu_{q+1} - mu_q between samples (M, p) (:class:`Modulation`'s ``base``); None
        without a quantizer or where it does not matter. For Gaussian noise before the quantizer
        with Var(n_{q+1} - n_q) = V_d, from the error's Fourier series e(x) = sum_n (step / (pi n))
        (-1)^(n+1) sin(2 pi n x / step) (Widrow & Kollar 2008 ch. 4; the terms damped by the noise's
        whole variance, and the error's covariance with the noise, left out), -2 Cov(e_{q+1}, e_q):

            w_q = -(step^2 / pi^2) sum_n n^-2 exp(-2 pi^2 n^2 V_d,q / step^2) cos(2 pi n dmu_q / step)

        (up to a constant, which the regression's intercept takes). A jitter's increments are part
        of V_d,q and follow the slope; the inner fit recomputes this at its fitted values.

        It matters when the noise changes by less than a step between samples (V_d < ~0.35 step^2).
        The terms left out are damped by the noise's whole variance V: exact enough for V above
        ~0.35 step^2 (0.6 step of noise); below, where the conditional mean is in the residual,
        approximate (they follow where the mean sits between the levels). Tones are left out."""
        q = model.effects.get("sensor.quantization")
        if q is None:
            return None
        d = self.data
        pr = model.predictor()
        st = pr.steady_state()
        gam = pr.variogram(2, quantization=False)
        if any(v is None for v in gam.values()):
            return None
        jit = model.effects.get("sensor.jitter")
        std_s = float(jit.params["std_s"]) if jit is not None else 0.0
        # the noise's own increments; a jitter's follow the slope: std_s^2 (ydot_{q+1}^2 + ydot_q^2
        # + 2 Var(ydot)) at sample q
        Vd0 = 2.0 * pr.before_quantizer({e: v for e, v in gam.items() if e != "sensor.jitter"})[1]   # (p,)
        step = np.broadcast_to(np.asarray(q.params["step"], float), (d.p,))
        a0 = 2.0 * np.pi**2 * Vd0 / step**2
        if np.all(a0 > QUANT_SLOPE_MAX):
            return None
        key = (_mean_key(model), tuple(float(f"{v:.4g}") for v in a0), tuple(step.tolist()), f"{std_s:.4g}")

        def compute():
            mean, ydot = self.ev.mean(model)
            dmu = np.diff(mean[d.k0:], axis=0)                       # (M, p)
            w = np.zeros_like(dmu)
            if std_s > 0:
                yv = np.zeros(d.p) if st.ydot_var is None else np.broadcast_to(st.ydot_var, (d.p,))
                jv = std_s**2 * (Modulation.slope_squares(ydot, d.k0) + 2.0 * yv)          # (M, p)
            for j in np.flatnonzero(a0 <= QUANT_SLOPE_MAX):
                a = a0[j] if std_s == 0 else a0[j] + 2.0 * np.pi**2 * jv[:, j] / step[j] ** 2
                for n in range(1, 64):
                    damp = np.exp(-a * n * n)
                    if np.max(damp) < 1e-6:
                        break
                    w[:, j] -= damp / n**2 * np.cos(2.0 * np.pi * n * dmu[:, j] / step[j])
                w[:, j] *= step[j] ** 2 / np.pi**2
            return w
        return self._qslope.get_or_compute(key, compute)

    # one evaluation: outer parameters fixed (in ``model``), the free variances fitted
    def inner_fit(self, model, free: dict) -> Fit:
        d = self.data
        self.ev.evals += 1
        # (effect id, parameter, power of the variance, channel or None): a sensor noise of several
        # outputs has one variance per output, an actuator or process noise of several inputs one per
        # input (:func:`n_channels`), the others one over their channels
        scales = []
        for e, names in free.items():
            if CATALOGUE[e].fit.kind in ("noise", "modulated") and e in model.effects:
                sname, power = _scale_name(model.effects[e])
                if sname in names:
                    # "hold:j" among the names: channel j's variance held at the model's value (a
                    # profile); COMMON: one factor over the channels
                    nc = n_channels(model, e)
                    chans = [j for j in range(nc) if f"hold:{j}" not in names] if nc > 1 and COMMON not in names \
                        else (None,)
                    scales += [(e, sname, power, j) for j in chans]
        scale_ids = [e for e, *_ in scales]
        scale_ch = [j for *_, j in scales]
        nonlin = any(hasattr(e, "knots") for e in model.effects.values())
        canon = model
        cur, refs = [], []
        for e, sname, power, j in scales:
            vals = np.atleast_1d(np.asarray(model.effects[e].params[sname], float))
            val = float(np.max(vals) if j is None else np.broadcast_to(vals, (n_channels(model, e),))[j])
            ref = val if (nonlin and val > 0) else _scale_ref(e, sname, d.Ts)
            cur.append(val)
            refs.append(ref)
        canon = _set_scales(canon, scales, refs, model)
        r, ydot, tone_amp, Ig = self.ev.grouped_periodogram(model, "sensor.tone" in free)
        if tone_amp is not None and "sensor.tone" in free:
            model = _set(model, "sensor.tone", {"amplitude": _vec(tone_amp)})
            canon = _set(canon, "sensor.tone", {"amplitude": _vec(tone_amp)})
        # the jitter's slope power: per output, or (several outputs) the matrix of mean products,
        # weighted by the taper like the periodogram (see :func:`.whittle.slope_power`)
        ydot_sq = self.ev.slope_power(model, ydot)
        parts = self.ev.parts(canon, ydot_sq)
        if "sensor.jitter" in model.effects and any(e != "sensor.jitter" for e in scale_ids):
            # the jitter's power includes the noise-driven slope, std_s^2 Var(ydot), set by the other
            # sources' variances: from their current values, not the scaling references of ``canon``
            # (a process noise of unit std made the jitter's part 4x too large on a two-output case)
            jm = model if "sensor.jitter" not in scale_ids else \
                _set(model, "sensor.jitter", {"std_s": refs[scale_ids.index("sensor.jitter")]})
            parts = dict(parts)
            parts["sensor.jitter"] = W.expected_parts(
                jm, d.M, d.k0, d.at_rest, ydot_sq=ydot_sq, skip=tuple(e for e in jm.effects if e != "sensor.jitter"),
                groups=d.groups, cross=d.p > 1)["sensor.jitter"]
        # an input's part reaches every output (not a diagonal element): each input's computed apart,
        # the effect's scale at its value in ``canon`` on that input alone (parts are linear in it)
        chparts = {}
        for e, sname in dict.fromkeys((e, sname) for e, sname, _, j in scales if j is not None and e in PER_INPUT):
            vec = np.broadcast_to(np.asarray(canon.effects[e].params[sname], float), (n_channels(model, e),))
            for j in range(vec.size):
                one = np.where(np.arange(vec.size) == j, vec, 0.0)
                chparts[(e, j)] = self.ev.parts(_set(canon, e, {sname: [float(x) for x in one]}), ydot_sq)[e] \
                    if vec[j] > 0 else np.zeros_like(parts[e])
        mod = None
        mod_index = None
        if "sensor.jitter" in model.effects or "sensor.jitter" in scale_ids:
            dd = np.diff(r[d.k0:], axis=0)
            if "sensor.jitter" in scale_ids:
                i = scale_ids.index("sensor.jitter")
                mod, mod_index = Modulation(dd, ydot, d.k0, refs[i] ** 2, self._quant_slope(model)), i
        qid = "sensor.quantization"
        white_q = parts.get(qid)
        qpart = self.ev.quant_part(model) if qid in model.effects else None
        if qpart is not None:
            # the quantizer's error is correlated when the signal crosses few steps per sample; how
            # much depends on the other sources' variances: from the model's values, then again
            # from the fitted ones until they settle (the part is not linear in them)
            parts = dict(parts)
            parts[qid] = qpart
        def assemble(parts, m):
            """E0 and U, the noise parts times the quantizer's Stein factors (:func:`_stein`)."""
            mo = self.ev.quant_moments(m)[0] if qid in m.effects and d.p > 1 else None
            tones = m.predictor().tone_ids() if mo is not None else ()
            ps, cps = _stein(parts, mo, tones), _stein(chparts, mo, tones)
            # the fixed parts: every effect without a free variance, and the channels held of one with
            # a variance per channel (at the model's value in ``canon``)
            pairs = set(zip(scale_ids, scale_ch))
            held = [_channel(ps[e], j, cps, e) for e in {e for e, j in pairs if j is not None} if e in ps
                    for j in range(n_channels(m, e)) if (e, j) not in pairs]
            return (sum((v for k, v in ps.items() if k not in scale_ids), np.zeros_like(Ig)) + sum(held, np.zeros_like(Ig)),
                    [_channel(ps.get(e, np.zeros_like(Ig)), j, cps, e) for e, j in zip(scale_ids, scale_ch)])
        E0, U = assemble(parts, model)
        inner = Inner(Ig, d.weights / W.taper(d.M)[2], E0, U, mod, mod_index)
        res_model = model                              # the model the residual (Ig) is of
        v0 = np.array([(c / ref) ** pw for c, ref, (_, _, pw, _) in zip(cur, refs, scales)]) if scales else None
        v, l = inner.optimize(v0)

        def values(v):               # the scales' values at the inner problem's variances v
            return [ref * vi ** (1.0 / sc[2]) for sc, vi, ref in zip(scales, v, refs)]

        for _ in range(QUANT_ROUNDS if qid in model.effects and scales else 0):
            trial = _set_scales(model, scales, values(v), model)
            # the quantizer's slope modulation at the fitted noise and jitter (:meth:`_quant_slope`)
            base_moved = False
            if mod is not None and mod.base is not None:
                nb = self._quant_slope(trial)
                scale = float(np.max(np.abs(mod.base))) or 1.0
                if nb is not None and not np.allclose(nb, mod.base, rtol=1e-2, atol=1e-2 * scale):
                    mod, base_moved = Modulation(dd, ydot, d.k0, refs[mod_index] ** 2, nb), True
            new_q = self.ev.quant_part(trial)
            new_q = white_q if new_q is None else new_q          # white at the fitted values
            # the quantizer's conditional mean, in the residual, follows the noise too
            mo_t, mo_r = self.ev.quant_moments(trial)[0], self.ev.quant_moments(res_model)[0]
            moved = _g_moved(mo_t, mo_r)
            # with the conditional mean, its Stein factors move the part too: settled to 1 %
            if np.allclose(new_q, parts[qid], rtol=1e-3 if mo_t is None else 1e-2, atol=0) and not (moved or base_moved):
                break
            parts = dict(parts)
            parts[qid] = new_q
            if moved:
                res_model = trial
                Ig = self.ev.grouped_periodogram(res_model, "sensor.tone" in free)[3]
            E0, U = assemble(parts, res_model)
            inner = Inner(Ig, d.weights / W.taper(d.M)[2], E0, U, mod, mod_index)
            v, l = inner.optimize(v)
        if "sensor.jitter" in model.effects and "sensor.jitter" not in scale_ids:
            # a fixed jitter still explains (or not) the modulation
            dd = np.diff(r[d.k0:], axis=0)
            std_s = float(model.effects["sensor.jitter"].params["std_s"])
            l += Modulation(dd, ydot, d.k0, 1.0, self._quant_slope(model))(std_s**2)[0]
        if d.grid is not None:
            l += self.grid_loglik(model)
        l += self.ev.ramp_term(res_model, "sensor.tone" in free)
        fitted = _set_scales(model, scales, values(v), model)
        ev, tone_free = self.ev, "sensor.tone" in free
        return Fit(fitted, free, l, parts, inner, v, scale_ids, scale_ch, chparts,
                   lambda: ev.level_term(res_model, tone_free, fitted))

    def grid_loglik(self, model) -> float:
        """l_grid: values on the model's quantization grid (ln(1 / 2e-6) each) when the data are."""
        q = model.effects.get("sensor.quantization")
        if q is None:
            return 0.0
        step = np.broadcast_to(q.params["step"], (self.data.p,))
        l = 0.0
        for j, g in enumerate(self.data.grid):
            if g is not None and np.isclose(step[j], g, rtol=1e-6):
                l += self.data.N * math.log(1 / (2 * GRID_TOL))
        return l

    # outer parameters: grid then golden section, coordinate ascent
    def fit(self, model, free: dict, rounds: int = 2, new: tuple = (), screen: bool = False,
            only: tuple | None = None) -> Fit:
        """Fit the free parameters of ``model``. ``new``: effects whose searched parameters get a
        coarse grid over their whole range first (the others start from their current values).
        ``screen``: a cheap pass that searches only the new effects' parameters, once, with a
        coarser grid (candidates are ranked by it, then the leaders are fitted in full).
        ``only``: search only these effects' parameters (the variances are always fitted)."""
        best = self.inner_fit(model, free)
        outer = [(e, spec) for e in free for spec in CATALOGUE[e].fit.shape if spec[0] in free[e]
                 and (not screen or e in new) and (only is None or e in only)]
        # the new effects first, in the order given: a candidate searched jointly with the mean
        # effects already in gets its coarse grid beside their fitted values, before they move
        # (a scale factor started mid-range at +25 % sent a fitted lag along the ridge the two
        # share, and two rounds stopped 120 below the truth in 2 Delta l: generated case 229)
        outer.sort(key=lambda x: new.index(x[0]) if x[0] in new else len(new))
        if "sensor.tone" in free and "frequency_hz" in free["sensor.tone"] and (not screen or "sensor.tone" in new):
            best = self._fit_tone_frequency(best)
        n_rounds = 1 if screen else rounds
        rnd = 0
        mean = any(CATALOGUE[e].fit.kind == "mean" for e, _ in outer)
        while rnd < n_rounds:
            before = best.objective(mean)
            x0 = self._coords(best, outer)
            for e, spec in outer:
                best = self._search(best, e, spec, coarse=(rnd == 0 and e in new),
                                    n_grid=7 if screen else 9, n_golden=6 if screen else 10)
            if rnd > 0 or not new:
                best = self._pattern(best, outer, x0)
            gain = best.objective(mean) - before
            if gain < 0.05:
                break
            rnd += 1
            if rnd == n_rounds and not screen and len(outer) > 1 and gain > 1.0 and n_rounds < rounds + MORE_ROUNDS:
                n_rounds += 1           # still climbing a ridge the parameters share: one more round
        # a mean effect's parameter one per channel (:data:`PER_CHANNEL`): from the common value,
        # each channel's over its whole range, then each around its value, while a round gains
        # (the channels trade off through the outputs they share: a ridge, climbed by more rounds
        # while one still gains more than 1 in l)
        per_ch = [(e, spec) for e, spec in outer if PER_CHANNEL in free[e] and shape_channels(best.model, e) > 1]
        n_rounds = 1 if screen else rounds
        rnd = 0
        while per_ch and rnd < n_rounds:
            before = best.objective(True)
            for e, spec in per_ch:
                for j in range(shape_channels(best.model, e)):
                    best = self._search(best, e, spec, coarse=(rnd == 0 and e in new),
                                        n_grid=7 if screen else 9, n_golden=6 if screen else 10, ch=j)
            gain = best.objective(True) - before
            if gain < 0.05:
                break
            rnd += 1
            if rnd == n_rounds and not screen and gain > 1.0 and n_rounds < rounds + 2 * MORE_ROUNDS:
                n_rounds += 1
        return best

    def _coords(self, fit: Fit, outer) -> np.ndarray:
        """The searched parameters in the search's coordinates (ln for log-spaced ones)."""
        out = []
        for e, spec in outer:
            v = _shape_value(fit.model.effects[e], spec[0], self.data.Ts)
            out.append(np.nan if v is None else (math.log(v) if spec[4] == "log" and v > 0 else float(v)))
        return np.array(out)

    def _pattern(self, fit: Fit, outer, x0: np.ndarray) -> Fit:
        """Hooke-Jeeves pattern moves: after a round of one-parameter searches moved several
        parameters, try continuing along that displacement (1, 2, 4 times it) while it gains. Two
        parameters that trade off (a lag and a scale factor both set the response's amplitude)
        form a ridge that coordinate searches climb in small zigzags."""
        if len(outer) < 2:
            return fit
        x1 = self._coords(fit, outer)
        dx = x1 - x0
        if not np.all(np.isfinite(dx)) or np.count_nonzero(np.abs(dx) > 1e-12) < 2:
            return fit
        best = fit
        mean = all(CATALOGUE[e].fit.kind == "mean" for e, _ in outer)
        for lam in (1.0, 2.0, 4.0):
            x = x1 + lam * dx
            m = fit.model
            try:
                for (e, spec), xi in zip(outer, x):
                    lo, hi, spacing = self._bounds(spec)
                    v = math.exp(xi) if spacing == "log" else float(xi)
                    if not lo <= v <= hi:
                        raise ValueError("outside the parameter's range")
                    m = _set(m, e, {spec[0]: v})
                if _radius(m.Ad) >= 1.0 and _radius(self.base.Ad) < 1.0:
                    break
                f = self.inner_fit(m, fit.free)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                break
            if f.objective(mean) <= best.objective(mean):
                break
            best = f
        return best

    def _bounds(self, spec, ch: int | None = None):
        """A searched parameter's range (channel ``ch``'s: an input's own command for "umax")."""
        name, lo, hi, unit, spacing = spec
        d = self.data
        if unit == "Ts|T":
            return lo * d.Ts, hi * d.T, spacing
        if unit == "umax":
            um = d.umax if ch is None or ch >= d.umax_in.size or d.umax_in[ch] <= 0 else float(d.umax_in[ch])
            return lo * um, hi * um, spacing
        return lo, hi, spacing

    def _try(self, fit: Fit, e: str, name: str, value: float, ch: int | None = None) -> Fit | None:
        """The fit with ``e``'s ``name`` at ``value`` (at channel ``ch`` alone, the others kept)."""
        try:
            if ch is not None:
                vals = np.broadcast_to(_shape_values(fit.model.effects[e], name, self.data.Ts),
                                       (shape_channels(fit.model, e),)).copy()
                vals[ch] = value
                value = _vec(vals)
            m = _set(fit.model, e, {name: value})
            if _radius(m.Ad) >= 1.0 and _radius(self.base.Ad) < 1.0:
                return None            # e.g. a lag faster than Ts under forward Euler: not a model of anything
            return self.inner_fit(m, fit.free)
        except (ModelError, ValueError, np.linalg.LinAlgError):
            return None

    def _search(self, fit: Fit, e: str, spec, coarse: bool, n_grid: int = 9, n_golden: int = 10,
                ch: int | None = None, step: float | None = None) -> Fit:
        """One searched parameter (all channels alike, or channel ``ch`` alone): a grid over its
        range when ``coarse`` (or unset), then golden section around the best (the bracket's half
        width ``step`` in the search's coordinates, log or linear; default 1/40 of the range)."""
        lo, hi, spacing = self._bounds(spec, ch)
        name = spec[0]
        cur = _shape_value(fit.model.effects[e], name, self.data.Ts, ch)
        tr = (np.log, np.exp) if spacing == "log" else (lambda x: x, lambda x: x)
        a, b = tr[0](lo), tr[0](hi)
        best = fit
        # a mean effect's parameter sets the level a step settles at: the record's level enters
        mean = CATALOGUE[e].fit.kind == "mean"
        if coarse or cur is None:
            xs = np.linspace(a, b, n_grid)
            for x in xs:
                f = self._try(fit, e, name, float(tr[1](x)), ch)
                if f is not None and f.objective(mean) > best.objective(mean):
                    best = f
            step = (b - a) / (n_grid - 1)
        elif step is None:
            step = (b - a) / 40
        c = _shape_value(best.model.effects[e], name, self.data.Ts, ch)
        if c is None:                  # nothing on the grid was valid and the effect has no value yet
            return fit
        gr = (math.sqrt(5) - 1) / 2
        # golden section in [x0 - step, x0 + step]; when the maximum is found at an end of that
        # bracket (not at the parameter's bound), the bracket moves there and the search goes on:
        # a refit after another effect was added can move a correlation time by more than one step
        for _ in range(1 if coarse or cur is None else MAX_SHIFTS + 1):
            x0 = tr[0](c)
            lo2, hi2 = max(a, x0 - step), min(b, x0 + step)
            a2, b2 = lo2, hi2
            cache = {}

            def val(x):
                if x not in cache:
                    cache[x] = self._try(best, e, name, float(tr[1](x)), ch)
                f = cache[x]
                return -1e300 if f is None else f.objective(mean)

            c1, d1 = b2 - gr * (b2 - a2), a2 + gr * (b2 - a2)
            for _ in range(n_golden):
                if val(c1) > val(d1):
                    b2, d1 = d1, c1
                    c1 = b2 - gr * (b2 - a2)
                else:
                    a2, c1 = c1, d1
                    d1 = a2 + gr * (b2 - a2)
            moved = False
            for f in cache.values():
                if f is not None and f.objective(mean) > best.objective(mean):
                    best, moved = f, True
            if not moved:
                break
            c = _shape_value(best.model.effects[e], name, self.data.Ts, ch)
            xb = tr[0](c)
            edge = gr ** n_golden * (hi2 - lo2) * 2
            if not ((xb - lo2 < edge and lo2 > a) or (hi2 - xb < edge and hi2 < b)):
                break
        return best

    def _fit_tone_frequency(self, fit: Fit) -> Fit:
        d = self.data
        tone = fit.model.effects["sensor.tone"]
        freq = np.broadcast_to(tone.params["frequency_hz"], (d.p,)).astype(float).copy()
        ym, _ = self.ev.mean(fit.model)
        mo = self.ev.quant_moments(fit.model)[0]
        r = d.y - ym if mo is None else d.y - ym - mo.g
        for j in range(d.p):
            freq[j] = refine_frequency(r[:, j], freq[j], d.Ts, d.k0, 1.0 / (d.M * d.Ts))
        m = _set(fit.model, "sensor.tone", {"frequency_hz": _vec(freq)})
        f = self.inner_fit(m, fit.free)
        # the periodogram's peak is the line's maximum-likelihood frequency (Kay 1993 ch. 7); the
        # Whittle likelihood of group means cannot resolve shifts of a CRLB (its differences there are
        # +-0.1, noise), so it only vetoes a refinement it rejects at 5 %: keeping the start on a
        # smaller difference left the frequency on its grid value in a quarter of the records
        return f if f.loglik >= fit.loglik - CHI2_95 / 2 else fit


def _shape_value(eff, name: str, Ts: float, ch: int | None = None) -> float | None:
    """The current value of a searched parameter (a correlation time given as rho: -Ts / ln rho):
    channel ``ch``'s, or (None) the mean over the channels."""
    v = _shape_values(eff, name, Ts)
    return None if v is None else float(np.mean(v) if ch is None else v[ch if v.size > 1 else 0])


def _shape_values(eff, name: str, Ts: float) -> np.ndarray | None:
    """A searched parameter's values (1-d: one, or one per channel)."""
    pd = eff.param_dict()
    v = pd.get(name)
    if v is None and name == "tau_s" and "rho" in pd:
        rho = np.atleast_1d(np.asarray(pd["rho"], float))
        if np.all((rho > 0) & (rho < 1)):
            v = -Ts / np.log(rho)
    return None if v is None else np.atleast_1d(np.asarray(v, float))


def _radius(A: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(A)), initial=0.0))


def _vec(a):
    a = [float(x) for x in np.atleast_1d(a)]
    return a[0] if all(x == a[0] for x in a) else a


def _set(model, eid: str, values: dict):
    """The model with effect ``eid``'s parameters updated (added if absent), in the spelling its
    file used (:meth:`.effects.base.Effect.respell`: a white noise given as a density stays one)."""
    eff = model.effects.get(eid)
    params = eff.param_dict() if eff is not None else {}
    params.update(eff.respell(values) if eff is not None else values)
    if "tau_s" in values:
        params.pop("rho", None)
    return model.with_params(eid, params)


PER_OUTPUT = ("sensor.white", "sensor.bias_walk", "sensor.bias_markov")   # one variance per output
PER_INPUT = ("actuator.white", "actuator.ar1", "process.white")            # ... per (noise) input
COMMON = "common"     # among an effect's free names: one factor over its channels (the file's proportions)
PER_CHANNEL = "per_channel"   # among a mean effect's free names: its searched parameters one per channel
# the mean effects offered one value per channel: not the lag, whose per-input time constants took
# the amplitude loss of a saturation beside it (two-input case 16: lags 0.36 and 0.87 s and a
# Gauss-Markov bias in place of the planted lag 0.49 s and limit 0.57, error 6.5)
PER_CHANNEL_MEAN = ("actuator.saturation", "actuator.deadzone", "sensor.scale_factor")


def shape_channels(model, eid: str) -> int:
    """How many channels a mean effect's searched parameter has: one per input for an actuator
    effect (a saturation limit, a dead-zone width), one per output for a sensor effect (a scale
    factor)."""
    stage = CATALOGUE[eid].stage
    return model.m if stage == "actuator" else model.p if stage == "sensor" else 1


def n_channels(model, eid: str) -> int:
    """How many variances effect ``eid``'s scale has in a fit: one per output for a sensor noise
    (:data:`PER_OUTPUT`), one per input for an actuator noise and per noise input (a column of L)
    for a process noise (:data:`PER_INPUT`), where there are several; else 1 (one factor)."""
    if eid in PER_OUTPUT:
        return model.p
    if eid == "process.white":
        return model.plant.nw
    return model.m if eid in PER_INPUT else 1


def _channel(E: np.ndarray, j, chparts: dict, eid: str):
    """Effect ``eid``'s part at channel ``j`` alone (None: all of it, ``E``). A sensor noise's outputs
    are independent, so its cross-spectral matrices are diagonal: one output's part is its diagonal
    element. An input's part reaches every output: computed apart, in ``chparts`` under (eid, j)."""
    if j is None:
        return E
    if eid in PER_INPUT:
        return chparts[(eid, j)]
    out = np.zeros_like(E)
    if E.ndim == 3:
        out[:, j, j] = E[:, j, j]
    else:
        out[:, j] = E[:, j]
    return out


def _set_scales(model, scales: list, values: list, like):
    """``model`` with each scale of ``scales`` [(effect id, parameter, power, output or None)] at
    its value: per output where it has one (:func:`_channel`), else by :func:`_set_scale`."""
    per: dict = {}
    for (e, sname, _, j), val in zip(scales, values):
        if j is None:
            model = _set_scale(model, e, sname, float(val), like)
        else:
            per.setdefault((e, sname), {})[j] = float(val)
    for (e, sname), vals in per.items():
        # the outputs not listed (held) keep ``like``'s values
        cur = np.atleast_1d(np.asarray(like.effects[e].params[sname], float))
        full = np.broadcast_to(cur, (max(cur.size, max(vals) + 1),)).copy()
        for j, v in vals.items():
            full[j] = v
        model = _set(model, e, {sname: [float(x) for x in full]})
    return model


def _set_scale(model, eid: str, name: str, value: float, like):
    """``model`` with effect ``eid``'s scale ``name`` at ``value`` on its largest channel, the others
    in the proportions they have in ``like`` (the user's per-output or per-input values, e.g. a
    position and a velocity sensor's noise, are scaled by one factor, not made equal; a scale that
    is one value, or all zero, is set as one value)."""
    eff = like.effects.get(eid)
    cur = None if eff is None or name not in eff.params else np.atleast_1d(np.asarray(eff.params[name], float))
    if cur is None or cur.size < 2 or not np.max(cur) > 0 or np.all(cur == cur[0]):
        return _set(model, eid, {name: value})
    return _set(model, eid, {name: [float(value * c) for c in cur / np.max(cur)]})


# -- candidates ---------------------------------------------------------------------------------------------
@dataclass
class Candidate:
    effect: str
    mode: str                       # add | refit | replace:<effect id>
    fit: Fit
    k: int                          # free parameters it adds
    score: float = float("nan")     # Delta BIC against the current hypothesis
    sel: float = float("nan")       # choice score among the significant (Search.choice)
    loglik: float = float("nan")
    alternatives: list = field(default_factory=list)   # other effects the data support as well
    full: bool = False              # fit is already the joint thorough refit (Search.refit_all)
    by_error: tuple | None = None   # added on the views' word: (model error before, after)


def _scale_name(eff) -> tuple[str, int]:
    """The parameter that scales an effect's noise and the power the variance goes with."""
    if "psd" in eff.params:
        return "psd", 1
    return type(eff).fit.scale, 2


TONE_SIDE = 25            # bins either side of a tone candidate that give the data's own background
TONE_MIN_BINS = 5         # ... of which at least this many below it (a line needs a background on both sides)
                          # and twice as many in all (near Nyquist the side above is short)


def _stands_out(x: np.ndarray, i: int, thr: float) -> bool:
    """Bin ``i`` of the periodogram ``x`` over its neighbours' mean (the median of bins 3 to
    :data:`TONE_SIDE` away on each side, over ln 2: robust to other lines) exceeds ``thr``."""
    lo = x[max(1, i - TONE_SIDE): max(1, i - 2)]
    hi = x[i + 3: i + TONE_SIDE + 1]
    if lo.size < TONE_MIN_BINS or lo.size + hi.size < 2 * TONE_MIN_BINS:
        return False
    back = float(np.median(np.concatenate([lo, hi]))) / math.log(2.0)
    return x[i] > thr * max(back, 1e-300)


def tone_peaks(I: np.ndarray, E: np.ndarray, M: int, Ts: float, max_peaks: int = 3,
               exclude: tuple | None = None) -> list[tuple[int, float]]:
    """(output, frequency Hz) of bins whose I/E exceeds what Exp(1) allows over all bins (P < 1e-3),
    strongest first, at least 5 bins apart, and not a sidelobe (within 50 bins of a peak or an
    excluded line and under 1 % of its I/E: a strong line leaks through the taper's sidelobes).
    ``exclude``: frequencies (Hz) that are no tones (the command's lines and harmonics) and the
    half-widths (bins) of their zones, the main lobe of an off-bin line and the uncertainty of the
    frequency included; their leakage beyond is skipped as sidelobes.

    A line also stands out from the data's own spectrum around it: I over the mean of its
    neighbours (the median of bins 3 to :data:`TONE_SIDE` away on both sides, over ln 2) above
    half the model test's threshold (that test controls false lines; this one only tells a line
    from a broad excess), with at least :data:`TONE_MIN_BINS` of those bins below it. A broad
    excess that the model lacks is no line, however far it rises over the model: a bias walk
    missing from the model made its lowest bins stand out, and a "tone" of 1.2 cycles in the
    record (0.0025 Hz in 470 s) was reported in its place (generated case 47)."""
    out = []
    nf = I.shape[0]
    thr = math.log(nf / 1e-3)
    thr_local = thr / 2
    ex_bins, ex_half = (np.zeros(0), np.zeros(0)) if exclude is None else \
        (np.asarray(exclude[0], float) * M * Ts, np.asarray(exclude[1], float))
    for j in range(I.shape[1]):
        ratio = I[:, j] / np.maximum(E[:, j], 1e-300)
        ratio[0] = 0.0                                  # DC is no tone
        idx = np.flatnonzero(ratio > thr)
        # the excluded lines' own peaks (their strongest bin within the zone) count as chosen, not offered
        lines = []
        for b, hw in zip(ex_bins, ex_half):
            lo, hi = max(1, int(math.floor(b - hw))), min(nf - 1, int(math.ceil(b + hw)))
            if lo <= hi:
                k = lo + int(np.argmax(ratio[lo:hi + 1]))
                lines.append((k, float(ratio[k])))
        chosen: list[tuple[int, float]] = []
        for i in idx[np.argsort(-ratio[idx])]:
            if np.any(np.abs(i - ex_bins) <= ex_half):
                continue
            if any(abs(i - c) < 5 for c, _ in chosen):
                continue
            if any(abs(i - c) <= 50 and ratio[i] < 0.01 * rc for c, rc in chosen + lines):
                continue                                # a sidelobe of a stronger line
            if not _stands_out(I[:, j], int(i), thr_local):
                continue                                # a broad excess, not a line
            chosen.append((int(i), float(ratio[i])))
            if len(chosen) >= max_peaks:
                break
        out += [(j, c / (M * Ts)) for c, _ in chosen]
    return out


MODE_RANK = {"replace": 0, "refit": 1, "add": 2}
SLOW_DRIFT = 10.0         # actuator AR(1) this many plant time constants slow: a drift (Search._drift_as_bias)
EXACT_RANK = {"replace": 0, "add": 1, "refit": 2}     # on an exact tie: the user's values kept
TIE = 2.0                 # within which candidates count as equally supported (ranking units: Search.choice, or Delta BIC)
EXACT_TIE = 0.5           # ... and within which they are the same fit (chain order decides)
DISTINCT_Z = 1.96         # a likelihood ratio this many of its standard deviations tells two fits apart
DRIFT_BIASES = ("sensor.bias_markov", "sensor.bias_walk")   # the sensor's models of a slow drift


def plant_time_constant(model) -> float:
    """The plant's slowest time constant, 1 / min(-Re lambda) over the eigenvalues of its
    continuous A, an actuator lag's state included (inf with an integrator or an unstable mode)."""
    A = np.asarray(model.Ac, float)
    if A.size == 0:
        return math.inf
    re = np.linalg.eigvals(A).real
    return math.inf if np.any(re >= 0) else float(1.0 / np.min(-re))


def exact_tie(c, lead, key) -> bool:
    """``c`` and ``lead`` are the same fit: scores within :data:`EXACT_TIE` with as many free
    parameters (identical spectra, e.g. process and actuator white noise through one input). Two
    candidates of different sizes within it are not a tie: their scores already weigh the extra
    parameter (a walk and a Gauss-Markov bias, whose choice score is the likelihood-ratio test of
    1/tau > 0, are as the test decides, not as the signal chain's order)."""
    # as a difference: scores of 1e16 (a model without sensor noise) have a spacing above 0.5
    return key(lead) - key(c) < EXACT_TIE and c.k == lead.k


# Near-ties (the data cannot tell the candidates apart, e.g. white actuator and process noise through
# the same input, or saturation, dead zone and scale factor under a two-level command) are ranked
# by: a replacement, then a changed value, then an addition (the fewest effects: a wrong value of
# an effect the user has explains the data with no new physics), then the signal chain's order;
# the others are reported as alternatives. An exact tie (identical spectra) between a new effect and
# a changed value goes to the new effect: nothing in the data contradicts the user's value.


@dataclass
class Start:
    """A candidate before fitting: its initial model and free parameters."""
    effect: str
    mode: str
    model: object
    free: dict
    k: int


class Search:
    """Greedy forward selection over the catalogue with joint refits (see the module docstring)."""

    def __init__(self, model, data: Data, log=None, n_full: int = 3):
        self.data = data
        self.H = Hypotheses(data, model)
        self.log = log or (lambda s: None)
        self.nominal = model
        self.n_full = n_full
        # threads pay off once an evaluation's arrays are large (their setup is ~1 ms)
        self.workers = min(WORKERS, os.cpu_count() or 1) if data.N * data.p >= PARALLEL_MIN else 1
        # a long record: candidates are screened on its first SCREEN_N samples (a valid likelihood of
        # that part), then scored on the whole record at the screened values; the leaders are fitted
        # on the whole record (see :meth:`candidates`)
        self._side: list[parallel.Task] = []   # tasks that ride along with the next map (:meth:`beside`)
        self.Hs = self.H
        if data.N >= 2 * SCREEN_N:
            part = Data(data.y[:SCREEN_N + 1], None if data.u is None else data.u[:SCREEN_N + 1], data.Ts,
                        data.at_rest, data.k0)
            self.Hs = Hypotheses(part, model)

    def start(self) -> Fit:
        return self.H.inner_fit(self.nominal, {})

    def score(self, fit: Fit, cur: Fit, k: int) -> float:
        """Delta BIC: whether the data support adding the candidate at all."""
        return 2 * (fit.loglik - cur.loglik) - k * math.log(self.data.n_bic)

    @staticmethod
    def choice(fit: Fit, cur: Fit, k: int) -> float:
        """Which of the significant candidates: 2 Delta l - k c, c = :data:`CHIBAR2_95`. Between
        nested alternatives (a walk and a Gauss-Markov bias, its long-tau limit 1/tau = 0; white and
        AR(1) actuator noise, its short-tau limit rho = 0) this is the likelihood-ratio test of the
        extra parameter at 5 %. That parameter's null value is on the boundary of its range (tau_s >
        0), so the statistic's null distribution is 1/2 chi2_0 + 1/2 chi2_1 (Self & Liang 1987), whose
        95 % point is 2.71, not chi2_1's 3.84. Delta BIC would ask ln n ~ 12 per parameter of it and
        keep the limit case, wrongly, for a correlation time that a record of 20 of them shows
        clearly."""
        return 2 * (fit.loglik - cur.loglik) - k * CHIBAR2_95

    def candidates(self, cur: Fit, bar: float = THRESHOLD) -> list[Candidate]:
        """Every candidate screened (its own parameters searched, the rest refitted only in their
        variances; on a long record on its first :data:`SCREEN_N` samples, then the variances
        refitted and the candidate scored on the whole record), then the ``n_full`` best fitted
        jointly with everything freed so far on the whole record (every searched parameter from a
        coarse grid). The significant ones (Delta BIC > :data:`THRESHOLD`) come
        first, ranked by :meth:`choice`, the others by Delta BIC; near-ties (within :data:`TIE`)
        resolved towards fewer effects: a replacement first, then a changed value, then an
        addition; within a mode the best score, and the signal chain's order on an exact tie
        (:data:`EXACT_TIE`). ``bar``: the Delta BIC that counts as significant (the model-error rule
        of :func:`.diagnose._by_error` ranks every candidate by the choice score: ``-inf``)."""
        out: list[Candidate] = []
        starts = self.starts(cur)

        def screen(st):
            try:
                # a mean effect beside mean effects already fitted: searched jointly with them (a lag
                # fitted alone takes the amplitude loss a saturation causes; adding the saturation to
                # that lag only makes it worse until the lag gives it back)
                others = tuple(e for e in cur.free if e != st.effect and CATALOGUE[e].fit.kind == "mean"
                               and CATALOGUE[e].fit.shape)
                Hs = self.Hs
                if CATALOGUE[st.effect].fit.kind == "mean" and others:
                    fit = Hs.fit(st.model, st.free, new=(st.effect,) + others, only=(st.effect,) + others)
                else:
                    fit = Hs.fit(st.model, st.free, new=(st.effect,), screen=True)
                return fit if Hs is self.H else self.H.inner_fit(fit.model, fit.free)
            except (ModelError, ValueError, np.linalg.LinAlgError) as exc:
                return exc

        def screen_cost(st):
            spec = CATALOGUE[st.effect].fit
            return (3 if spec.kind == "mean" else 1) * (1 + len(spec.shape)) + (2 if st.effect == "sensor.tone" else 0)

        def per_input(st):
            return PER_CHANNEL in st.free.get(st.effect, ()) and CATALOGUE[st.effect].stage == "actuator"

        # an actuator mean effect's per-input form (a grid per input: the dearest screen) only where
        # its one-value form comes near significance (two limits clip alike: one value finds both)
        first = [st for st in starts if not per_input(st)]
        todo = [(first, self._map(screen, first, cost=screen_cost))]
        near = set()
        for st, fit in zip(*todo[0]):
            if not isinstance(fit, Exception) and self.score(fit, cur, st.k) >= bar - 30:
                near.add((st.effect, st.mode))
        later = [st for st in starts if per_input(st) and (st.effect, st.mode) in near]
        if later:
            todo.append((later, self._map(screen, later, cost=screen_cost)))
        for st, fit in ((st, fit) for sts, fits in todo for st, fit in zip(sts, fits)):
            if isinstance(fit, Exception):
                self.log(f"candidate {st.mode} {st.effect}: skipped ({fit})")
                continue
            c = Candidate(st.effect, st.mode, fit, st.k)
            c.score = self.score(fit, cur, st.k)
            c.start = st
            out.append(c)
        out.sort(key=lambda c: -c.score)
        # the two forms of a noise of several inputs (per input or one factor) and of a mean effect
        # of several channels (one value per channel or one for all): the better by Delta BIC
        best: dict = {}
        for c in out:
            best.setdefault((c.effect, c.mode), c)
        two = {(c.effect, c.mode) for c in out if c.effect in PER_INPUT or PER_CHANNEL in c.start.free.get(c.effect, ())}
        out = [c for c in out if (c.effect, c.mode) not in two or best[(c.effect, c.mode)] is c]
        leaders = [c for c in out[:self.n_full] if c.score >= bar - 30]

        def full_fit(c):
            try:
                return self.refit_all(c.fit, thorough=True)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                return None

        for c, full in zip(leaders, self._map(full_fit, leaders)):
            if full is not None and full.loglik > c.fit.loglik:
                c.fit = full
                c.score = self.score(full, cur, c.k)
                c.full = True
        for c in out:
            c.loglik = c.fit.loglik
            c.sel = self.choice(c.fit, cur, c.k)
        # significant candidates first, ranked by the choice score; the rest by Delta BIC
        out.sort(key=lambda c: (c.score < bar, -(c.sel if c.score >= bar else c.score)))
        if out:
            key = (lambda c: c.sel) if out[0].score >= bar else (lambda c: c.score)
            top = key(out[0])
            near = [c for c in out if top - key(c) < TIE and (c.score >= bar) == (out[0].score >= bar)]
            # the preferred mode first; within it the best score, and on an exact tie (identical
            # spectra, e.g. process and actuator white noise through the same input) chain order
            rank = min(MODE_RANK[c.mode.split(":")[0]] for c in near)
            same = [c for c in near if MODE_RANK[c.mode.split(":")[0]] == rank]
            lead = max(same, key=key)
            first = min((c for c in same if exact_tie(c, lead, key)), key=lambda c: CATALOGUE[c.effect].chain_order)
            sig = out[0].score >= bar
            first = self._drift_as_bias(first, [c for c in out if (c.score >= bar) == sig
                                                and MODE_RANK[c.mode.split(":")[0]] == rank], key)
            # an exact tie between a new effect and a changed value (identical spectra): the data do
            # not contradict the user's value, so it is kept and the effect is added. The leader's tie
            # first, then the chosen candidate's: a third candidate leading (an AR(1) 0.8 ahead in the
            # choice score, its extra parameter near the test's level) used to hide the latter, and
            # a refit of process noise was taken over the added actuator noise it is identical with
            for anchor in (max(near, key=key), first):
                exact = [c for c in near if exact_tie(c, anchor, key) and exact_tie(anchor, c, key)]
                if {"add", "refit"} <= {c.mode.split(":")[0] for c in exact}:
                    first = min(exact, key=lambda c: (EXACT_RANK[c.mode.split(":")[0]], CATALOGUE[c.effect].chain_order))
                    break
            near = [first] + [c for c in near if c is not first]
            first.alternatives = [c for c in near[1:] if c.effect != first.effect]
            out.remove(first)
            out.insert(0, first)
        return out

    def drift_margin(self, ar1: Fit, bias: Fit) -> float | None:
        """Colored actuator noise whose correlation time exceeds :data:`SLOW_DRIFT` times the
        plant's slowest time constant reaches the output through the plant's low-frequency gain
        alone: a drift the data can hardly tell from a sensor bias drift (a Gauss-Markov bias, or
        the walk, its long-tau limit), the usual model of such a drift. The margin (in the units of
        :meth:`choice`) by which the AR(1) fit ``ar1`` must beat the bias fit ``bias`` to be
        reported instead: :data:`TIE`, or :data:`DISTINCT_Z` standard deviations of the likelihood
        ratio between the two (:func:`lr_spread`) when larger (on the generated Gauss-Markov cases
        the AR(1)'s lead reached 2.2 with a spread of 2.1). None when the AR(1) is not that slow."""
        tau = _shape_value(ar1.model.effects["actuator.ar1"], "tau_s", self.data.Ts)
        if tau is None or not tau > SLOW_DRIFT * plant_time_constant(self.nominal):
            return None
        return max(TIE, DISTINCT_Z * (lr_spread(ar1, bias) or 0.0))

    def _drift_as_bias(self, first: Candidate, pool: list, key) -> Candidate:
        """A slow actuator AR(1) on top gives way to the better supported of the sensor bias
        candidates it does not beat by :meth:`drift_margin`. ``pool``: the candidates of the
        first's mode and significance."""
        if first.effect != "actuator.ar1":
            return first
        bias = []
        for c in pool:
            if c.effect in DRIFT_BIASES:
                margin = self.drift_margin(first.fit, c.fit)
                if margin is not None and key(first) - key(c) < margin:
                    bias.append(c)
        return max(bias, key=key) if bias else first

    def beside(self, fn) -> parallel.Task:
        """fn() as one more item of the next :meth:`_map` that forks (a process comes free for it
        there, where a process of its own would be a third on two cores), or when its result is
        asked for, whichever comes first (:class:`service.parallel.Task`)."""
        s = parallel.Task(fn)
        self._side.append(s)
        return s

    def _map(self, fn, items: list, cost=None) -> list:
        """fn over items, two at a time on long records: in this process and a forked copy of it
        where that is safe (:func:`service.parallel.can_fork`; the fits are mostly Python, which
        threads cannot run at once), else in :data:`WORKERS` threads (the transforms and array
        arithmetic release the GIL; the caches they share are :class:`service.memo.Memo`); results in order.
        ``cost``: an item's expected cost, the costliest started first (no worker idles at the
        end while the other runs a long fit)."""
        side, self._side = [s for s in self._side if not s.done], []
        if self.workers <= 1 or len(items) + len(side) < 2:
            self._side = side
            return [fn(x) for x in items]
        order = sorted(range(len(items)), key=lambda i: -cost(items[i])) if cost else list(range(len(items)))
        if parallel.can_fork():
            return parallel.fork_map(fn, items, order, portable=_portable, side=side, carry=self._carry())
        self._side = side
        from concurrent.futures import ThreadPoolExecutor
        out = [None] * len(items)
        with ThreadPoolExecutor(max_workers=self.workers) as pool:
            futures = {i: pool.submit(fn, items[i]) for i in order}
            for i, f in futures.items():
                out[i] = f.result()
        return out

    def _carry(self):
        """(mark, take, give) of :func:`.parallel.fork_map`: the parts a forked child computed
        (:meth:`Evaluator.parts`' cache, of the whole record and of the screened prefix) come back
        to this process, so that the next map's fits find them. The joint refits of a step's
        leaders share every correlation time of their coarse grids, and later steps' refits the
        same again: serially the second and third leader's refit took 0.8 s after the first's
        3.2 s (10^6 samples), forked each took 4.5 s, the child's parts lost with it."""
        caches = [ev._parts for ev in {id(h.ev): h.ev for h in (self.H, self.Hs)}.values()]

        def mark():
            return [set(c.keys()) for c in caches]

        def take(marks):
            return [{k: v for k, v in c.items() if k not in m} for c, m in zip(caches, marks)]

        def give(brought):
            for c, new in zip(caches, brought):
                c.update(new)
        return mark, take, give

    def starts(self, cur: Fit) -> list[Start]:
        d = self.data
        out: list[Start] = []
        model = cur.model
        for eid, cls in CATALOGUE.items():
            spec = cls.fit
            if spec.kind == "none" or eid in cur.free:
                continue
            if not model.can_have(eid):         # e.g. an actuator in a sensor-only model: none is there
                continue
            if spec.needs_command and not d.has_command:
                continue
            mode = "refit" if eid in model.effects else "add"
            try:
                if spec.kind in ("noise", "modulated", "mean"):
                    out += self._noise_or_mean(cur, eid, mode)
                    for rep in spec.replaces:
                        if mode == "add" and rep in model.effects and rep not in cur.free:
                            out += self._noise_or_mean(cur, eid, f"replace:{rep}")
                elif spec.kind == "grid":
                    out += self._grid(cur, mode)
                elif spec.kind == "line":
                    out += self._tones(cur, mode)
            except (ModelError, ValueError, np.linalg.LinAlgError) as exc:
                self.log(f"candidate {eid}: skipped ({exc})")
        return out

    def _noise_or_mean(self, cur: Fit, eid: str, mode: str) -> list[Start]:
        d = self.data
        spec = CATALOGUE[eid].fit
        model = cur.model
        if mode.startswith("replace:"):
            model = model.without_effect(mode.split(":", 1)[1])
        names = []
        init: dict = {}
        if spec.kind in ("noise", "modulated"):
            if mode == "refit":
                sname, _ = _scale_name(model.effects[eid])
            else:
                sname = spec.scale
                init[sname] = _unit_scale(spec, d.Ts) * (1e-3 if spec.kind == "noise" else 1e-1)
            names.append(sname)
        for sh in spec.shape:
            lo, hi, spacing = self.H._bounds(sh)
            if hi <= lo:
                return []
            names.append(sh[0])
            cur_v = None
            if mode == "refit":
                cur_v = _shape_value(model.effects[eid], sh[0], d.Ts)
            init[sh[0]] = cur_v if cur_v is not None else \
                (math.sqrt(lo * hi) if spacing == "log" else 0.5 * (lo + hi))
        m = _set(model, eid, init) if init else model
        free = dict(cur.free)
        free[eid] = names
        nc = n_channels(model, eid) if spec.kind == "noise" else 1
        out = [Start(eid, mode, m, free, len(names) + nc - 1)]
        ns = shape_channels(model, eid) if eid in PER_CHANNEL_MEAN else 1
        if ns > 1:
            # a mean effect of several inputs or outputs: also one value per channel (a saturation
            # limit per input, a scale factor per output; the file's values for a refit), each a
            # parameter for Delta BIC; :meth:`candidates` keeps the better supported of the two
            mc = m
            if mode == "refit":
                for sh in spec.shape:
                    v = _shape_values(model.effects[eid], sh[0], d.Ts)
                    if v is not None and v.size == ns:
                        mc = _set(mc, eid, {sh[0]: _vec(v)})
            elif eid == "sensor.scale_factor":
                # linear in the residual: each output's least-squares factor on the mean response
                # (a grid cannot start near it when the response is far above the noise)
                mc = _set(mc, eid, {"error": _vec(self._scale_ls(model))})
            out.append(Start(eid, mode, mc, dict(free, **{eid: names + [PER_CHANNEL]}), len(names) * ns))
        if nc > 1 and eid in PER_INPUT:
            # a noise of several inputs: also one factor over them (the file's proportions, equal for
            # a new effect); :meth:`candidates` keeps the better supported of the two. Where inputs
            # reach the outputs alike their variances are not told apart, and a per-input fit put
            # all of an equal noise on one of them
            out.append(Start(eid, mode, m, dict(free, **{eid: names + [COMMON]}), len(names)))
        return out

    def _scale_ls(self, model) -> np.ndarray:
        """Per output, the least-squares scale-factor error e of y - E[y] = e E[y] (both centered,
        from sample k0), within the search's range."""
        d = self.data
        ym, _ = self.H.ev.mean(model)
        a = ym[d.k0:] - ym[d.k0:].mean(axis=0)
        r = d.y[d.k0:] - ym[d.k0:]
        r = r - r.mean(axis=0)
        den = np.sum(a * a, axis=0)
        e = np.where(den > 0, np.sum(r * a, axis=0) / np.where(den > 0, den, 1.0), 0.0)
        lo, hi, _ = self.H._bounds(CATALOGUE["sensor.scale_factor"].fit.shape[0])
        return np.clip(e, lo, hi)

    def _grid(self, cur: Fit, mode: str) -> list[Start]:
        d = self.data
        steps = d.grid
        if any(s is None for s in steps):
            return []
        q = cur.model.effects.get("sensor.quantization")
        if q is not None and np.allclose(np.broadcast_to(q.params["step"], (d.p,)), steps, rtol=1e-6):
            return []
        m = _set(cur.model, "sensor.quantization", {"step": _vec(steps)})
        free = dict(cur.free)
        free["sensor.quantization"] = []
        return [Start("sensor.quantization", mode, m, free, d.p)]

    def _tones(self, cur: Fit, mode: str) -> list[Start]:
        d = self.data
        free = dict(cur.free)
        free["sensor.tone"] = ["amplitude", "frequency_hz"]
        if mode == "refit":
            return [Start("sensor.tone", mode, cur.model, free, 2 * d.p)]
        r, _, _ = self.H.ev.residual(cur.model, False)
        I = W.periodogram(r, d.k0)
        E = sum(W.expected_parts(cur.model, d.M, d.k0, d.at_rest, cache=self.H.ev._parts,
                                 ydot_sq=W.slope_power(self.H.ev.mean(cur.model)[1][d.k0:], False)).values())
        out = []
        # a line at a frequency (or harmonic) of the command's own lines is the mean response's error
        # (a lag, a gain, a saturation's odd harmonics), not an interference tone
        lines = d.command_lines()
        order = np.arange(1, HARMONICS + 1)
        harm = np.outer(lines, order).ravel()
        # zone: the main lobe of an off-bin line (+-2.5 bins) and the line's frequency known to half a
        # bin, times the harmonic's order
        half = np.broadcast_to(2.5 + 0.5 * order, (lines.size, order.size)).ravel()
        keep = harm < 0.5 / d.Ts
        harm, half = harm[keep], half[keep]
        if harm.size:
            self.log(f"tone candidates: none at the command's lines and their harmonics "
                     f"({', '.join(f'{x:.4g}' for x in harm[:4])}{', ...' if harm.size > 4 else ''} Hz)")
        for j, f in tone_peaks(I, E, d.M, d.Ts, exclude=(harm, half)):
            amp = np.zeros(d.p)
            amp[j] = 1.0
            m = _set(cur.model, "sensor.tone", {"amplitude": _vec(amp), "frequency_hz": _vec(np.full(d.p, f))})
            out.append(Start("sensor.tone", "add", m, free, 3))
        return out

    def refit_all(self, cur: Fit, thorough: bool = False) -> Fit:
        """Refit every free parameter jointly. Searched parameters move locally from their current
        values; ``thorough``: each first gets a coarse grid over its whole range (after an effect is
        added or removed, where an earlier effect may have taken its power with a very different
        shape, e.g. an AR(1) that stretched its correlation time to stand in for a missing walk)."""
        new = tuple(e for e in cur.free if CATALOGUE[e].fit.shape) if thorough else ()
        return self.H.fit(cur.model, cur.free, rounds=2, new=new)


# -- intervals ----------------------------------------------------------------------------------------------
class ChannelKey(NamedTuple):
    """An interval task's key (:func:`interval_tasks`) for one output's value of a parameter fitted
    per output: ``side`` 0 or 1 (its lower or upper end, each its own profile search) or None (its
    whole interval); ``ch`` the output, ``n`` how many outputs the parameter has, ``main``: the
    output whose interval is also the parameter's one interval (the largest value's)."""

    name: str
    side: int | None
    ch: int
    n: int
    main: bool


def merge_intervals(done: list) -> tuple[dict, dict]:
    """({name: interval}, {name: [each output's interval or None]}) from :func:`interval_tasks`'
    (key, result) pairs. The second holds the parameters fitted per output (:class:`ChannelKey`);
    the first, every parameter, one of those as its ``main`` output's interval."""
    out: dict = {}
    per: dict = {}
    main: dict = {}
    for key, res in done:
        if key is None:                              # (intervals, per output) of several parameters
            out.update(res[0])
            per.update(res[1])
        elif isinstance(key, ChannelKey):
            ivs = per.setdefault(key.name, [None] * key.n)
            if key.side is None:
                ivs[key.ch] = res
            else:
                if ivs[key.ch] is None:
                    ivs[key.ch] = [None, None]
                ivs[key.ch][key.side] = res
            if key.main:
                main[key.name] = key.ch
        elif isinstance(key, tuple):                 # (name, 0 | 1): one end
            out.setdefault(key[0], [None, None])[key[1]] = res
        else:
            out[key] = res
    for name, j in main.items():
        out[name] = per[name][j]
    return out, per


def per_output(model, eid: str) -> bool:
    """Whether ``eid``'s per-channel values are one per output (a sensor effect of a model of
    several outputs), so that each output's interval is profiled (:func:`interval_tasks`); an
    actuator's or process noise's channels are its inputs, and their interval stays the largest
    channel's."""
    return CATALOGUE[eid].stage == "sensor" and model.p > 1


def interval_tasks(H: Hypotheses, fit: Fit, eid: str) -> list:
    """95 % profile-likelihood intervals of ``eid``'s free parameters at the joint fit (every other
    free variance re-optimized, and the effect's own searched parameters too for its variance: a
    Gauss-Markov std and its tau trade off against each other), as independent (key, thunk) pairs
    to run concurrently (:func:`merge_intervals` assembles them). key: a parameter
    name (its interval), (name, 0 or 1) (its lower or upper end: each end is its own profile
    search), a :class:`ChannelKey` (one output's interval or end, for a parameter fitted per output),
    or None (intervals and per-output intervals of several parameters).

    A parameter fitted one value per output (:func:`per_output`: a sensor noise's variance, a
    scale factor's value per output) gets each output's own interval: the profile over that
    output's value alone, every other free value (the other outputs' too) re-optimized at each
    point, as for the one parameter of a single output. Its one interval (the ``name`` key) is the
    output's whose value is the largest, as for a parameter fitted per input."""
    eff = fit.model.effects.get(eid)
    if eff is None:
        return []
    spec = CATALOGUE[eid].fit
    p = fit.model.p
    if spec.kind == "line":
        return [(None, lambda: _tone_intervals(H, fit))]
    if spec.kind == "grid":
        # found exactly on the data's grid: each output's step is its own interval; the one interval
        # is the range of the outputs' steps
        step = eff.param_dict()["step"]
        iv = [step, step] if not isinstance(step, list) else [min(step), max(step)]
        own = np.broadcast_to(np.asarray(eff.params["step"], float), (p,))
        per = {"step": [[float(v), float(v)] for v in own]} if isinstance(step, list) else {}
        return [(None, lambda: ({"step": iv}, per))]
    shaped = [sh for sh in spec.shape if sh[0] in fit.free.get(eid, [])]
    out = []
    if eid in fit.scale_ids:
        name, power = _scale_name(eff)
        vals = np.broadcast_to(np.asarray(eff.params[name], float), (n_channels(fit.model, eid),))
        top = int(np.argmax(vals))
        chans = sorted({c for e, c in zip(fit.scale_ids, fit.scale_ch) if e == eid and c is not None})
        each = chans if chans and per_output(fit.model, eid) else [top] if chans else [None]
        for j in each:
            val = float(np.max(vals) if j is None else vals[j])
            if shaped:
                tasks = [(side, lambda side=side, j=j, val=val:
                          _profile_scale_shaped(H, fit, eid, name, val, 2 * side - 1, j)) for side in (0, 1)]
            else:
                tasks = [(None, lambda j=j, val=val: _profile_scale(H, fit, eid, name, power, val, j))]
            for side, task in tasks:
                if len(each) > 1:
                    key = ChannelKey(name, side, j, p, j == top)
                else:
                    key = name if side is None else (name, side)
                out.append((key, task))
    for sh in shaped:
        # one value per channel (:data:`PER_CHANNEL`): each output's own interval; a per-input
        # one's, the largest channel's (in magnitude), as a noise's of several inputs is
        ch = None
        chans = [None]
        if PER_CHANNEL in fit.free.get(eid, ()) and shape_channels(fit.model, eid) > 1:
            v = _shape_values(eff, sh[0], H.data.Ts)
            ch = int(np.argmax(np.abs(v))) if v is not None and v.size > 1 else None
            chans = list(range(shape_channels(fit.model, eid))) if per_output(fit.model, eid) else [ch]
        for j in chans:
            for side in (0, 1):
                key = ChannelKey(sh[0], side, j, len(chans), j == ch) if len(chans) > 1 else (sh[0], side)
                out.append((key, lambda sh=sh, side=side, j=j: _profile_outer(H, fit, eid, sh, 2 * side - 1, j)))
    return out


def _profile_scale(H: Hypotheses, fit: Fit, eid: str, name: str, power: int, val: float, j: int | None) -> list:
    """The 95 % profile interval of an effect's scale whose variance is one of the inner problem's
    (no searched parameter: :meth:`Inner.profile`, the other variances re-optimized at each value):
    channel ``j``'s (value ``val``), or (None) the one factor over its channels. The scale is
    ref v^(1 / power) (:meth:`Hypotheses.inner_fit`), so the variance's ends map to
    val (v_end / v_hat)^(1 / power); at v_hat = 0 (none of it fitted) through the reference."""
    a = fit.scale_ids.index(eid) if j is None else \
        next(i for i, (e, c) in enumerate(zip(fit.scale_ids, fit.scale_ch)) if e == eid and c == j)
    lo, hi = fit.inner.profile(a, fit.v, fit.loglik - _extra(H, fit), _scale_chi2(H, fit, eid, a))
    vhat = float(fit.v[a])
    if vhat > 0 and val > 0:
        return [val * (lo / vhat) ** (1 / power), val * (hi / vhat) ** (1 / power)]
    ref = _scale_ref(eid, name, H.data.Ts)
    return [ref * lo ** (1 / power), ref * hi ** (1 / power)]


def _tone_intervals(H: Hypotheses, fit: Fit) -> tuple[dict, dict]:
    """Least-squares amplitude (Var = 2 S / N) and the Cramer-Rao bound of the frequency
    (Var(w) = 12 / (eta N^3) with eta = A^2 / (2 S), i.e. 24 S / (A^2 N^3): Kay 1993 eq. 3.41), S
    the residual's per-sample spectral density next to the line (the 40 bins on each side, the
    line's own +-3 bins left out). ({name: interval}, {name: per output}) as
    :func:`merge_intervals` takes them: the amplitude is each output's own (several outputs), the
    one frequency's interval and the amplitude's one interval are the largest amplitude's."""
    d = H.data
    tone = fit.model.effects["sensor.tone"]
    amp = np.broadcast_to(tone.params["amplitude"], (d.p,)).astype(float)
    freq = np.broadcast_to(tone.params["frequency_hz"], (d.p,)).astype(float)
    r, _, _ = H.ev.residual(fit.model, True)
    n = d.N - d.k0
    lo_a, hi_a, lo_f, hi_f = [], [], [], []
    for j in range(d.p):
        x = r[d.k0:, j] - r[d.k0:, j].mean()
        X = np.abs(np.fft.rfft(x)) ** 2 / n
        b = int(round(freq[j] * n * d.Ts))
        idx = np.r_[max(1, b - 43):max(1, b - 3), b + 4:min(X.size, b + 44)]
        S = float(np.mean(X[idx])) if idx.size else float(np.var(x))
        sa = math.sqrt(2 * S / n)
        sf = math.sqrt(24 * S / (max(amp[j], 1e-300) ** 2 * n**3)) / (2 * np.pi * d.Ts) if amp[j] > 0 else 0.0
        lo_a.append(max(amp[j] - 1.96 * sa, 0.0))
        hi_a.append(amp[j] + 1.96 * sa)
        lo_f.append(freq[j] - 1.96 * sf)
        hi_f.append(freq[j] + 1.96 * sf)
    k = int(np.argmax(amp))
    per = {"amplitude": [[a, b] for a, b in zip(lo_a, hi_a)]} if d.p > 1 else {}
    return {"amplitude": [lo_a[k], hi_a[k]], "frequency_hz": [lo_f[k], hi_f[k]]}, per


def _profile_scale_shaped(H: Hypotheses, fit: Fit, eid: str, name: str, val: float, direction: int,
                          j: int | None = None) -> float:
    """The lower (``direction`` -1) or upper (+1) end of the profile interval of an effect's scale
    (value ``val``), its searched parameters refitted at every value. A scale per channel
    (:func:`n_channels`): channel ``j``'s alone, the other channels' variances re-optimized with the
    searched parameters (their data counted as evidence on them); ``j`` None: the one factor over
    the channels (the others scaled along with it)."""
    free = dict(fit.free)
    nc = n_channels(fit.model, eid)
    vec = np.broadcast_to(np.asarray(fit.model.effects[eid].params[name], float), (nc,)).copy()
    per_channel = j is not None
    chi2 = CHI2_95
    if _behind_nonlinearity(fit.model, eid):
        # the variance's sandwich factor where its gain switches (the shape held), for the
        # profile over the shape too
        pairs = list(zip(fit.scale_ids, fit.scale_ch))
        a = pairs.index((eid, j)) if per_channel and (eid, j) in pairs else fit.scale_ids.index(eid)
        chi2 = _scale_chi2(H, fit, eid, a)
    target = fit.loglik - chi2 / 2
    # the others' variances stay free (re-optimized at every value), channel j's is held
    free[eid] = list(fit.free[eid]) + [f"hold:{j}"] if per_channel else [n for n in fit.free[eid] if n != name]

    def at(v):
        if not per_channel:
            return _set_scale(fit.model, eid, name, v, fit.model)
        w = vec.copy()
        w[j] = v
        return _set(fit.model, eid, {name: [float(x) for x in w]})

    def l_at(v):
        try:
            return H.fit(at(v), free, rounds=1).loglik
        except (ModelError, ValueError, np.linalg.LinAlgError):
            return -1e300

    def edge(direction):
        inside, l_in, factor, ref = val, fit.loglik, 1.05, val
        if not val > 0:
            # fitted at 0 (the data have none of it): the lower end is 0; the upper is searched from
            # the value a new effect starts at, first down by decades to a value inside the interval
            if direction < 0:
                return 0.0
            ref = inside = _unit_scale(CATALOGUE[eid].fit, H.data.Ts) * 1e-3
            for _ in range(8):
                l_in = l_at(inside)
                if l_in >= target:
                    break
                inside /= 10.0
            else:
                return inside            # below 1e-8 of that: 0 for any purpose
        outside = inside * factor ** direction
        for _ in range(30):
            l_out = l_at(outside)
            if l_out < target:
                break
            if not UNBOUNDED < outside / ref < 1.0 / UNBOUNDED:
                # the data do not bound it on this side (a channel they hardly see): 0, or the
                # largest value tried (the factor squared at every step overflowed a float)
                return 0.0 if direction < 0 else outside
            inside, l_in, factor = outside, l_out, factor ** 2
            outside = inside * factor ** direction
        else:
            return outside
        return _crossing(l_at, inside, l_in, outside, l_out, target, peak=val if val > 0 else None)

    return edge(direction)


UNBOUNDED = 1e-4          # a profile's end this far from the estimate (ratio): the data do not bound it


def _crossing(l_at, x_in, l_in, x_out, l_out, target, tol=0.02, max_iter=10, log=True, peak=None):
    """Where the profile log-likelihood crosses ``target`` between x_in (above) and x_out (below):
    regula falsi on z = ln x (x > 0; ``log=False``: on x) with the Illinois modification (Dowell &
    Jarratt 1971), to |l - target| < tol (0.04 in 2 Delta l against the 3.84 that defines the edge;
    every step is a full refit, so a bisection's 8 steps cost twice as much for no useful digit).
    ``peak``: the estimate, where the profile is highest, x_in and x_out on one side of it: the
    search then runs on s = (z - z_peak)^2, in which a quadratic profile is a straight line (its
    first step lands on the crossing; on z, a bracket from the peak took 4-5)."""
    fwd, back = (math.log, math.exp) if log else ((lambda v: v), (lambda v: v))
    if peak is not None:
        zp = fwd(peak)
        sign = 1.0 if fwd(x_out) > zp else -1.0

        def to(x):
            return (fwd(x) - zp) ** 2

        def frm(sv):
            return back(zp + sign * math.sqrt(max(sv, 0.0)))
    else:
        to, frm = fwd, back
    a, fa = to(x_in), l_in - target                 # fa > 0
    b, fb = to(x_out), l_out - target               # fb < 0
    side = 0
    for _ in range(max_iter):
        c = b - fb * (b - a) / (fb - fa) if fb != fa else 0.5 * (a + b)
        if not (min(a, b) < c < max(a, b)):
            c = 0.5 * (a + b)
        fc = l_at(frm(c)) - target
        if abs(fc) < tol:
            return frm(c)
        if fc > 0:
            a, fa = c, fc
            if side == -1:
                fb *= 0.5
            side = -1
        else:
            b, fb = c, fc
            if side == 1:
                fa *= 0.5
            side = 1
    return frm(b - fb * (b - a) / (fb - fa)) if fb != fa else frm(0.5 * (a + b))


def _extra(H: Hypotheses, fit: Fit) -> float:
    """The parts of the log-likelihood outside the inner problem (grid, fixed jitter)."""
    lin = fit.inner.value(fit.v)[0] if fit.inner is not None else 0.0
    return fit.loglik - lin


def _profile_outer(H: Hypotheses, fit: Fit, eid: str, spec, direction: int, ch: int | None = None) -> float:
    """The lower (``direction`` -1) or upper (+1) end of a searched parameter's profile interval
    (channel ``ch``'s, for a parameter fitted per channel: the other channels re-fitted at each
    value)."""
    name = spec[0]
    lo_b, hi_b, spacing = H._bounds(spec, ch)
    x = _shape_value(fit.model.effects[eid], name, H.data.Ts, ch)
    mean = CATALOGUE[eid].fit.kind == "mean"
    target = fit.objective(mean) - CHI2_95 / 2

    tr = math.log if spacing == "log" else (lambda z: z)

    def l_at(v):
        f = H._try(fit, eid, name, v, ch)
        if f is not None and ch is not None:
            # a profile: the other channels re-fitted (they trade off through shared outputs). The
            # bracket is twice this channel's displacement (it moves when the best is at its
            # end): a bracket of 1/40 of the range with 6 golden steps left the others where they
            # were, a conditional interval; a scale factor of 0.1 on one output and -0.05 on a
            # second, whose noise is coherent with the first's, read 0.0992 in (0.09913, 0.09930)
            # when its spread over records is 0.00056
            dx = max(abs(tr(v) - tr(x)), 1e-9 * max(abs(tr(x)), 1.0))
            for o in range(shape_channels(fit.model, eid)):
                if o != ch:
                    f = H._search(f, eid, spec, coarse=False, n_golden=12, ch=o, step=2.0 * dx)
        return -1e300 if f is None else f.objective(mean)

    def edge(direction):
        inside, l_in, l_out = x, fit.objective(mean), None
        if spacing == "log":
            step = 1.1
            outside = x * step ** direction
            for _ in range(40):
                if outside <= lo_b * 0.5 or outside >= hi_b * 2:
                    l_out = None
                    break
                l_out = l_at(outside)
                if l_out < target:
                    break
                inside, l_in, outside = outside, l_out, outside * (step ** direction)
                step = step ** 1.5
        else:
            span = (hi_b - lo_b) / 200
            outside = x + direction * span
            for _ in range(40):
                l_out = l_at(outside)
                if l_out < target:
                    break
                inside, l_in, outside = outside, l_out, outside + direction * span
                span *= 1.6
        if l_out is not None and -1e299 < l_out < target <= l_in:
            # a bracket of two fitted values: regula falsi on the squared distance from the estimate
            # (3-4 fits where the bisection took 12 to the same 0.02 in log-likelihood)
            return _crossing(l_at, inside, l_in, outside, l_out, target, log=spacing == "log", peak=x)
        for _ in range(12):
            # beyond the searched range, or a value that is no model (an unstable plant): bisection
            mid = math.sqrt(inside * outside) if spacing == "log" else 0.5 * (inside + outside)
            if l_at(mid) > target:
                inside = mid
            else:
                outside = mid
        return 0.5 * (inside + outside)

    return edge(direction)


# -- a forked second process for the candidate maps ---------------------------------------------------
def _portable(x):
    """A map's result made ready to cross to the parent: a :class:`Fit`'s level computed (its
    closure over this process' caches does not travel), recursively in lists, tuples and dicts."""
    if isinstance(x, Fit):
        _ = x.level
        x.level_fn = None
        return x
    if isinstance(x, (list, tuple)):
        return type(x)(_portable(v) for v in x)
    if isinstance(x, dict):
        return {k: _portable(v) for k, v in x.items()}
    return x
