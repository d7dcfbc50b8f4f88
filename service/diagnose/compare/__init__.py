"""Compare a recording with a model: residual, the views, the model error, where it fails.

Residual: r_k = y_k - E[y_k], the measurement minus the model's predicted mean response to the
*recorded* command (seed section 3), so a recording that holds the command needs no truth.

Every prediction is the expectation of the very estimator applied to the data, computed exactly
from the model's per-effect variogram gamma(d) = E[(r_{k+d} - r_k)^2] / 2. For any process with
stationary increments (the linear part, tones, white noises and the bias walk alike) and any
estimator that is a quadratic form x^T A x with A annihilating constants (every estimator below
removes a mean), E[x^T A x] = -sum_{i,j} A_ij gamma(|i - j|). So the bias walk and the per-segment
mean removal are inside the predictions instead of being excluded:

* ``variance``: sample variance (mean removed) of consecutive windows of W samples (time windows);
  E = (1/W^2) sum_{i,j} gamma(|i-j|).
* ``acf``: autocovariance averaged over segments of M samples, each with its mean removed (lags);
  E[r(d)] = (1/M) [(M - d)(-gamma(d) - G) + sum_{n<M-d} (g(n) + g(n+d))], g(a) = (1/M) sum_m
  gamma(|a - m|), G = mean(g).
* ``psd``: Welch (Hann, 50 % overlap, segment mean removed, one-sided, every bin doubled as
  :func:`noiselab.stats.welch`), averaged in log bands (frequency bands); per bin
  E|X_j|^2 = -sum_{n,m} h_n conj(h_m) gamma(|n-m|), h_n = w_n e^{-i w_j n} - W_j / L.
* ``allan``: overlapping Allan deviation at octave taus (taus), the exact discrete Allan variance
  of the model (:func:`noiselab.model.spectra.allan_from_variogram`), its bounds from the
  estimator's equivalent degrees of freedom (Greenhall).

Standardized deviations z (E[z^2] = 1 when the model is right):
  psd (log bands, nu in the tens to thousands): z = (ln(emp / pred) - E[ln(chi2_nu / nu)]) /
  sd[ln(chi2_nu / nu)], E = digamma(nu/2) - ln(nu/2), Var = trigamma(nu/2), nu the equivalent dof;
  variance and allan (few dof at long windows and taus, skewed estimates): z = (emp - pred) / sd
  with the estimator's exact variance under the Gaussian model, so E[z^2] = 1 holds exactly; their
  flags come from the chi-squared band with nu = 2 E^2 / Var;
  acf: z = (emp - pred) / se, se from Bartlett's formula with the predicted autocovariance,
  divided by the number of segments, then scaled to the exact variance at lag 0 (the mean of the
  segments' variances, the correlation between segments included): Bartlett alone understates it
  when a memory (a Gauss-Markov bias) is as long as the segment.
The error of a view is mean(z^2); **the model error** is the mean of the views' errors (outputs
averaged). Both are about 1 when the model explains the data within the sampling noise of the
estimators and grow with the mismatch (a factor f in power in a band adds about (ln f)^2 nu / 2).
Points with |z| beyond the Bonferroni threshold of their view (family-wise 5 %) are flagged;
contiguous flagged runs are the :class:`Region` s where the data leave the model.

A noise whose variance follows the slope (a jitter: std_s^2 ydot_k^2) has its level taken over
the analysed record's own mean response, and the estimators' spreads are widened for the
modulation (:func:`.modulation.modulation_kappa`; the variance view predicts each window's own level).

The error of an effect acting after the sum (a quantizer) is correlated when the signal crosses
few steps per sample; how much depends on the other sources and on the mean response's increments
over the record (:func:`.cache.quantization_gamma`, :mod:`noiselab.model.effects.sensor_quantization`).

One module per concept: :mod:`.run` (compare(): settings, the record's predictions, the views run),
:mod:`.views` (the five views), :mod:`.spread` (each estimator's spread under the model; the
expectations are :mod:`noiselab.model.expected`'s), :mod:`.modulation` (a noise whose variance
changes over the record), :mod:`.summary` (the model error, the regions) and :mod:`.cache` (the
predictions kept per model).
"""

from __future__ import annotations

from ..results import AnalysisError
from .cache import (
    CACHE,
    cache_clear,
    predictor_of,
    quantization_gamma,
    quantizer_moments,
)
from .modulation import LocalVariance, modulation_kappa, slope_modulation
from .run import auto_burn, check_samples, compare, default_settings, transient_samples
from .spread import (
    KURT_DENSE,
    PSD_DOF_MAX,
    allan_edf_model,
    psd_band_dof_factor,
    psd_fine_length,
    window_kurtosis,
    windowed_variance_var,
)
from .summary import model_error, regions_of
from .views import (
    FAMILY_ALPHA,
    acf_view,
    allan_view,
    level_view,
    psd_view,
    variance_view,
)

__all__ = ["CACHE", "FAMILY_ALPHA", "KURT_DENSE", "PSD_DOF_MAX", "AnalysisError", "LocalVariance", "acf_view",
           "allan_edf_model", "allan_view", "auto_burn", "cache_clear", "check_samples", "compare",
           "default_settings", "level_view", "model_error", "modulation_kappa", "predictor_of", "psd_band_dof_factor",
           "psd_fine_length", "psd_view", "quantization_gamma", "quantizer_moments", "regions_of",
           "slope_modulation", "transient_samples", "variance_view", "window_kurtosis", "windowed_variance_var"]
