"""Estimators on data: Welch PSD, autocorrelation, Allan-family deviations, rolling variance,
each with the sampling distribution the model checker needs (degrees of freedom, standard
errors, confidence intervals).

Conventions common to all modules: inputs are 1-D arrays of finite samples at a uniform rate
(``fs`` or ``rate`` in Hz); spectra are one-sided per Hz; autocovariances are per-sample-lag and
biased (1/N); variances say their ddof; deviations carry the data's units. Every bad argument
raises :class:`StatsError` (a ValueError) naming the argument. See each module's docstring for
the equations and references (NIST SP 1065, Percival & Walden 1993, Greenhall & Riley 2003,
Riley & Greenhall 2004, Brockwell & Davis 1991).
"""

from .acf import AcfEstimate, acf, bartlett_se
from .allan import AllanResult, adev, allan_taus, mdev, oadev, oadev_from_phase
from .edf import ONE_SIGMA_CONF, chi2_bounds, edf_greenhall
from .errors import StatsError
from .noise_id import noise_id_lag1
from .psd import PsdEstimate, psd_band, psd_log_bins, welch
from .rolling import RollingVariance, rolling_variance

__all__ = [
    "ONE_SIGMA_CONF",
    "AcfEstimate",
    "AllanResult",
    "PsdEstimate",
    "RollingVariance",
    "StatsError",
    "acf",
    "adev",
    "allan_taus",
    "bartlett_se",
    "chi2_bounds",
    "edf_greenhall",
    "mdev",
    "noise_id_lag1",
    "oadev",
    "oadev_from_phase",
    "psd_band",
    "psd_log_bins",
    "rolling_variance",
    "welch",
]
