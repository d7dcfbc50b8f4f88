"""Noises whose local variance is modulated over a record, and the estimators' spreads under it.

A white noise whose variance follows the signal's slope (the ``("jitter", s2)`` primitive of
:mod:`noiselab.model.effects.base`: variance s2 ydot_k^2) is predicted as white noise of its mean
variance, right on average; the estimators' spreads depend on how that variance is spread over
the record (:func:`modulation_kappa`). A quantizer's variance follows where the mean sits between
its levels the same way (``qmod`` of the views).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LocalVariance:
    """The modulated white part of one output: local variance ``m`` (n,) times its mean, owned by
    the effects ``ids`` (their parts of each view follow it)."""

    m: np.ndarray
    ids: tuple

    def share(self, parts: dict):
        """The sum of the modulated effects' parts among ``parts`` ({id: array}), or None."""
        got = [parts[e] for e in self.ids if e in parts]
        return sum(got) if got else None


def slope_modulation(pr, mean, burn: int):
    """(m, scale), or (None, None) without a noise whose variance follows the slope (a jitter,
    :meth:`Predictor.slope_modulated`). m_k (n, p): the local variance over its mean over the
    analysed samples, (ydot_k^2 + Var(ydot)) / mean. scale ({id: (p,)}): each effect's mean
    variance over the one the predictor used (its own command over its horizon, e.g. one sweep of
    a chirp from rest), for its variogram. The predictions take the noise as white of the mean
    variance (right on average); the estimators' spreads depend on how the variance is spread:
    :func:`modulation_kappa`."""
    levels = {eid: s2 for eid, s2 in pr.slope_modulated().items() if np.any(np.asarray(s2, float) > 0)}
    if not levels:
        return None, None
    st = pr.steady_state()
    if st.ydot_var is None or any(st.contributions.get(eid) is None for eid in levels):
        return None, None
    s2 = mean.ydot[burn:] ** 2 + st.ydot_var
    mu = s2.mean(axis=0)
    scale = {}
    for eid, v in levels.items():
        var = np.broadcast_to(np.asarray(v, float), mu.shape) * mu
        level = np.broadcast_to(st.contributions[eid], mu.shape)
        scale[eid] = np.where(level > 0, var / np.where(level > 0, level, 1.0), 1.0)
    return np.where(mu > 0, s2 / np.where(mu > 0, mu, 1.0), 1.0), scale


def _moving_mean(m: np.ndarray, ell: int) -> np.ndarray:
    ell = int(min(max(ell, 1), m.size))
    c = np.concatenate([[0.0], np.cumsum(m)])
    return (c[ell:] - c[:-ell]) / ell


def modulation_kappa(m: np.ndarray, ell, phi) -> np.ndarray:
    """Var(estimate) / Var under stationarity for quadratic estimators that resolve ``ell`` samples
    (per point: a Welch band of K bins of L-sample Hann segments resolves 0.51 L / K, an Allan
    deviation at tau = m Ts resolves 2m, a window its own length) of a noise whose white part, a
    fraction ``phi`` of the point's expected value, has local variance m_k times its mean: with
    P = 1 - phi + phi mbar (mbar the local means over ``ell``), mean(P^2) / mean(P)^2. A Gaussian
    quadratic form's variance follows the square of its local expectation, so a jitter whose power
    follows the slope (concentrated where a chirp crosses a resonance) leaves fewer effective
    degrees of freedom than the same power spread evenly."""
    ell = np.broadcast_to(np.asarray(ell, np.int64), np.shape(phi))
    phi = np.clip(np.asarray(phi, float), 0.0, 1.0)
    out = np.ones(phi.shape)
    moments = {}
    for i, (e, f) in enumerate(zip(ell.ravel(), phi.ravel())):
        if f <= 0:
            continue
        if e not in moments:
            mb = _moving_mean(m, e)
            moments[e] = (float(mb.mean()), float(np.mean(mb**2)))
        mu1, mu2 = moments[e]
        num = (1 - f) ** 2 + 2 * f * (1 - f) * mu1 + f**2 * mu2
        out.flat[i] = max(num / ((1 - f) + f * mu1) ** 2, 1.0)
    return out

