"""The IEEE Std 952-1997 (annex C) slope readings of an Allan deviation of rate data: the
coefficients Q (quantization noise), N (random walk), K (rate random walk) and B (bias instability) as
allan_variance_ros and imu_utils report them, and the names of the power laws in SP 1065 and
IEEE 952 terms.

References:
    IEEE Std 952-1997, Specification format guide and test procedure for single-axis
    interferometric fiber optic gyros, annex C.
    NIST SP 1065: W. J. Riley, Handbook of Frequency Stability Analysis, 2008, sec. 5.2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import special as _sps_special
from scipy import stats as _sps

from .allan import AllanResult
from .errors import StatsError

__all__ = ["FLICKER_FLOOR", "IEEE952_NAMES", "NOISE_NAMES", "NOISE_SLOPES", "SlopeReading", "ieee952_readings"]

#: SP 1065's name of each power law (alpha of S_y(f) ~ f^alpha, the rate data's PSD), and the
#: slope mu/2 of sigma_y(tau) ~ tau^(mu/2) it gives (mu = -alpha - 1 for -2 <= alpha <= 1; white
#: and flicker PM both fall as about tau^-1; SP 1065 sec. 5.2, table 1).
NOISE_NAMES = {2: "white PM", 1: "flicker PM", 0: "white FM", -1: "flicker FM", -2: "random walk FM"}
NOISE_SLOPES = {2: -1.0, 1: -1.0, 0: -0.5, -1: 0.0, -2: 0.5}
#: The same power laws in IEEE Std 952-1997 (annex C) terms, for rate data such as a gyro's:
#: white PM is (angle) quantization noise Q, white FM the angle (velocity) random walk N, flicker
#: FM the bias instability B, random walk FM the rate random walk K.
IEEE952_NAMES = {2: "quantization (Q)", 1: "flicker PM", 0: "random walk (N)", -1: "bias instability (B)",
                 -2: "rate random walk (K)"}

#: sqrt(2 ln 2 / pi): the flat Allan deviation of flicker FM of coefficient B is B times this
#: (IEEE Std 952-1997, table C.1: sigma^2 = 2 ln 2 B^2 / pi), so B = floor / 0.664.
FLICKER_FLOOR = float(np.sqrt(2.0 * np.log(2.0) / np.pi))
# Passes of the N and K line fits, each with the other's variance removed (see ieee952_readings):
# the lines move by less than 1e-6 of themselves after the third on white noise plus a walk.
_LINE_PASSES = 4


@dataclass(frozen=True)
class SlopeReading:
    """One IEEE 952 coefficient read off an Allan deviation curve.

    Attributes:
        value: the coefficient (N and K: of the fitted line at tau_ref; B: the floor / 0.664), or
            None when the curve has no region to read it on (``reason`` says why).
        interval: (lo, hi) at the curve's confidence level, or None.
        tau_range: (first, last) tau [s] of the points it was read on, or None.
        points: number of taus read.
        reason: why ``value`` is None (None when there is a value).
    """

    value: float | None
    interval: tuple[float, float] | None
    tau_range: tuple[float, float] | None
    points: int
    reason: str | None


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) of each run of consecutive True in ``mask``."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _line_region(r: AllanResult, alpha: int) -> tuple[slice | None, str | None]:
    """The longest run of consecutive taus identified as ``alpha`` (the first of equals), or
    None and the reason."""
    slope = NOISE_SLOPES[alpha]
    if not np.any(r.dev > 0.0):
        return None, "the deviation is 0 at every tau (constant data)"
    runs = _runs((r.alpha == alpha) & (r.dev > 0.0))     # a zero deviation has no logarithm
    if not runs:
        found = ", ".join(sorted({NOISE_NAMES[int(a)] for a in r.alpha}, key=list(NOISE_NAMES.values()).index))
        return None, f"no tau where the noise is {NOISE_NAMES[alpha]} (slope {slope:+g}); found {found}"
    a, b = max(runs, key=lambda ab: (ab[1] - ab[0], -ab[0]))
    if b - a < 2:
        return None, (f"only one tau ({r.taus[a]:.4g} s) where the noise is {NOISE_NAMES[alpha]} "
                      f"(slope {slope:+g}); a line needs two")
    return slice(a, b), None


def _line_fit(r: AllanResult, sl: slice, slope: float, other_var: np.ndarray) -> tuple[float, float]:
    """(c, sd of c) of ln sigma = c + slope ln tau on the taus ``sl``, after removing the
    variance ``other_var`` the other line puts there (at most half of each point's)."""
    nu = r.edf[sl]
    half = 0.5 * nu
    # ln(dev^) = ln(sigma) + e, dev^2 = sigma^2 chi2_nu / nu: E[e] = (psi(nu/2) - ln(nu/2)) / 2,
    # Var[e] = psi'(nu/2) / 4 (the log-gamma moments); the offset removed, weights 1/Var[e]
    bias = 0.5 * (_sps_special.digamma(half) - np.log(half))
    var = 0.25 * _sps_special.polygamma(1, half)
    w = 1.0 / var
    dev2 = r.dev[sl] ** 2
    own = np.maximum(dev2 - other_var[sl], 0.5 * dev2)
    c = float(np.sum(w * (0.5 * np.log(own) - bias - slope * np.log(r.taus[sl]))) / np.sum(w))
    # the octaves share data (their errors are positively correlated): bound the sd of the
    # weighted mean by the fully correlated case, sum(w sd) / sum(w)
    return c, float(np.sum(w * np.sqrt(var)) / np.sum(w))


def _line_readings(r: AllanResult) -> dict[str, SlopeReading]:
    """Q, N and K: the lines of slope -1, -1/2 and +1/2, read at sqrt(3), 1 and 3 s. See
    :func:`ieee952_readings`."""
    lines = {"Q": (2, float(np.sqrt(3.0))), "N": (0, 1.0), "K": (-2, 3.0)}
    regions = {name: _line_region(r, alpha) for name, (alpha, _) in lines.items()}
    fits = {name: (0.0, 0.0) for name in lines}
    log_tau = np.log(r.taus)

    def line_var(name):  # the variance the fitted line ``name`` predicts at every tau
        if regions[name][0] is None:
            return np.zeros(r.taus.size)
        return np.exp(2.0 * (fits[name][0] + NOISE_SLOPES[lines[name][0]] * log_tau))

    for _ in range(_LINE_PASSES):
        fits = {name: _line_fit(r, regions[name][0], NOISE_SLOPES[lines[name][0]],
                                sum(line_var(o) for o in lines if o != name)) if regions[name][0] is not None
                else fits[name] for name in lines}
    z = float(_sps.norm.ppf(0.5 * (1.0 + r.conf)))
    out = {}
    for name, (alpha, tau_ref) in lines.items():
        sl, reason = regions[name]
        if sl is None:
            out[name] = SlopeReading(None, None, None, 0, reason)
            continue
        c, sd = fits[name]
        value = float(np.exp(c + NOISE_SLOPES[alpha] * np.log(tau_ref)))
        out[name] = SlopeReading(value, (value * float(np.exp(-z * sd)), value * float(np.exp(z * sd))),
                                 (float(r.taus[sl.start]), float(r.taus[sl.stop - 1])), sl.stop - sl.start, None)
    return out


def _floor_reading(r: AllanResult) -> SlopeReading:
    """B = min dev / 0.664 where the minimum is a floor. See :func:`ieee952_readings`."""
    i = int(np.argmin(r.dev))
    n = r.dev.size
    if not r.dev[i] > 0.0:
        return SlopeReading(None, None, None, 0, f"the deviation is 0 at tau = {r.taus[i]:.4g} s (constant data "
                            "there): no flicker floor")
    rises = i < n - 1 and bool(np.any(r.lo[i + 1:] > r.hi[i]))
    if not (r.alpha[i] == -1 or (i > 0 and rises)):
        at = f"{r.taus[i]:.4g} s"
        if i == n - 1:
            why = f"the deviation is lowest at the longest tau ({at}) and has not levelled off"
        elif i == 0:
            why = f"the deviation is lowest at the shortest tau ({at}) and rises from there"
        else:
            why = (f"the minimum at {at} is not flicker FM and the deviation does not rise "
                   "significantly after it")
        return SlopeReading(None, None, None, 0, why + ": no flicker floor in this record")
    # the floor's extent: the taus around the minimum whose intervals reach down to its own
    near = r.lo <= r.hi[i]
    a, b = next((s, e) for s, e in _runs(near) if s <= i < e)
    return SlopeReading(float(r.dev[i] / FLICKER_FLOOR),
                        (float(r.lo[i] / FLICKER_FLOOR), float(r.hi[i] / FLICKER_FLOOR)),
                        (float(r.taus[a]), float(r.taus[b - 1])), b - a, None)


def ieee952_readings(r: AllanResult) -> dict[str, SlopeReading]:
    """The IEEE Std 952-1997 (annex C) slope readings of an Allan deviation of rate data: the
    coefficients as allan_variance_ros and imu_utils report them.

    * ``Q`` (quantization noise, units times s): sigma = sqrt(3) Q / tau, so Q is the value at
      tau = sqrt(3) s of the line of slope -1, read where the noise is white PM (flicker PM, of
      the same slope, is not IEEE 952's Q);
    * ``N`` (angle / velocity random walk, units/sqrt(Hz)): sigma = N / sqrt(tau), so N is the
      value at tau = 1 s of the line of slope -1/2;
    * ``K`` (rate random walk, units/sqrt(s)): sigma = K sqrt(tau / 3), the value at tau = 3 s of
      the line of slope +1/2;
    * ``B`` (bias instability, units): the flicker floor sigma = 0.664 B, so B = min sigma / 0.664.

    Where the slope is -1 (-1/2, +1/2): at the taus whose identified noise type (``r.alpha``, lag-1
    autocorrelation or B1, :mod:`.noise_id`) is white PM (white FM, random walk FM), the power laws
    whose deviations have that slope (SP 1065 sec. 5.2): the identification uses all the data at
    each tau, where the difference of two neighbouring points is a noisy slope. The line is
    fitted on the longest run of such consecutive taus (at least two), each line after removing the
    variance the other lines put there, its slope held fixed as
    allan_variance_ros's ``get_intercept`` does (a least-squares line in log-log with the slope
    pinned; it fits tau < 10 s for N and every tau for K, here the run says where), each point
    weighted by 1 / Var(ln dev^) and its mean offset removed (dev^2 ~ sigma^2 chi2_nu / nu with
    nu = ``r.edf``: E[ln dev^] - ln sigma = (psi(nu/2) - ln(nu/2)) / 2, Var = psi'(nu/2) / 4).
    The interval bounds the fit's sd by the fully correlated case (the octaves share data) at
    the curve's confidence level ``r.conf``.

    B (as imu_utils divides by 0.6643): the minimum is read as a floor when its noise type is
    flicker FM, or when it lies after the shortest tau and some longer tau's interval lies
    wholly above the minimum's (the curve turns up); a curve still falling at its longest tau
    (white noise only) or rising from its shortest has none. ``tau_range`` is the run of taus
    around the minimum whose intervals reach down to its upper bound; the interval is the
    minimum's own.

    Readings that cannot be made are None with the reason. Only for ``adev`` and ``oadev``
    (the modified deviation has other slopes).
    """
    if r.kind not in ("adev", "oadev"):
        raise StatsError(f"r: IEEE 952 slope readings are defined on adev or oadev, not {r.kind}")
    return {**_line_readings(r), "B": _floor_reading(r)}
