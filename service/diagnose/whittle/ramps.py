"""The taper's ramps: what the tapered periodogram leaves out, given back in the time domain."""

from __future__ import annotations

import math

import numpy as np

from .periodograms import TAPER

# -- the taper's ramps: what the tapered periodogram leaves out ---------------------------------------------
RAMP_MIN = 256           # shortest differenced record given a ramp term
RAMP_LOG2_SEG = 13       # the whitener's Welch segments: up to 2^13 samples (M / 8 at most), half as many taps
RAMP_FLOOR = 1e-5       # the whitener's spectrum floor, relative to its mean


class Ramps:
    """l_ramp: the part of the differenced residual the taper weighs down, in the time domain.

    The tapered periodogram gives sample q the weight u_q^2 (u the Tukey shape, 0 at the ends, 1
    in the middle): a mean response that changes only in the first or last tenth of the record (a
    step at t = 0 from rest: its whole transient) leaves almost no trace in it. The samples'
    complement c_q = 1 - u_q^2 enters here instead:

        e = h * d (per output),   l_ramp = -(nu / 2) ln(sum_q c_q e_q^2 / nu),   nu = sum_q c_q

    with h a minimum-phase whitening filter of the residual's differenced spectrum (a generalized
    least-squares fit of the mean response over the ramps) and the noise scale profiled out. The
    whitener is estimated once per record, from the nominal model's residual (Welch, Hann
    segments; cepstral minimum phase, Oppenheim & Schafer 2010 ch. 13), and held fixed: every
    hypothesis is scored with the same one, so the term changes only with the mean response and
    the tones; for noise-only hypotheses it is a constant and their likelihood ratios are the
    periodogram's alone. Its spectrum is floored at :data:`RAMP_FLOOR` of its mean (a differenced
    record without a walk has a zero at DC that an exact whitener would integrate back). A
    record not from rest: the first len(h) samples, whose filter would read unseen samples before
    the record, are left out."""

    def __init__(self, d: np.ndarray, at_rest: bool):
        M, p = d.shape
        u = tukey_shape(M)
        L = int(np.count_nonzero(u[: M // 2] < 1.0))
        nseg = 1 << int(min(RAMP_LOG2_SEG, max(5, math.floor(math.log2(max(M // 8, 32))))))
        self.taps = nseg // 2
        self.M, self.L = M, L
        c = 1.0 - u**2
        self.c_start = c[:L].copy()
        if not at_rest:
            self.c_start[: self.taps] = 0.0
        self.c_end = c[M - L:].copy()
        self.nu = float(self.c_start.sum() + self.c_end.sum())
        self.h = [self._whitener(d[:, j], nseg) for j in range(p)]

    def _whitener(self, x: np.ndarray, nseg: int) -> np.ndarray:
        from scipy.signal import welch
        S = welch(x, nperseg=nseg, window="hann", detrend="constant")[1]
        S = np.maximum(S, RAMP_FLOOR * max(float(np.mean(S)), 1e-300))
        # the whitener's log magnitude -ln(S) / 2 folded to minimum phase through the real cepstrum
        cep = np.fft.irfft(-0.5 * np.log(S), nseg)
        fold = np.zeros(nseg)
        fold[0] = cep[0]
        fold[1:nseg // 2] = 2.0 * cep[1:nseg // 2]
        fold[nseg // 2] = cep[nseg // 2]
        h = np.fft.irfft(np.exp(np.fft.rfft(fold)), nseg)[: self.taps]
        return h / h[0]

    def __call__(self, d: np.ndarray) -> float:
        """l_ramp of the differenced residual ``d`` (M, p)."""
        from scipy.signal import oaconvolve
        if self.nu <= 0:
            return 0.0
        M, L, K = self.M, self.L, self.taps
        total = 0.0
        for j, h in enumerate(self.h):
            x = d[:, j]
            rss = float(self.c_start @ (oaconvolve(x[:L], h)[:L] ** 2))
            a = max(0, M - L - K)
            rss += float(self.c_end @ (oaconvolve(x[a:], h)[M - L - a: M - a] ** 2))
            total += -0.5 * self.nu * math.log(max(rss, 1e-300) / self.nu)
        return total


def tukey_shape(M: int) -> np.ndarray:
    """The taper's shape u (M,), 0..1, before its normalization to sum w^2 = M."""
    from scipy.signal.windows import tukey
    return tukey(M, TAPER) if M > 2 else np.ones(M)
