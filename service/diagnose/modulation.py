"""The jitter's modulation term: residual power that follows the square of the predicted slope.

The squared differenced residual z_q is modelled as Gamma (chi-squared 1) with mean a + b x_q (x_q
the predicted slope squared, b = std_s^2, a fixed by the average level), a quasi-likelihood
divided by the dependence factor 1 + 2 sum rho_d(h)^2 (:func:`_dependence`).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft


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
    :meth:`.hypotheses.Hypotheses._quant_slope`: for small slopes it grows as ydot^2 too, and a coarse
    quantizer's own modulation would be read as a jitter). It is subtracted from z_q before the regression: known
    from the model, it leaves the jitter's slope its whole information (a free coefficient for it
    would absorb part of a real jitter)."""

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
        the sandwich variance, :func:`.sandwich.godambe_factor`)."""
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
