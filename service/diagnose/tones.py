"""Tone lines: peaks of the residual's periodogram that stand out, and a tone's frequency and
amplitude by least squares."""

from __future__ import annotations

import math

import numpy as np

from .thresholds import TONE_MIN_BINS, TONE_SIDE


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


def _stands_out(x: np.ndarray, i: int, thr: float) -> bool:
    """Bin ``i`` of the periodogram ``x`` over its neighbours' mean (the median of bins 3 to
    :data:`.thresholds.TONE_SIDE` away on each side, over ln 2: robust to other lines) exceeds ``thr``."""
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
    neighbours (the median of bins 3 to :data:`.thresholds.TONE_SIDE` away on both sides, over ln 2) above
    half the model test's threshold (that test controls false lines; this one only tells a line
    from a broad excess), with at least :data:`.thresholds.TONE_MIN_BINS` of those bins below it. A broad
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
