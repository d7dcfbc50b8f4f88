"""The comparison's predictions, computed once per model and estimator sizes.

Predictions depend on the model and the estimator sizes only, never on the data (except where a
quantizer's correlated error makes them depend on the record's mean response, whose hash is then
in the key): they are kept in one bounded :class:`noiselab.memo.Memo` so that a live analyzer, which
recomputes its views at 2 Hz on a window that fills up and then keeps its size, pays for them once
per model revision. The memo is least-recently-used (a live analyzer's cache must keep the views
it reads at every update however early they were put), bounded in count and in the bytes of the
arrays its values hold (dicts, lists and tuples of arrays, counted through), and keyed by the
model's content (:meth:`noiselab.model.model.Model.cache_key`). Cached arrays are read-only: every
comparison that uses them shares them.
"""

from __future__ import annotations

import hashlib

import numpy as np

from ...memo import Memo, deep_nbytes
from ...model.expected import _KERNELS
from ..results import AnalysisError
from .spread import _HANN_POWER

CACHE_MAX_BYTES = 64 * 2**20
CACHE_MAX_ENTRIES = 2048                   # a filling window adds ~2 small entries per update
CACHE = Memo(CACHE_MAX_ENTRIES, CACHE_MAX_BYTES, lru=True, sizeof=deep_nbytes)


def _freeze(value) -> None:
    """Cached arrays are shared by every comparison that uses them: make them read-only."""
    if isinstance(value, np.ndarray):
        value.flags.writeable = False
    elif isinstance(value, dict):
        for v in value.values():
            _freeze(v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            _freeze(v)


def _put(k, value) -> None:
    """``value`` kept under ``k`` (read-only) where it fits the byte bound; else not kept."""
    if deep_nbytes(value) <= CACHE.nbytes:
        _freeze(value)
    CACHE.put(k, value)


def cache_clear() -> None:
    """Forget every cached prediction (and the Welch kernels): what a fresh process starts with."""
    CACHE.clear()
    _KERNELS.clear()
    _HANN_POWER.clear()


def _cached(model, what: str, key, compute):
    """``compute()`` once per (model, what, key), from the bounded cache."""
    k = (model.cache_key(), what, key)
    hit = CACHE.get(k)
    if hit is None:
        hit = compute()
        _put(k, hit)
    return hit


def predictor_of(model):
    """The model's :class:`~noiselab.model.predict.Predictor`, one per model (its steady state and
    linear system are computed once, not at every comparison)."""
    return _cached(model, "predictor", None, model.predictor)


def _generous(L: int) -> int:
    """L rounded up to 1/8 of its power of two (at most +12.5 %): a window that fills up asks for a
    new variogram length at every update; this way it is computed ~8 times per doubling."""
    q = 1 << max(int(L).bit_length() - 3, 4)
    return -(-int(L) // q) * q


def gamma_parts(model, L: int) -> dict:
    """{effect id: (L, p) variogram} of the stationary-increment parts; error if not stable.
    One variogram per model is kept, computed for a generous length and sliced (the values at lag
    d do not depend on the length computed: :meth:`Predictor.variogram` builds them by doubling)."""
    k = (model.cache_key(), "gamma", None)
    got = CACHE.get(k)
    if got is None or got[0] < L:
        if got is not None:
            CACHE.pop(k)                        # free the shorter one before computing the longer
        Lg = _generous(L)
        got = (Lg, _gamma_parts_uncached(model, Lg))
        _put(k, got)
    return {eid: g[:L] for eid, g in got[1].items()}


def _gamma_parts_uncached(model, L: int) -> dict:
    vg = predictor_of(model).variogram(L, quantization=False)    # compare() puts in the record's own
    bad = [eid for eid, v in vg.items() if v is None]
    if bad:
        raise AnalysisError(f"model {model.name}: the plant has an unstable mode or a chain of integrators "
                            f"(a single integrator is supported), so {', '.join(bad)} has no stationary "
                            "increments to compare with")
    return vg


def record_hash(a: np.ndarray) -> str:
    """A record's array as a cache key (blake2b of its float64 bytes)."""
    return hashlib.blake2b(np.ascontiguousarray(a, float).tobytes(), digest_size=16).hexdigest()


def quantization_gamma(model, gam: dict, mean_y: np.ndarray, k0: int, jkey=None, h: str | None = None):
    """The variogram (L, p) over this record of the effect acting after the sum (a quantizer,
    :meth:`Predictor.after_sum`), and its part's lag 0 (p,): its error is correlated when the signal
    moves by less than a step between samples (:mod:`noiselab.model.effects.sensor_quantization`),
    and its conditional mean (in the mean response: :func:`quantizer_moments`) and variance depend
    on where the signal sits between the steps, so it depends on the record's own mean response
    (``mean_y`` from sample ``k0``), cached by it."""
    L = next(iter(gam.values())).shape[0]
    h = record_hash(mean_y) if h is None else h          # the caller's, when it has hashed mean_y

    def compute():
        pr = predictor_of(model)
        mo = quantizer_moments(model, mean_y, k0, h)
        R = pr.quantization_acf(gam, pr.motion(mean_y.shape[0], mean_y, k0), moments=mo)
        return R[0] - R, R[0].copy()
    return _cached(model, "quantization", (L, k0, h, jkey), compute)


def quantizer_moments(model, mean_y: np.ndarray, k0: int = 0, h: str | None = None):
    """The quantizer's conditional moments over this record (:meth:`Predictor.quantizer_moments`:
    E[Q(x_k)] - mu_k, the part of the mean measurement the quantizer adds when the noise before it
    is under about 0.84 step), cached by the record's mean response; None when there are none."""
    h = record_hash(mean_y) if h is None else h
    return _cached(model, "quantizer_moments", (k0, h, mean_y.shape),
                   lambda: predictor_of(model).quantizer_moments(mean_y, k0))
