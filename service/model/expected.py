"""The expected value of each spectral estimator under the model, exact for the sampled process.

Every prediction compared with a record is the expectation of the very estimator applied to it,
formed from the model's autocovariance R(d) or variogram gamma(d) = E[(y_{k+d} - y_k)^2] / 2:
:func:`expected_welch`, E[Welch estimate] without segment-mean removal, from R(d) per effect.

Welch conventions are :func:`service.stats.welch`'s: one-sided, units^2/Hz, at f_j = j / (L Ts),
every bin (DC and Nyquist too) doubled.
"""

from __future__ import annotations

import numpy as np
from scipy.signal import get_window


def expected_welch(acf: dict, nperseg: int, Ts: float, window: str = "hann") -> dict:
    """E[Welch estimate] per effect {id: (nperseg//2+1, p)} from its autocovariance ``acf``
    ({id: R (>= nperseg, p) or None}), without segment-mean removal.

    The predicted spectrum seen through the estimator's window, exact for the sampled process:
    E|sum_n w_n x_n e^{-i w n}|^2 = sum_d R(d) c_w(d) e^{-i w d}, c_w(d) = sum_n w_n w_{n+d}
    (Percival & Walden 1993, eq. 186e), divided by fs sum w^2 and doubled except at DC and
    Nyquist. Leakage at resonances and tones is thus in the prediction, not in the error.
    Segment-mean removal (detrend "constant") biases only the lowest two or three bins.
    """
    from ..stats.psd import window_autocorrelation

    L = int(nperseg)
    w = get_window(window, L)
    c = window_autocorrelation(w)                        # c_w(d), d = 0..L-1
    out = {}
    for eid, R in acf.items():
        if R is None:
            out[eid] = None
            continue
        g = R * c[:, None]
        E = 2.0 * np.fft.rfft(g, axis=0).real - g[0]
        E *= 2.0 * Ts / np.sum(w**2)
        out[eid] = E
    return out
