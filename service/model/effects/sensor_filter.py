"""``sensor.filter``: the sensor's own digital low-pass or decimation filter.

Where it sits. A MEMS IMU samples its transducer with an ADC at a high internal rate, passes the
words through a digital low-pass / decimation filter and writes the filter's output to the output
register that the host reads: the MPU-6050's DLPF (register 0x1A, DLPF_CFG: bandwidths 260 Hz down
to 5 Hz) and the ADIS16405's Bartlett-window FIR decimation filter (register SENS_AVG: 2^M taps)
both act before the register. Everything that enters the signal before the ADC's word is
formed is filtered: the transducer's white (thermal, ADC) noise, its bias drift (walk,
Gauss-Markov) and vibration pick-up (a tone). The register word is quantized at the filter's
output, so ``sensor.quantization`` acts after the filter (the grid of the recorded values is that
of the register, whatever the filter does). Signal chain at sample k (see :mod:`.base`):

    x_k = b_k + beta_k + v_k + tone_k                    sensor sources (chain orders 7-10)
    w_k = (h * x)_k                                       this filter (chain order 10.5)
    y_k = Q( (1 + s_f) (C x_k + D drive_k) + w_k + ydot_k dt_k )

The plant's output (with the scale factor) and the jitter's term ydot_k dt_k (which follows the
signal) pass unfiltered: exact for a static sensor, and for a signal inside the filter's passband
to the filter's gain error there; filtering the signal path too needs the mean response filtered
and a per-sample filter state in the step path (not done).

Kinds (each with unit gain at DC, so a bias passes unchanged):

* ``lowpass1`` with ``cutoff_hz`` f_c: the impulse-invariant first order (an RC stage sampled),
  a = exp(-2 pi f_c Ts),   w_k = a w_{k-1} + (1 - a) x_k,   H(z) = (1 - a) / (1 - a z^-1).
  For white x of variance s^2: Var w = s^2 (1 - a) / (1 + a), correlation a^d at lag d.
* ``lowpass2`` with ``cutoff_hz``: the second-order Butterworth (Q = 1/sqrt(2)) by the bilinear
  transform with the cutoff prewarped, K = tan(pi f_c Ts), c = 1 + sqrt(2) K + K^2:
  b0 = b2 = K^2 / c, b1 = 2 b0, a1 = 2 (K^2 - 1) / c, a2 = (1 - sqrt(2) K + K^2) / c,
  w_k = b0 x_k + b1 x_{k-1} + b2 x_{k-2} - a1 w_{k-1} - a2 w_{k-2}
  (what ``scipy.signal.butter(2, f_c, fs=1/Ts)`` gives; |H| = 1/sqrt(2) at f_c exactly).
* ``average`` with ``taps`` N: the moving average w_k = (1/N) sum_{i=0}^{N-1} x_{k-i} (an MA(N-1)
  filter); for white x: Var w = s^2 / N, correlation (N - d) / N for d < N, 0 beyond. Two such
  stages in cascade are the Bartlett (triangular) window of the ADIS16405.

IEEE Std 952 terms are unchanged by the filter: with unit DC gain, the mean of m samples over tau
= m Ts much longer than the filter's memory has the unfiltered variance, so the Allan deviation's
-1/2 line (N of ``sensor.white``) and the slower terms (K, the Gauss-Markov's) read the same; the
filter shows at tau of a few Ts (the Allan deviation below the N / sqrt(tau) line there), in the
ACF at short lags and in the PSD toward Nyquist.

The filter starts at rest (its state zero at k = 0, as the sources' states do): the first samples
(N - 1 for ``average``, a few 1 / (1 - a) for the low-passes) have less than the stationary variance.

Predictions are exact, through the output-filter hook ``output_filter()`` (F_f, G_f, H_f, J_f), a
state-space realization of H(z) per output (w = H_f s_f + J_f x, s_f' = F_f s_f + G_f x): the
predictor cascades it with every sensor source before it (a white noise becomes a state source of
the filter's states; a Gauss-Markov bias's states drive the filter's), and a tone's amplitude is
scaled by |H| at its frequency. A bias walk b before the filter (no stationary state: not in the
augmented system) is predicted from the filter's impulse response h directly. Its increments are
white of variance q per sample, so those of w = h * b are white noise through the filter, of
autocovariance q R_h(j), R_h(j) = sum_i h_i h_(i+j) (:meth:`SensorFilter.impulse_acf`); hence

    PSD  S_w(f) = |H(f)|^2 S_b(f)                                    (:meth:`SensorFilter.power_gain`)
    2 gamma_w(d) = Var(w_(k+d) - w_k) = q sum_(|j|<d) (d - |j|) R_h(j)
    Var w_k = Var(b_0) s_k^2 + q sum_(m<k) s_m^2,  s_m = sum_(i<=m) h_i   (:meth:`SensorFilter.step_response`)

the last from the walk's start (b_k = b_0 + sqrt(q) sum_(l<k) eta_l, the filter at rest). The
growth rate of Var w (q per sample) is the walk's: the filter's DC gain is 1.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import solve_discrete_lyapunov
from scipy.signal import lfilter, tf2ss

from ..lyapunov import _powers_apply
from ..schema import positive
from .base import Effect, FitSpec, _g

TAPS_MAX = 256
"""The longest moving average: its realization has N - 1 states per output in the predictions'
augmented system (a Lyapunov solve cubic in the states)."""

KINDS = ("lowpass1", "lowpass2", "average")


TAPS_FOUND = range(2, 17)
"""The moving averages the diagnosis tries (a MEMS IMU's decimation averages a few to 16 samples of
its internal rate; the likelihood is not unimodal in the taps, so each is a start of its own)."""


class SensorFilter(Effect):
    id = "sensor.filter"
    stage = "sensor"
    role = "modifier"
    chain_order = 10.5          # after the sensor sources (7-10), before the jitter and the quantizer
    summary = "the sensor's own digital low-pass / decimation filter"
    # the diagnosis: a shape of the noises before it, no variance of its own; its starts (fit_starts)
    # are each kind, a low-pass's cutoff searched from 0.5 % to 45 % of the sample rate
    fit = FitSpec("filter", shape=(("cutoff_hz", 0.005, 0.45, "fs", "log"),))

    @classmethod
    def fit_starts(cls, Ts: float) -> list[tuple[dict, list]]:
        """(parameters, searched names) of each start the diagnosis tries: a first- and a
        second-order low-pass (the cutoff searched), and each moving average of :data:`TAPS_FOUND`."""
        mid = float(np.sqrt(0.005 * 0.45)) / Ts
        return ([({"kind": k, "cutoff_hz": mid}, ["cutoff_hz"]) for k in ("lowpass1", "lowpass2")]
                + [({"kind": "average", "taps": n}, []) for n in TAPS_FOUND])

    def parse(self, t):
        self.kind = t.string("kind", choices=KINDS)
        nyq = 0.5 / self.dims.Ts
        if self.kind == "average":
            if t.has("cutoff_hz"):
                raise t.error("cutoff_hz", "kind 'average' takes taps (the number of samples averaged), not cutoff_hz")
            self.params["taps"] = float(t.integer("taps", check=lambda v: 1 <= v <= TAPS_MAX,
                                                  expect=f"an integer number of taps between 1 and {TAPS_MAX}"))
        else:
            if t.has("taps"):
                raise t.error("taps", f"kind {self.kind!r} takes cutoff_hz, not taps")
            self.params["cutoff_hz"] = t.vector(
                "cutoff_hz", self.dims.p, check=lambda v: bool(positive(v) and np.all(v < nyq)),
                expect=f"cutoff frequencies in Hz between 0 and the Nyquist frequency {nyq:g}")
        self.coeffs = [self._coeffs(j) for j in range(self.dims.p)]

    def param_dict(self):
        out = {"kind": self.kind}
        if self.kind == "average":
            out["taps"] = int(self.params["taps"])
        else:
            out.update(super().param_dict())
        return out

    def _coeffs(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) of H(z) = sum b_i z^-i / sum a_i z^-i for output j (module docstring)."""
        Ts = self.dims.Ts
        if self.kind == "average":
            n = int(self.params["taps"])
            return np.full(n, 1.0 / n), np.array([1.0])
        fc = float(self.params["cutoff_hz"][j])
        if self.kind == "lowpass1":
            a = np.exp(-2.0 * np.pi * fc * Ts)
            return np.array([1.0 - a]), np.array([1.0, -a])
        K = np.tan(np.pi * fc * Ts)
        c = 1.0 + np.sqrt(2.0) * K + K * K
        b0 = K * K / c
        return np.array([b0, 2.0 * b0, b0]), np.array([1.0, 2.0 * (K * K - 1.0) / c, (1.0 - np.sqrt(2.0) * K + K * K) / c])

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        if "taps" in params:
            return f"{cls.summary}: a moving average of {int(params['taps'])} samples"
        return f"{cls.summary}: a {params.get('kind', 'low-pass')} of cutoff {_g(params['cutoff_hz'])} Hz"

    # -- simulation -----------------------------------------------------------------------------
    def init_state(self, static_rng, trials):
        return {"zi": [np.zeros((trials, max(len(a), len(b)) - 1)) for b, a in self.coeffs]}

    def filter_terms(self, x: np.ndarray, state: dict) -> np.ndarray:
        """The filter applied to the sensor sources' sum ``x`` (trials, n, p) of one block, its
        state carried to the next block (the batch and step paths give the same floats)."""
        out = np.empty_like(x)
        for j, (b, a) in enumerate(self.coeffs):
            zi = state["zi"][j]
            if zi.shape[1] == 0:
                out[..., j] = b[0] * x[..., j]
                continue
            out[..., j], state["zi"][j] = lfilter(b, a, x[..., j], axis=-1, zi=zi)
        return out

    # -- prediction hooks (:mod:`.base`) ----------------------------------------------------------
    def output_filter(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(F_f, G_f, H_f, J_f): the filter as s_f' = F_f s_f + G_f x, w = H_f s_f + J_f x, block
        diagonal over the outputs (x, w: (p,))."""
        blocks = [_realize(b, a) for b, a in self.coeffs]
        n = sum(blk[0].shape[0] for blk in blocks)
        p = self.dims.p
        F, G, H, J = np.zeros((n, n)), np.zeros((n, p)), np.zeros((p, n)), np.zeros((p, p))
        i = 0
        for j, (Fj, Gj, Hj, Jj) in enumerate(blocks):
            k = Fj.shape[0]
            F[i:i + k, i:i + k] = Fj
            G[i:i + k, j] = Gj[:, 0]
            H[j, i:i + k] = Hj[0]
            J[j, j] = Jj[0, 0]
            i += k
        return F, G, H, J

    def gain(self, f_hz: np.ndarray) -> np.ndarray:
        """|H(e^{i 2 pi f Ts})| per output at frequencies ``f_hz`` (broadcast with (p,))."""
        f = np.broadcast_to(np.asarray(f_hz, float), (self.dims.p,))
        out = np.empty(self.dims.p)
        for j, (b, a) in enumerate(self.coeffs):
            zinv = np.exp(-2j * np.pi * f[j] * self.dims.Ts)
            out[j] = abs(np.polyval(b[::-1], zinv) / np.polyval(a[::-1], zinv))
        return out

    def power_gain(self, f_hz: np.ndarray) -> np.ndarray:
        """|H(e^{i 2 pi f Ts})|^2 at frequencies ``f_hz`` (nf,) per output: (nf, p)."""
        zinv = np.exp(-2j * np.pi * np.asarray(f_hz, float) * self.dims.Ts)
        return np.stack([np.abs(np.polyval(b[::-1], zinv) / np.polyval(a[::-1], zinv)) ** 2
                         for b, a in self.coeffs], axis=-1)

    def step_response(self, n: int) -> np.ndarray:
        """s_m = sum_(i<=m) h_i, m = 0..n-1 (n, p): the filter's response to a unit step from rest."""
        return np.stack([lfilter(b, a, np.ones(n)) for b, a in self.coeffs], axis=-1)

    def impulse_acf(self, L: int) -> np.ndarray:
        """R_h(j) = sum_i h_i h_(i+j), j = 0..L-1 (L, p): the autocovariance of unit white noise
        through the filter. ``average`` of N taps: (N - j) / N^2 for j < N. A recursive filter from
        its realization (F, G, H, J): P = F P F^T + G G^T, R_h(0) = H P H^T + J^2, R_h(j) =
        H F^(j-1) (F P H^T + G J) for j >= 1, zero beyond where F^j has decayed below 1e-16."""
        out = np.zeros((L, self.dims.p))
        j = np.arange(L)
        for col, (b, a) in enumerate(self.coeffs):
            if len(a) == 1:
                K = min(L, b.size)
                out[:K, col] = [b[:b.size - k] @ b[k:] for k in range(K)]
                continue
            F, G, H, J = _realize(b, a)
            if F.shape[0] == 1:                    # first order: R_h(j) = R_h(1) f^(j-1)
                f = F[0, 0]
                P = G[0, 0] ** 2 / (1.0 - f * f)
                out[0, col] = H[0, 0] ** 2 * P + J[0, 0] ** 2
                out[1:, col] = H[0, 0] * (f * P * H[0, 0] + G[0, 0] * J[0, 0]) * f ** (j[1:] - 1.0)
                continue
            P = solve_discrete_lyapunov(F, G @ G.T)
            X = F @ P @ H.T + G @ J
            rho = float(np.max(np.abs(np.linalg.eigvals(F))))
            K = min(L - 1, int(np.ceil(np.log(1e-16) / np.log(rho))) + 2 + F.shape[0])
            out[0, col] = (H @ P @ H.T + J @ J.T)[0, 0]
            if K > 0:
                out[1:K + 1, col] = np.einsum("i,kil->k", H[0], _powers_apply(F, X, K))
        return out

    def walk_variogram(self, q: np.ndarray, L: int) -> np.ndarray:
        """gamma(d), d = 0..L-1 (L, p), of a walk of increment variance q (p,) per sample through
        the filter: q/2 [d R_h(0) + 2 sum_(j=1)^(d-1) (d - j) R_h(j)] (module docstring)."""
        R = self.impulse_acf(L)
        d = np.arange(L, dtype=float)[:, None]
        S0 = np.concatenate([np.zeros((1, R.shape[1])), np.cumsum(R[1:], axis=0)])     # sum_(1<=j<=n) R(j)
        S1 = np.concatenate([np.zeros((1, R.shape[1])), np.cumsum(d[1:] * R[1:], axis=0)])
        inner = np.zeros_like(R)
        inner[1:] = d[1:] * S0[:-1] - S1[:-1]              # sum_(j=1)^(d-1) (d - j) R(j)
        return 0.5 * np.asarray(q, float) * (d * R[0] + 2.0 * inner)


def _realize(b: np.ndarray, a: np.ndarray):
    """A state-space realization (F, G, H, J) of sum b_i z^-i / sum a_i z^-i (both padded to one
    length: a proper transfer function in z of that degree), by :func:`scipy.signal.tf2ss`."""
    n = max(len(a), len(b))
    bb, aa = np.zeros(n), np.zeros(n)
    bb[:len(b)], aa[:len(a)] = b, a
    if n == 1:
        return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.array([[bb[0] / aa[0]]])
    F, G, H, J = tf2ss(bb, aa)
    return F, G, H, J
