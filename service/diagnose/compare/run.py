"""compare(): a recording against a model, the views computed (in threads on long records) and
summed up in a :class:`.results.Comparison` (formulas in :mod:`noiselab.diagnose.compare`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ... import parallel
from ...model import ModelError
from ...model.lyapunov import LEAK
from ...model.mean_response import free_response_fit
from ..results import VIEW_NAMES, AnalysisError, Comparison
from .cache import (
    _cached,
    gamma_parts,
    predictor_of,
    quantization_gamma,
    quantizer_moments,
    record_hash,
)
from .modulation import LocalVariance, slope_modulation
from .summary import model_error, regions_of
from .views import acf_view, allan_view, level_view, psd_view, variance_view

JITTER_LEVEL_STEP = 0.005     # the jitter's level over the record is applied on a grid of this step in ln
VIEW_THREADS = 2              # threads for the views of one comparison, on records ...
VIEW_THREADS_MIN = 50_000     # ... of at least this many samples x outputs


# -- settings ----------------------------------------------------------------------------------
def default_settings(n: int) -> dict:
    """Estimator sizes for n samples: Welch segment L, ACF segment M and max lag, variance window."""
    L = int(min(4096, 2 ** np.floor(np.log2(max(n // 8, 16)))))
    M = int(min(4096, 2 ** np.floor(np.log2(max(n // 4, 16)))))
    return {"nperseg": L, "acf_segment": M, "max_lag": max(4, M // 8), "window": int(max(16, n // 50)),
            "bins_per_decade": 10}


def transient_samples(model) -> int:
    """Samples until the covariance of a model started at rest is within 1 % of stationary:
    ln(0.01) / (2 ln rho), rho the spectral radius of the augmented stationary dynamics. The states
    of a source that starts stationary (``initial_cov``: a flicker bias's correlation times run to
    10 / (2 pi f_lo), far beyond a record) have no transient and are left out: they feed the other
    states but are fed by none, so the other states' eigenvalues are those of F without them."""
    pr = predictor_of(model)
    pr.steady_state()
    F = pr._ls.F
    if F.size == 0:
        return 0
    still = np.concatenate([idx for _, idx, _ in pr.stationary_starts()] or [np.zeros(0, int)])
    keep = np.setdiff1d(np.arange(F.shape[0]), still)
    F = F[np.ix_(keep, keep)]
    if F.size == 0:
        return 0
    lam = np.linalg.eigvals(F)
    if pr._Dj:
        # a plant that integrates: its walk has stationary increments from the first sample (the
        # comparison is on them); the transient is the other modes'
        lam = lam[np.abs(lam - (1.0 - LEAK)) > LEAK]
    rho = float(np.max(np.abs(lam), initial=0.0))
    if rho <= 0 or rho >= 1:
        return 0
    return int(np.ceil(np.log(0.01) / (2.0 * np.log(rho))))

# -- entry point -----------------------------------------------------------------------------------------
def auto_burn(at_rest: bool, u) -> int | None:
    """compare()'s ``burn`` for a record: None (skip the model's transient from rest) when the
    record starts at rest (the transient is in its covariance), or when it has a command but does
    not start at rest (cut mid-stream, or the longest run after a gap: the predicted mean response
    of its command starts from zero there, the record does not); else 0."""
    return None if at_rest or (u is not None and bool(np.any(u))) else 0


def check_samples(model, t, y, u=None):
    """y (N, p) and t (N,) as float arrays, or AnalysisError naming what is wrong with them (or
    with the recorded command ``u``, (N, m), when there is one)."""
    y = np.asarray(y, float).reshape(len(y), -1)
    t = np.asarray(t, float)
    if y.shape[1] != model.p:
        raise AnalysisError(f"the recording has {y.shape[1]} measurement components, the model {model.p}")
    if u is not None:
        m = np.asarray(u, float).reshape(len(u), -1).shape[1]
        if m != model.m:
            raise AnalysisError(f"the recording's command has {m} components, the model {model.m} inputs")
    if not np.all(np.isfinite(y)):
        k = int(np.flatnonzero(~np.all(np.isfinite(y), axis=1))[0])
        raise AnalysisError(f"the measurement holds NaN or inf (first at sample {k}, t = {t[k]:g} s)")
    gamma_parts(model, 2)           # a plant the comparison cannot follow fails here, before its overflows
    return y, t




