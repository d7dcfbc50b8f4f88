"""The likelihood the diagnosis ranks and fits effects with: a debiased Whittle likelihood of the
differenced residual, exact for a record that starts at rest.

Symbols -> names:

=============  ==============  =================================================================
symbol         name            meaning
=============  ==============  =================================================================
r_k            ``r``           residual y_k - E[y_k] (measurement minus the model's mean response)
d_q            ``d``           differenced residual r_{q+k0+1} - r_{q+k0}, q = 0..M-1
I_f            ``I``           periodogram |sum_q w_q d_q e^{-i 2 pi f q / M}|^2 / M, f = 0..nf-1
E_f            ``E``           its expectation under the model, per effect (``parts``)
R(h), R_d(h)   ``R``, ``Rd``   autocovariance of r and of d at lag h samples
=============  ==============  =================================================================

Why this form:

* Differencing makes the bias random walk white (its increments are iid), so the nonstationary
  effect of the catalogue enters like every other one, and removes any constant offset.
* The periodogram's expectation is computed exactly for the finite record (the "debiased Whittle
  likelihood", Sykulski, Olhede, Guillaumin, Lilly & Early 2019, Biometrika 106(2)):
  E I_f = sum_{|h|<M} (1 - |h|/M) R_d(h) e^{-i w_f h}, so leakage from resonances and steep
  spectra is inside the prediction, never read as a missing effect.
* A record that starts at rest (noiselab's emulator starts every state at zero) is not stationary:
  P_k = P - F^k P F^T^k (the solution of P_{k+1} = F P_k F^T + Gamma Gamma^T from P_0 = 0, seed
  section 4), so Cov(s_k, s_l) = [stationary] - F^k P F^T^l for every k, l. The correction is
  separable, and its effect on E I_f is -(1/M) sum_c |sum_q w_{q,c} e^{-i w_f q}|^2 with
  w_q = v_{q+1} - v_q, v_k = H F^k P^{1/2}. No samples need to be thrown away as burn-in.
* The differenced series is tapered (Tukey, 10 % cosine at each end, normalized to sum w^2 = M)
  before the transform. Without it the end-point term (r_M - r_0), common to every bin, leaks
  Var(r)/M into all low frequencies and buries a bias walk there; with it E I_f =
  (1/M) sum_h c_w(h) R_d(h) e^{-i w_f h}, c_w the taper's autocorrelation (Dahlhaus 1988).
* Whittle: l = -(1/kappa) sum_f [ln E_f + I_f / E_f] (Whittle 1953). Several outputs: the
  cross-periodogram matrices I_f = X_f X_f^H / M against their expectations E_f (p x p, complex
  Hermitian), l = -(1/kappa) sum_f [ln det E_f + tr(E_f^-1 I_f)] (Brillinger 1981 ch. 7): two
  sensors of one plant share its noise, and summing their separate likelihoods would count that
  evidence twice. The cross terms come from the same sums of exponentials (Cov(y_{k+h}, y_k) =
  R(h), R(-h) = R(h)^T); sensor white noise and the bias walk are per output, the jitter's one
  sampling instant correlates the outputs through their slopes. kappa = M sum w^4 /
  (sum w^2)^2 corrects for the correlation the taper puts between neighbouring bins (the
  likelihood's curvature would otherwise be overstated by that factor).
* What the taper takes (sample q weighs u_q^2 in the periodogram, u the Tukey shape: nothing at
  the record's ends) is given back in the time domain by :class:`Ramps` with the complementary
  weights 1 - u_q^2: a step at t = 0 from rest has its whole transient there. The ends are not
  simply left untapered: at the start of a record from rest the process noise is zero but the
  sensor noise is not, so an untapered first sample r_0 is common to every low-frequency bin,
  whose periodogram values are then far from independent (on a null record with a chirp, the
  bias walk's likelihood-ratio score had 4x its model spread).

Every autocovariance is a sum of exponentials: with F = V diag(lambda) V^-1 (the augmented
dynamics of :class:`noiselab.model.predict.LinearSystem`), R(h) = Re sum_i c_i lambda_i^(h-1) for
h >= 1 (Percival & Walden 1993 ch. 9 for AR forms), computed in blocks up to where it has decayed
below 1e-13 of its start. Defective F (e.g. a critically damped plant) falls back to repeated
products of F.

The likelihood in modules, one idea each: :mod:`.periodograms` (the taper and the periodogram of
the differenced residual), :mod:`.groups` (frequency groups), :mod:`.modes` (sums of
exponentials), :mod:`.parts` (each source's expected periodogram, the Whittle log-likelihood),
:mod:`.ramps` (the taper's ramps) and :mod:`.level` (the record's level).
"""

from . import groups, level, modes, parts, periodograms, ramps
from .groups import Groups
from .level import level_density, level_loglik
from .modes import COND_MAX, DECAY, Modes
from .parts import (
                    PARTS_CACHE,
                    PARTS_CACHE_BYTES,
                    _sub_system,
                    acf_part,
                    expected_parts,
                    linear_part,
                    loglik,
                    parts_cache,
                    psd_sqrt,
                    walk_part,
                    white_part,
)
from .periodograms import TAPER, _spectrum, n_freqs, periodogram, slope_power, taper
from .ramps import RAMP_FLOOR, RAMP_LOG2_SEG, RAMP_MIN, Ramps, tukey_shape

__all__ = ["COND_MAX", "DECAY", "PARTS_CACHE", "PARTS_CACHE_BYTES", "RAMP_FLOOR", "RAMP_LOG2_SEG", "RAMP_MIN",
           "TAPER", "Groups", "Modes", "Ramps", "_spectrum", "_sub_system", "acf_part", "expected_parts",
           "groups", "level", "level_density", "level_loglik", "linear_part", "loglik", "modes", "n_freqs",
           "parts", "parts_cache", "periodogram", "periodograms", "psd_sqrt", "ramps", "slope_power", "taper",
           "tukey_shape", "walk_part", "white_part"]
