"""Editing a model's effects: setting parameters and scales, reading an effect's shape values and
channels (per output, per input, one common factor), the catalogue's units of a scale."""

from __future__ import annotations

import numpy as np

from ..model.effects import CATALOGUE


# -- hypotheses ---------------------------------------------------------------------------------------------
def plant_stable(model) -> bool:
    """Every eigenvalue of the discrete plant inside the unit circle, an integrator's (within
    :func:`noiselab.model.predict.unit_tol` of 1) excluded."""
    from ..model.predict import unit_tol
    Ad = np.asarray(model.Ad, float)
    if Ad.size == 0:
        return True
    return _radius(Ad) < 1.0 - unit_tol(np.asarray(model.Ac, float), model.Ts)


def _unit_scale(spec, Ts):
    return Ts / 10 if spec.unit_scale == "Ts/10" else float(spec.unit_scale)


def _scale_ref(eid: str, sname: str, Ts: float) -> float:
    """The value of ``eid``'s scale ``sname`` at which the inner problem's variance is 1 (its
    catalogue unit; a psd's is 1), unless the model is nonlinear and the scale is not 0
    (:meth:`.hypotheses.Hypotheses.inner_fit`: then its value)."""
    return _unit_scale(CATALOGUE[eid].fit, Ts) if sname != "psd" else 1.0


def _shape_value(eff, name: str, Ts: float, ch: int | None = None) -> float | None:
    """The current value of a searched parameter (a correlation time given as rho: -Ts / ln rho):
    channel ``ch``'s, or (None) the mean over the channels."""
    v = _shape_values(eff, name, Ts)
    return None if v is None else float(np.mean(v) if ch is None else v[ch if v.size > 1 else 0])


def _shape_values(eff, name: str, Ts: float) -> np.ndarray | None:
    """A searched parameter's values (1-d: one, or one per channel)."""
    pd = eff.param_dict()
    v = pd.get(name)
    if v is None and name == "tau_s" and "rho" in pd:
        rho = np.atleast_1d(np.asarray(pd["rho"], float))
        if np.all((rho > 0) & (rho < 1)):
            v = -Ts / np.log(rho)
    return None if v is None else np.atleast_1d(np.asarray(v, float))


def _radius(A: np.ndarray) -> float:
    return float(np.max(np.abs(np.linalg.eigvals(A)), initial=0.0))


def _vec(a):
    a = [float(x) for x in np.atleast_1d(a)]
    return a[0] if all(x == a[0] for x in a) else a


def _set(model, eid: str, values: dict):
    """The model with effect ``eid``'s parameters updated (added if absent), in the spelling its
    file used (:meth:`.effects.base.Effect.respell`: a white noise given as a density stays one)."""
    eff = model.effects.get(eid)
    params = eff.param_dict() if eff is not None else {}
    params.update(eff.respell(values) if eff is not None else values)
    if "tau_s" in values:
        params.pop("rho", None)
    return model.with_params(eid, params)


COMMON = "common"     # among an effect's free names: one factor over its channels (the file's proportions)
PER_CHANNEL = "per_channel"   # among a mean effect's free names: its searched parameters one per channel


def per_input(eid: str) -> bool:
    """Whether effect ``eid``'s scale has one variance per input (an actuator noise) or per noise
    input (a process noise): its part on one input reaches every output (``Effect.channels``)."""
    return CATALOGUE[eid].channels in ("input", "noise_input")


def shape_channels(model, eid: str) -> int:
    """How many channels a mean effect's searched parameter has: one per input for an actuator
    effect (a saturation limit, a dead-zone width), one per output for a sensor effect (a scale
    factor)."""
    stage = CATALOGUE[eid].stage
    return model.m if stage == "actuator" else model.p if stage == "sensor" else 1


def n_channels(model, eid: str) -> int:
    """How many variances effect ``eid``'s scale has in a fit (``Effect.channels``): one per output
    for a sensor noise, one per input for an actuator noise and per noise input (a column of L) for
    a process noise, where there are several; else 1 (one factor)."""
    layout = CATALOGUE[eid].channels
    if layout == "output":
        return model.p
    if layout == "noise_input":
        return model.plant.nw
    return model.m if layout == "input" else 1


def _channel(E: np.ndarray, j, chparts: dict, eid: str):
    """Effect ``eid``'s part at channel ``j`` alone (None: all of it, ``E``). A sensor noise's outputs
    are independent, so its cross-spectral matrices are diagonal: one output's part is its diagonal
    element. An input's part reaches every output: computed apart, in ``chparts`` under (eid, j)."""
    if j is None:
        return E
    if per_input(eid):
        return chparts[(eid, j)]
    out = np.zeros_like(E)
    if E.ndim == 3:
        out[:, j, j] = E[:, j, j]
    else:
        out[:, j] = E[:, j]
    return out


def _set_scales(model, scales: list, values: list, like):
    """``model`` with each scale of ``scales`` [(effect id, parameter, power, output or None)] at
    its value: per output where it has one (:func:`_channel`), else by :func:`_set_scale`."""
    per: dict = {}
    for (e, sname, _, j), val in zip(scales, values):
        if j is None:
            model = _set_scale(model, e, sname, float(val), like)
        else:
            per.setdefault((e, sname), {})[j] = float(val)
    for (e, sname), vals in per.items():
        # the outputs not listed (held) keep ``like``'s values
        cur = np.atleast_1d(np.asarray(like.effects[e].params[sname], float))
        full = np.broadcast_to(cur, (max(cur.size, max(vals) + 1),)).copy()
        for j, v in vals.items():
            full[j] = v
        model = _set(model, e, {sname: [float(x) for x in full]})
    return model


def _set_scale(model, eid: str, name: str, value: float, like):
    """``model`` with effect ``eid``'s scale ``name`` at ``value`` on its largest channel, the others
    in the proportions they have in ``like`` (the user's per-output or per-input values, e.g. a
    position and a velocity sensor's noise, are scaled by one factor, not made equal; a scale that
    is one value, or all zero, is set as one value)."""
    eff = like.effects.get(eid)
    cur = None if eff is None or name not in eff.params else np.atleast_1d(np.asarray(eff.params[name], float))
    if cur is None or cur.size < 2 or not np.max(cur) > 0 or np.all(cur == cur[0]):
        return _set(model, eid, {name: value})
    return _set(model, eid, {name: [float(value * c) for c in cur / np.max(cur)]})


def _scale_name(eff) -> tuple[str, int]:
    """The parameter that scales an effect's noise and the power the variance goes with."""
    if "psd" in eff.params:
        return "psd", 1
    return type(eff).fit.scale, 2
