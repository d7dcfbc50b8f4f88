"""The sensor's own filter (``output_filter``, :mod:`.effects.sensor_filter`) in the predictions.

The filter acts on the sum of the sensor sources before it in the chain (``chain_order`` below the
filter's); the predictor sees each such source through it:

* a source with states (``sensor_linear``: s' = F_s s + G_s e, x = H_s s) is cascaded with the
  filter's realization (F_f, G_f, H_f, J_f) into one block of states [s, s_f] (:func:`cascade`);
* a white primitive (variance s^2, no states) becomes a source of the filter's states alone
  (x = J e with J = diag(s)), so it leaves the primitives (:func:`filtered_whites`);
* a tone A sin(2 pi f0 t) leaves the filter as |H(f0)| A sin(2 pi f0 t + phase): its amplitude is
  scaled (the phase is random in a record);
* a walk has no stationary state: it stays a primitive and carries the filter, whose impulse
  response its spectra are computed with (the ``("walk", q, var0, filter)`` primitive).

Exact for a linear time-invariant filter: superposition over the sources.
"""

from __future__ import annotations

import numpy as np


def output_filter_of(model):
    """The model's effect with the ``output_filter`` hook (the sensor's own filter), None without one."""
    return next((e for e in model.effects.values() if hasattr(e, "output_filter")), None)


def _before(e, flt) -> bool:
    """Whether effect ``e`` acts before the filter ``flt`` (and so passes through it)."""
    return flt is not None and e.chain_order < flt.chain_order


def sensor_blocks(model, sen_lin: list, flt) -> list:
    """[(effect id, (F, G, H, J))]: the sensor sources with states ``sen_lin`` (``sensor_linear``,
    y += H s + J e) and, with the sensor's own filter ``flt``, every sensor source before it
    cascaded with the filter (:func:`cascade`): a white primitive becomes a source of the filter's
    states (J = diag(std), no states of its own)."""
    p = model.p
    out = []
    for e in sen_lin:
        F, G, H = e.sensor_linear()
        out.append((e.id, (F, G, H, np.zeros((p, G.shape[1])))))
    if flt is None:
        return out
    filt = flt.output_filter()
    out = [(eid, cascade(blk, filt) if _before(model.effects[eid], flt) else blk) for eid, blk in out]
    for e in filtered_whites(model, flt):
        var = sum(np.broadcast_to(np.asarray(prm[1], float), (p,)) for prm in e.spectral() if prm[0] == "white")
        white = (np.zeros((0, 0)), np.zeros((0, p)), np.zeros((p, 0)), np.diag(np.sqrt(var)))
        out.append((e.id, cascade(white, filt)))
    return out


def filtered_whites(model, flt) -> list:
    """The sensor effects with a white primitive before the sensor's own filter (none without one)."""
    if flt is None:
        return []
    return [e for e in model.effects.values() if e.stage == "sensor" and hasattr(e, "spectral")
            and _before(e, flt) and any(prm[0] == "white" for prm in e.spectral())]


def primitives(model, flt) -> list:
    """[(effect id, kind, params)] of the effects' ``spectral()`` primitives (white / walk / tone /
    jitter) as the predictor sees them: the whites before the filter left out (states of the
    augmented system instead), a tone before it scaled by |H| at its frequency, and a walk's params
    (q, var0, filter) with the filter it passes through, or None."""
    out = []
    as_states = {e.id for e in filtered_whites(model, flt)}
    for e in model.effects.values():
        if not hasattr(e, "spectral"):
            continue
        for prim in e.spectral():
            if prim[0] == "white" and e.id in as_states:
                continue
            if prim[0] == "tone" and _before(e, flt):
                # a sinusoid through H(z): amplitude times |H| at its frequency
                prim = ("tone", np.asarray(prim[1], float) * flt.gain(prim[2]), prim[2])
            if prim[0] == "walk":
                prim = tuple(prim[:3]) + (flt if _before(e, flt) else None,)
            out.append((e.id,) + tuple(prim))
    return out


def cascade(src: tuple, filt: tuple) -> tuple:
    """A source (F_s, G_s, H_s, J_s) (x = H_s s + J_s e) feeding a filter (F_f, G_f, H_f, J_f)
    (w = H_f s_f + J_f x): states [s, s_f],

        F = [[F_s, 0], [G_f H_s, F_f]],  G = [[G_s], [G_f J_s]],  H = [J_f H_s, H_f],  J = J_f J_s."""
    Fs, Gs, Hs, Js = src
    Ff, Gf, Hf, Jf = filt
    ns, nf = Fs.shape[0], Ff.shape[0]
    F = np.zeros((ns + nf, ns + nf))
    F[:ns, :ns] = Fs
    F[ns:, :ns] = Gf @ Hs
    F[ns:, ns:] = Ff
    return F, np.vstack([Gs, Gf @ Js]), np.hstack([Jf @ Hs, Hf]), Jf @ Js


def line_gain(model, eid: str, f_hz) -> np.ndarray:
    """|H(f)| per output of the sensor's own filter for a line of effect ``eid`` at ``f_hz`` (one
    value or one per output): the factor from the line's amplitude in the model file to its
    amplitude in the measurement; 1 without a filter or for an effect after it."""
    flt = output_filter_of(model)
    if not _before(model.effects[eid], flt):
        return np.ones(model.p)
    return flt.gain(f_hz)