def compare(model, t: np.ndarray, y: np.ndarray, u: np.ndarray | None = None, *, truth=None,
            burn: int | None = 0, settings: dict | None = None, revision: int = 0,
            notes: list | None = None, level: bool = False, free_start: bool = False) -> Comparison:
    """Compare samples y (N, p) at times t (N,) (regular, period model.Ts) with ``model``.

    ``u`` (N, m): the recorded command (None: the model's own command generator). ``burn``:
    samples to skip at the start (None: the model's transient from rest, capped at half the
    record). ``settings`` override :func:`default_settings`. ``level``: the record starts at rest
    (sample 0 of a noiselab stream), so its absolute level is predicted where the model predicts
    one (:attr:`Model.predicts_level`: not a sensor-only model's): add the level view.
    ``free_start``: the record does not start at rest (cut mid-stream, or the longest run after a
    gap); under a command, the mean state after the burn is fitted
    (:func:`noiselab.model.mean_response.free_response_fit`).
    """
    y, t = check_samples(model, t, y, u)
    if model.command.kind == "external":
        # zero as the model computes it: the predictions' averages over the recorded command (a
        # generated command's record is its own, a live window of it the same shifted)
        model = model.replaying(u)
    pr = predictor_of(model)
    try:
        mean = pr.mean_response(command=u) if u is not None else pr.mean_response(len(y))
    except ModelError as exc:
        raise AnalysisError(str(exc))
    n = len(y)
    if burn is None:
        burn = min(_transient(model), n // 2)
    fitted_start = bool(free_start and u is not None and np.any(u) and model.n_x)
    if fitted_start:
        my, myd = free_response_fit(model, y, mean.y, mean.ydot, burn, model.out_gain)
        mean = replace(mean, y=my, ydot=myd)
    y_mean = mean.y
    qmo = quantizer_moments(model, mean.y) if pr.after_sum() is not None else None
    if qmo is not None:
        y_mean = mean.y + qmo.g                         # E[Q(x)]: a coarse step biases the mean
    r = (y - y_mean)[burn:]
    s = default_settings(r.shape[0])
    if settings:
        s.update(settings)
    pp = _record_predictions(model, pr, mean, burn, r.shape[0], s, qmo)
    # per output: one the plant's walk reaches has no stationary variance to hold its levels to
    level_at = np.isfinite(pp.var_stat) if level and model.predicts_level else np.zeros(model.p, bool)
    views = _run_views(_view_jobs(model, r, t[burn:], s, pp, level_at, burn), r.size)
    k = np.arange(n)[:, None]
    y_sd = np.sqrt(pp.var_stat + pp.walk0 + k * pp.walk_rate)
    if qmo is not None:
        # a quantizer's variance follows the mean's place between its levels (the walk included)
        y_sd[:, qmo.active] = np.sqrt(qmo.var_y[:, qmo.active])
    nts = list(notes or [])
    if fitted_start:
        nts.append(f"the record does not start at rest: analysis starts at t = {t[burn]:.3g} s ({burn} samples), "
                   f"the command's mean response from the mean state fitted there ({model.n_x} states, least squares)")
    elif burn:
        nts.append(f"analysis starts at t = {t[burn]:.3g} s, after the model's transient from rest ({burn} samples)")
    return _comparison(model, t, y, y_mean, y_sd, truth, views, revision, nts)


def _transient(model) -> int:
    """:func:`transient_samples`, cached per model."""
    return _cached(model, "transient", 0, lambda: transient_samples(model))


@dataclass
class _Predicted:
    """What the views of one record are compared with, beyond the model's own predictions."""

    gam: dict                   # {id: variogram (>= record length + 1, p)}, this record's parts in
    gam_short: dict             # ... cut to the longest estimator segment
    mod: np.ndarray | None      # (n, p) the slope-modulated white part's local variance over its mean
    mod_ids: tuple              # ... its effects
    jkey: object                # what else the cached view predictions depend on
    qmo_r: object               # the quantizer's moments over the analysed samples, or None
    corr: int                   # the stationary part's correlation length (samples), for the Allan dof
    var_stat: np.ndarray        # (p,) stationary Var(y), the quantizer's part over this record
    walk0: np.ndarray           # (p,) Var(b_0) of the walks
    walk_rate: np.ndarray       # (p,) their growth of Var(y) per sample
    walk_ids: set
    lines: set                  # the spectral lines' effects (tones)


def _record_predictions(model, pr, mean, burn: int, n: int, s: dict, qmo) -> _Predicted:
    """The model's variograms for a record of ``n`` analysed samples after ``burn``, with the
    parts that depend on its mean response ``mean``: a slope-modulated noise's level over this
    record (the predictor's is over its own horizon), on a 0.5 % grid (a live window sliding along
    a chirp then reuses the cached predictions), and a quantizer's correlated error."""
    L_need = max(s["nperseg"], s["acf_segment"], s["window"])
    gam = gamma_parts(model, max(L_need, n + 1))
    mod, jscale = slope_modulation(pr, mean, burn)
    jkey = None
    if jscale is not None:
        gam = dict(gam)
        steps = {eid: np.round(np.log(np.maximum(sc, 1e-12)) / JITTER_LEVEL_STEP).astype(int)
                 for eid, sc in jscale.items()}
        for eid, st_ in steps.items():
            gam[eid] = gam[eid] * np.exp(st_ * JITTER_LEVEL_STEP)
        jkey = tuple(int(x) for st_ in steps.values() for x in st_)
    q = pr.after_sum()
    qmo_r = q0 = None                                  # the quantizer's moments over the analysed samples
    if q is not None:
        gam = dict(gam)
        h = record_hash(mean.y[burn:])
        gq, q0 = quantization_gamma(model, gam, mean.y[burn:], burn, jkey, h)
        qmo_r = quantizer_moments(model, mean.y[burn:], burn, h)
        gam[q.id] = gq
        if qmo is not None or (gq.shape[0] > 2 and not np.all(gq[2:] == gq[1:2])):
            # correlated: every view's prediction depends on this record's mean response, so its
            # cache key must too (a white error is the same for every record, and stays shared)
            jkey = (jkey, h, burn)
    corr = 5 * _transient(model) + 10
    # predicted variance of y_k: stationary part + the walk's growth (R_b,k = R_b,0 + k Q_b)
    st = pr.steady_state()
    walk_rate = np.broadcast_to(st.bias_var_rate * model.Ts, (model.p,))
    var_stat = st.var_y if st.var_y is not None else np.full(model.p, np.nan)
    if q is not None and st.var_y is not None:
        # the quantizer's part over this record (its steady state has the uniform step^2 / 12)
        var_stat = var_stat - st.contributions[q.id] + q0
    return _Predicted(gam=gam, gam_short={eid: g[:L_need] for eid, g in gam.items()}, mod=mod,
                      mod_ids=tuple(jscale or ()), jkey=jkey, qmo_r=qmo_r, corr=corr, var_stat=var_stat,
                      walk0=pr.walk_initial_var(), walk_rate=walk_rate, walk_ids=pr.walk_ids(),
                      lines=pr.tone_ids())


def _view_jobs(model, r: np.ndarray, ta: np.ndarray, s: dict, pp: _Predicted, level_at, burn: int) -> list:
    """The views of every output, as functions to call (they are independent)."""
    jobs = []
    gam, short, jkey = pp.gam, pp.gam_short, pp.jkey
    gam_stat = {eid: g for eid, g in gam.items() if eid not in pp.walk_ids}
    for j in range(model.p):
        rj = r[:, j]
        mj = None if pp.mod is None else LocalVariance(pp.mod[:, j], pp.mod_ids)
        qj = qk = None
        if pp.qmo_r is not None and pp.qmo_r.active[j] and np.mean(pp.qmo_r.var_y[:, j]) > 0:
            vm = np.mean(pp.qmo_r.var_y[:, j])
            qj = np.maximum(pp.qmo_r.var_y[:, j], 1e-9 * vm) / vm       # a window all on a level: not 0 / 0
            qk = pp.qmo_r.k4[:, j]
        g_long = sum(g[:, j] for g in gam.values())       # to the record's length: both views' spreads
        jobs += [lambda rj=rj, j=j, gl=g_long, mj=mj, qj=qj, qk=qk: variance_view(
                     rj, ta, short, j, s["window"], model, gam_long=gl, mod=mj, jkey=jkey, qmod=qj, qk4=qk),
                 lambda rj=rj, j=j, gl=g_long, mj=mj, qj=qj: acf_view(
                     rj, model.Ts, short, j, s["acf_segment"], s["max_lag"], model, gam_long=gl, jkey=jkey,
                     mod=mj, qmod=qj),
                 lambda rj=rj, j=j, mj=mj, qj=qj: psd_view(
                     rj, model.Ts, short, j, s["nperseg"], s["bins_per_decade"], model, mod=mj, jkey=jkey,
                     gam_fine=gam, line_ids=pp.lines, qmod=qj),
                 lambda rj=rj, j=j, mj=mj, qj=qj: allan_view(rj, model.Ts, gam, j, pp.corr, model, mod=mj,
                                                             jkey=jkey, qmod=qj)]
        if level_at[j]:
            jobs.append(lambda rj=rj, j=j: level_view(rj, ta, gam_stat, j, s["window"], burn, float(pp.var_stat[j]),
                                                      float(pp.walk0[j]), float(pp.walk_rate[j]), model, jkey=jkey))
    return jobs


def _run_views(jobs: list, size: int) -> list:
    """The views, in threads on a record of at least VIEW_THREADS_MIN values (their transforms and
    array arithmetic release the GIL)."""
    if size >= VIEW_THREADS_MIN and VIEW_THREADS > 1:
        return parallel.Pool().map(lambda f: f(), jobs, workers=VIEW_THREADS, processes=False)
    return [f() for f in jobs]


def _comparison(model, t, y, y_mean, y_sd, truth, views: list, revision: int, notes: list) -> Comparison:
    """The :class:`Comparison`: the views' errors (per view, the model error) and regions."""
    per_view = {}
    for name in VIEW_NAMES:
        errs = [v.error for v in views if v.name == name]
        if errs:
            per_view[name] = float(np.mean(errs))
    regions = [rg for v in views for rg in regions_of(v)]
    for rg in regions:
        rg.output_name = model.output_names[rg.output]
    return Comparison(model_name=model.name, model_source=model.source, revision=revision, Ts=model.Ts,
                      t=t, y=y, y_mean=y_mean, y_sd=y_sd, truth=truth, views=views, error=model_error(views),
                      error_per_view=per_view, regions=regions, notes=notes,
                      output_names=tuple(model.output_names), output_units=tuple(model.output_units),
                      model_effects={eid: e.param_dict() for eid, e in model.effects.items()})
