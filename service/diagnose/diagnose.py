"""`noiselab diagnose`: where the model fails, which physical effect is missing, fit it, repeat.

1. Localize: :func:`.compare.compare` of the recording with the user's model (views, flagged
   regions, the model error of DESIGN.md).
2. Rank: every effect of the catalogue is fitted as a candidate (added when absent, refitted when
   present with a wrong value, AR(1) in place of white actuator noise) and scored by Delta BIC
   (:mod:`.search`).
3. Add the best candidate when its Delta BIC exceeds :data:`.thresholds.THRESHOLD`, refit everything
   freed so far jointly, and repeat while something significant remains (``max_effects`` effects
   the model lacks; refitting one it has is not counted, :func:`_spent`). When
   nothing passes that threshold but the model error still exceeds :data:`ERROR_OK` (the views
   see the model fail), the best candidate is added if its likelihood-ratio test passes at 1 %
   family-wise over the candidates and it brings the model error down by a third (:func:`_by_error`).
4. Report: the model error before, after each step and at the end; each added effect with its
   fitted parameters (the model file's names), 95 % profile intervals, score and one sentence of
   evidence; the extended model file.
"""

from __future__ import annotations

import math
import threading
import time

import numpy as np

from .. import parallel
from ..model.effects import CATALOGUE
from ..model.effects.base import _g
from .closed_loop import mark_closed_loop, reach_sentence, scale_factor_reach
from .compare import auto_burn, check_samples, compare, transient_samples
from .data import Data
from .entries import candidate_entry, missing_entry, step_entry
from .intervals import interval_tasks, merge_intervals
from .lines import line_hz, lines_params, without_line
from .modes import ADD, REFIT, replacing
from .search import Search
from .thresholds import MAX_EFFECTS, THRESHOLD

ERROR_OK = 1.5            # a model error the views call explained
ERROR_FALL = 2.0 / 3.0    # ... and the fall an effect added on their word must bring
BY_ERROR_ALPHA = 0.01     # ... and the family-wise level of its likelihood-ratio test (see _by_error)


def _spent(accepted) -> int:
    """What the accepted steps took of ``max_effects``: the effects the model lacked (added, or put
    in the place of one it has). Refitting an effect the model already has (a value the user
    wrote wrong, or the first guess of a white noise once a quantizer takes its share) finds no
    new physics, so it is not counted: a budget spent on refits would stop a real sensor's
    diagnosis short of the effects it lacks."""
    return sum(1 for c in accepted if c.mode.kind != "refit")


def _step_cap(model, max_effects: int) -> int:
    """The most steps one diagnosis takes: ``max_effects`` additions and one refit of each effect
    of the user's model on top (a refit frees every value of the effect, so a second refit of the
    same effect is the joint refit's business, not a step's)."""
    return max_effects + len(model.effects)


def _prefer_replacements(S, cur, accepted, say):
    """Revisit additions that could have been replacements (AR(1) actuator noise beside the user's
    white actuator noise): with every effect now in, drop the replaceable effect when the data
    support the smaller model as well (Delta BIC within the tie margin; same free parameters)."""
    from ..model import ModelError
    from .thresholds import TIE

    for c in accepted:
        if c.mode != ADD:
            continue
        for rep in CATALOGUE[c.effect].fit.replaces:
            if rep not in cur.model.effects or rep in cur.free:
                continue
            try:
                alt = S.refit_all(type(cur)(cur.model.without_effect(rep), cur.free, 0.0), thorough=True)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                continue
            if 2 * (alt.loglik - cur.loglik) > -TIE:
                say(f"{c.effect} replaces {rep}: the data support the model without {rep} as well "
                    f"(2 Delta l = {2 * (alt.loglik - cur.loglik):.1f})")
                c.mode = replacing(rep)
                cur = alt
    return cur


def _exchange(S, cur, accepted, step_cands, say, n_alt: int = 5):
    """Revisit the greedy order: an effect added early can stand in for another while a third is
    still missing (a gain-like saturation for a scale factor that also scales the noise, while a
    bias is missing; a walk for a Gauss-Markov bias). With every effect now in, each added effect
    is exchanged for the best of the other candidates its step ranked near the top and found
    significant, when the whole
    model then fits better by more than the tie margin (in the units of ``Search.choice``: twice
    the log-likelihood gain less 2.71 per extra parameter) and the new effect is significant by itself (Delta BIC > THRESHOLD given the
    rest). Before that, a backward pass undoes the least needed addition or changed value while it
    is not significant given the others (a refitted process noise that stood in for a colored
    actuator noise before that was fitted; a walk added after a Gauss-Markov bias can make the bias
    redundant); after an exchange it runs again (a refit that stood beside the effect exchanged
    out may not be needed beside its replacement). A slow actuator AR(1) and a sensor bias follow
    the drift rule both ways (:meth:`.search.Search.drift_margin`): the bias stays unless the
    AR(1) beats it by that margin, and replaces the AR(1) unless beaten by it. The last step, with
    nothing changed since it, keeps its own decision: only its
    leaders (their joint thorough refits reused) are compared again, for the nonlinearity tie rule.
    Returns the fit and whether anything changed."""
    return _Exchange(S, cur, accepted, step_cands, say, n_alt).run()


class _Exchange:
    """The state of one :func:`_exchange`: the current fit, the accepted candidates (changed in
    place), the fits with one of them undone (per current fit)."""

    def __init__(self, S, cur, accepted, step_cands, say, n_alt: int):
        self.S, self.cur, self.accepted, self.step_cands, self.say, self.n_alt = S, cur, accepted, step_cands, say, n_alt
        self.swapped = False
        self.log_n = math.log(S.data.n_bic)
        self.step_of = {id(c): i for i, c in enumerate(accepted)}       # the step that ranked each addition
        self.undone: dict = {}          # (id(cur), id(c)) -> (cur, fit): cur kept so its id is not reused

    def run(self):
        self.backward()
        any_exchange = False
        for c in list(self.accepted):
            any_exchange |= self.exchange(c)
        if any_exchange:    # an effect the exchanged one needed may not be needed now
            self.backward()
        return self.cur, self.swapped

    def without(self, c):
        """The fit with ``c`` undone: an added effect removed, a refitted one back at the user's values
        (once per current fit: the backward pass and the exchange ask for the same ones)."""
        from .hypotheses import Fit
        S, cur = self.S, self.cur
        key = (id(cur), id(c))
        if key not in self.undone:
            free = {k: v for k, v in cur.free.items() if k != c.effect}
            if c.mode == REFIT:
                m = cur.model.with_params(c.effect, S.nominal.effects[c.effect].param_dict())
            elif c.mode.kind == "add" and CATALOGUE[c.effect].repeatable \
                    and len(cur.model.effects[c.effect].all_lines()) > 1:   # its line alone, the others kept
                m = cur.model.with_params(c.effect, without_line(cur.model.effects[c.effect], line_hz(c)))
                free = dict(cur.free)
            elif c.mode.replaces is not None:           # the user's effect back, at the user's values
                old = c.mode.replaces
                m = cur.model.without_effect(c.effect).with_effect(old, S.nominal.effects[old].param_dict())
            else:
                m = cur.model.without_effect(c.effect)
            self.undone[key] = (cur, S.refit_all(Fit(m, free, -math.inf), thorough=True))
        return self.undone[key][1]

    def backward(self):
        """While the least needed addition is not significant given the others, drop it."""
        from ..model import ModelError

        def try_without(c):
            try:
                return self.without(c)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                return None

        while True:
            cur, owns = self.cur, []
            todo = [c for c in self.accepted if c.effect in cur.model.effects
                    and not (c.mode.replaces is not None and c.mode.replaces in cur.model.effects)]
            for c, d in zip(todo, self.S._map(try_without, todo)):
                if d is not None:
                    self.undone.setdefault((id(cur), id(c)), (cur, d))    # kept here when a forked map computed it
                    owns.append((2 * (cur.loglik - d.loglik) - c.k * self.log_n, c, d))
            if not owns:
                break
            own, c, d = min(owns, key=lambda x: x[0])
            if own >= THRESHOLD:
                break
            what = {"refit": f"{c.effect} back at the model's values",
                    "replace": f"{c.mode.replaces} back in place of {c.effect}"}.get(c.mode.kind, c.effect)
            if CATALOGUE[c.effect].repeatable and c.mode.kind == "add":
                what = f"the line of {c.effect} at {_g(line_hz(c))} Hz"
            self.say(f"drop: {what} (Delta BIC {own:.1f} once the others are in)")
            self.accepted.remove(c)
            self.cur, self.swapped = d, True

    def alternatives(self, c) -> list:
        """The other candidates ``c``'s step found significant (one the data did not support then,
        with fewer effects in, is not a competing explanation of what c explains). For the last
        step, with nothing changed since, its own decision stands as it was taken: its leaders'
        joint thorough refits had exactly these effects free (those before it, and theirs), so are
        reused (the tie rule for a nonlinearity still applies); the others were passed over on
        their screens then, as now."""
        cur = self.cur
        alts = [a for a in self.step_cands[self.step_of[id(c)]][:self.n_alt + 1] if a.score >= THRESHOLD
                and not (a.mode not in (ADD, REFIT) or a.effect == c.effect or a.effect not in a.fit.model.effects
                        or (a.mode == ADD and a.effect in cur.model.effects) or a.effect in cur.free)]
        return [a for a in alts if a.full] if self.reuse(c) else alts

    def reuse(self, c) -> bool:
        return c is self.accepted[-1] and not self.swapped

    def exchange(self, c) -> bool:
        """Exchange added effect ``c`` for the best of :meth:`alternatives` that beats it by
        :meth:`margin`; whether it was."""
        from ..model import ModelError
        from .hypotheses import Fit
        from .search import exact_tie
        from .thresholds import CHIBAR2_95, TIE

        S, cur, say = self.S, self.cur, self.say
        i = self.accepted.index(c)
        if c.mode != ADD or c.effect not in cur.model.effects:
            return False
        try:        # everything else in, without c: c's own Delta BIC given the rest
            drop = self.without(c)
        except (ModelError, ValueError, np.linalg.LinAlgError):
            return False
        own = 2 * (cur.loglik - drop.loglik) - c.k * self.log_n
        reuse = self.reuse(c)
        alts = self.alternatives(c)

        def exchanged(a, drop=drop, reuse=reuse):
            if reuse:                   # a leader of the last step (the others were filtered out)
                return a.fit
            try:
                params = a.fit.model.effects[a.effect].param_dict()
                m = drop.model.with_params(a.effect, params) if a.mode == REFIT else \
                    drop.model.with_effect(a.effect, params)
                free = dict(drop.free)
                free[a.effect] = list(a.fit.free.get(a.effect, []))
                return S.refit_all(Fit(m, free, -math.inf), thorough=True)
            except (ModelError, ValueError, np.linalg.LinAlgError):
                return None

        trials = []
        for a, alt in zip(alts, S._map(exchanged, alts)):
            if alt is None:
                continue
            a_own = 2 * (alt.loglik - drop.loglik) - a.k * self.log_n
            gain = 2 * (alt.loglik - cur.loglik) - (a.k - c.k) * CHIBAR2_95    # Search.choice's units
            say(f"  exchange trial {c.effect} -> {a.effect}: {gain:.1f} (own Delta BIC {a_own:.1f})")
            if _vanished(alt.model.effects[a.effect]) or a_own < THRESHOLD:
                continue            # not significant by itself with the rest in
            if gain > self.margin(c, a, alt, gain) or (abs(gain) <= TIE and CATALOGUE[c.effect].clips
                                                       and not CATALOGUE[a.effect].clips and a.k <= c.k):
                # better; or as good and linear in place of a nonlinearity: a saturation or dead zone
                # that the data cannot tell from a gain (a two-level command) shows no clipping
                trials.append((gain, a, alt, a_own - own))
        if not trials:
            return False
        # the best; among equally good (identical spectra) the preferred mode, then chain order
        gains = {id(x[1]): x[0] for x in trials}
        lead = max(trials, key=lambda x: x[0])[1]
        gain, a, alt, d_bic = min((x for x in trials if exact_tie(x[1], lead, lambda c: gains[id(c)])),
                                  key=lambda x: (x[1].mode.exact_rank, CATALOGUE[x[1].effect].chain_order))
        say(f"exchange: {a.effect} in place of {c.effect} (2 Delta l - Delta k chi2 = {gain:+.1f}, "
            f"Delta BIC {d_bic:+.1f}, with everything else in)")
        a.score = float(c.score + d_bic)
        a.alternatives = [x for x in c.alternatives if x.effect != a.effect]
        if abs(gain) <= TIE:
            a.alternatives = [c] + a.alternatives
        self.accepted[i] = a
        self.step_of[id(a)] = self.step_of[id(c)]
        self.cur, self.swapped = alt, True
        return True

    def margin(self, c, a, alt, gain: float) -> float:
        """By how much ``a`` (fitted in ``alt``) must beat ``c`` (in the current fit) to take its
        place: the tie margin, or the drift rule's (``Effect.drift``) between a slow actuator noise
        and a sensor bias, or 0 between two sensor drifts."""
        from .search import drift
        from .thresholds import TIE

        S, say = self.S, self.say
        margin = TIE
        if drift(a.effect) == "actuator" and drift(c.effect) == "sensor":
            margin = S.drift_margin(alt, self.cur) or TIE      # a slow drift stays the sensor's bias
            if TIE < gain <= margin:
                say(f"  {c.effect} kept: a drift this slow through the plant's gain, and the AR(1)'s "
                    f"lead within {margin:.1f} (its spread)")
        elif drift(c.effect) == "actuator" and drift(a.effect) == "sensor":
            slow = S.drift_margin(self.cur, alt)               # ... and becomes it unless clearly worse
            if slow is not None:
                margin = -slow
                if -slow < gain <= TIE:
                    say(f"  {a.effect} for a drift this slow through the plant's gain: the AR(1)'s lead "
                        f"{-gain:+.1f} is within {slow:.1f} (its spread)")
        elif drift(c.effect) == "sensor" and drift(a.effect) == "sensor":
            # a walk and a Gauss-Markov bias are nested (the walk is the long-tau limit): the
            # units are the likelihood-ratio test of 1/tau > 0, which decides between them as a
            # step's ranking does (the better choice score), not the incumbent's margin. A
            # Gauss-Markov bias added while the sensor's white noise was still missing took a
            # tau of the record's length once it was in, and stayed though the walk then led
            # by 1.7 (pure walk records of bench_noise_density: model error 2.04 after)
            margin = 0.0
        return margin


def _vanished(eff) -> bool:
    """The effect's size parameters are all zero (a noise of std 0, a tone of amplitude 0, ...)."""
    sizes = [np.asarray(v, float) for k, v in eff.params.items() if k in ("std", "psd", "std_s", "amplitude", "error")]
    return bool(sizes) and all(not np.any(v) for v in sizes)


def _compare(S, model, t, y, u, burn, revision: int):
    """:func:`compare` as the diagnosis runs it on its record: the level view when it starts at
    rest; else, under a command, the mean state fitted where the analysis starts."""
    return compare(model, t, y, u, burn=burn, level=S.data.at_rest, free_start=not S.data.at_rest, revision=revision)


def _by_error(S, cur, accepted, steps, comps, step_models, max_effects, t, y, u, burn, say):
    """Nothing passes the Delta BIC threshold, but the views still see the model fail (model error
    above :data:`ERROR_OK`): the best candidate by :meth:`.search.Search.choice` is added when
    its likelihood-ratio test passes at :data:`BY_ERROR_ALPHA` (1 %) family-wise over the
    candidates offered (2 Delta l above the chi2_k point of 0.01 / m, m candidates: the best of
    m is being tested) and it takes the model error down to :data:`ERROR_FALL` of its value or
    less, or to a model the views call explained (a Gauss-Markov bias in the model at 4x its
    tau, 380 s at 2 ms: the refit to the right tau passed the test with 2 Delta l = 29 for 2
    parameters, Delta BIC 4.8, and took the error from 1.58 to 1.16, a fall of only 27 %, so
    nothing was reported). BIC asks ln n per parameter, and n counts samples: a slow drift's
    evidence grows with the record's length, not its sample rate, so on a fast-sampled record a
    Gauss-Markov bias that the Allan view shows 11x off (generated case 21: 2 Delta l = 20.8 for
    2 parameters, p < 1e-4) fell 1.7 short of Delta BIC 0. The views' error is the second
    witness the threshold's margin stands in for; a model the views call explained gets nothing
    this way. The views alone are not enough: on a short record their error spreads more than
    its formula says (null records of 60 s, two outputs: sd 0.42 against 0.17; 6 of 40 above
    1.5), and a per-candidate 5 % test let 2 of those 40 add an effect. So does a slow bias's:
    the truth of generated case 48 (a Gauss-Markov bias of tau 15 s in 380 s) reads 1.14 on
    average over 12 records, its ACF and Allan views 1.53, above 1.5 on 1 in 12; diagnosed
    against itself (nominal = truth) on one such record (error 1.59), a 5 % family-wise test let
    an AR(1) replace its white actuator noise (2 Delta l = 11.9, p = 0.03 over 12 candidates).
    The views' rule is a second chance after BIC refused, taken on records the views already
    single out, so its test is at 1 %."""
    from scipy import stats as sps

    while _spent(accepted) < max_effects and len(accepted) < _step_cap(S.nominal, max_effects) \
            and comps[-1].error > ERROR_OK:
        cands = S.candidates(cur, bar=-math.inf)       # every candidate ranked by the choice score
        if not cands:
            break
        c = cands[0]
        lr = 2.0 * (c.fit.loglik - cur.loglik)
        crit = float(sps.chi2.isf(BY_ERROR_ALPHA / len(cands), c.k))
        if lr <= crit:
            say(f"model error {comps[-1].error:.3g}, but no candidate passes the likelihood-ratio test "
                f"(best: {c.mode} {c.effect}, 2 Delta l = {lr:.1f} against {crit:.1f}, "
                f"{100 * BY_ERROR_ALPHA:g} % over {len(cands)} candidates)")
            break
        new = c.fit if c.full else S.refit_all(c.fit, thorough=True)
        cmp = _compare(S, new.model, t, y, u, burn, revision=len(comps))
        if cmp.error > max(ERROR_FALL * comps[-1].error, ERROR_OK):
            say(f"model error {comps[-1].error:.3g}; {c.mode} {c.effect} (Delta BIC {c.score:.1f}) would "
                f"leave it at {cmp.error:.3g}: not added")
            break
        say(f"step {len(steps) + 1}: {c.mode} {c.effect} on the views' word (Delta BIC {c.score:.1f}; "
            f"2 Delta l = {lr:.1f} against {crit:.1f}; model error {comps[-1].error:.3g} -> {cmp.error:.3g})")
        c.by_error = (float(comps[-1].error), float(cmp.error))
        cmp.model_name = f"+ {c.effect}"
        steps.append(step_entry(c, new.model, cmp.error, S.nominal.Ts))
        comps.append(cmp)
        step_models.append(new.model)
        accepted.append(c)
        cur = new
    return cur


def _replay(S, start, final, accepted):
    """The fits after each step, in order, each effect at its final parameters then refitted with
    those before it."""
    from .hypotheses import Fit

    cur, out = start, []
    for c in accepted:
        m = cur.model
        free = dict(cur.free)
        if c.mode.replaces is not None:
            rep = c.mode.replaces
            m = m.without_effect(rep)
            free.pop(rep, None)
        params = final.model.effects[c.effect].param_dict()
        if CATALOGUE[c.effect].repeatable and c.mode.kind == "add":
            # the lines found so far (this one first) and those the model had at the start
            hz = [line_hz(a) for a in accepted[:accepted.index(c) + 1] if a.effect == c.effect and a.mode.kind == "add"]
            own = start.model.effects.get(c.effect)
            params = lines_params(final.model.effects[c.effect], hz[::-1],
                                   [] if own is None else [float(np.max(f)) for _, f in own.all_lines()])
        m = m.with_params(c.effect, params) if c.effect in m.effects else m.with_effect(c.effect, params)
        free[c.effect] = list(c.fit.free.get(c.effect, []))
        cur = S.refit_all(Fit(m, free, float("-inf")))
        out.append(cur)
    return out


class _Counted:
    """The search's maps counted for a progress report: ``progress(label, done, total)`` (e.g.
    :class:`noiselab.progress.Steps`) hears, under the current :meth:`phase`'s label, every fit
    the phase's maps finish out of the fits they were given. The maps' items done in this process
    are counted as they finish (from worker threads too); a forked child's, when its results come
    back at the map's end."""

    def __init__(self, S, progress):
        self.progress = progress
        self.label, self.done, self.total = "", 0, 0
        self._lock = threading.Lock()
        self._map = S._map
        S._map = self.map                   # the search's own maps are counted too

    def phase(self, label: str, total: int | None = None) -> None:
        with self._lock:
            self.label, self.done, self.total = label, 0, 0
        self.progress(label, 0, total)

    def _tick(self, n: int, grow: int = 0) -> None:
        with self._lock:
            self.done += n
            self.total += grow
            label, done, total = self.label, self.done, self.total
        self.progress(label, done, total)

    def map(self, fn, items: list, cost=None) -> list:
        def counted(x):
            out = fn(x)
            self._tick(1)
            return out

        with self._lock:
            start = self.done
        self._tick(0, len(items))
        out = self._map(counted, items, cost=cost)
        with self._lock:
            missing = start + len(items) - self.done
        if missing > 0:                       # the forked child's items, whose ticks stayed there
            self._tick(missing)
        return out


def diagnose(model, t, y, u=None, *, at_rest: bool = True, max_effects: int = MAX_EFFECTS, log=None,
             compare_burn="auto", progress=None) -> dict:
    """Diagnose samples y (N, p) at t (N,) with the recorded command u (N, m) against ``model``.

    ``at_rest``: the record starts at rest at sample 0 (noiselab streams from seq 0). Returns
    the JSON-ready report (DESIGN.md fields ``error_before``, ``error_after``, ``missing``; see
    the README) plus ``model`` (the fitted model object) and ``before``/``after`` comparisons.
    ``progress``: None, or ``progress(label, done, total)`` told each phase of the search (its
    label: the starting fit, ``step i/K: candidates``, the exchanges, the intervals) and the fits
    it has finished of those it was given (:class:`_Counted`); called from worker threads too.
    """
    say = log or (lambda s: None)
    t0 = time.perf_counter()
    y, t = check_samples(model, t, y, u)       # bad input fails here, before any fitting
    u = None if u is None else np.asarray(u, float).reshape(len(u), -1)
    users = model
    model = model.replaying(u)
    k0 = 0 if at_rest else min(transient_samples(model), len(y) // 2)
    burn = auto_burn(at_rest, u) if compare_burn == "auto" else compare_burn
    data = Data(y, u, model.Ts, at_rest, k0)
    S = Search(model, data, log=say)
    mark_closed_loop(S, model, data, say)
    count = _Counted(S, progress) if progress is not None else None
    # the comparisons (before, after each step, after all) run beside the fits on long records
    # (:meth:`.search.Search.beside`): as one more item of the next candidate map where the maps
    # fork a second process (a process of its own would be a third on two cores), else in one more
    # thread (the candidate maps leave a core idle at their ends)
    bg = S
    try:
        before = _later(bg, lambda: _compare(S, model, t, y, u, burn, revision=0))
        try:
            return _given_back(_diagnose(model, t, y, u, S, data, before, burn, say, bg, max_effects, t0, count),
                               users, model)
        except Exception:
            # what the comparison found wrong with the input comes first (as when it ran first)
            exc = before.exception()
            if exc is not None:
                raise exc from None
            raise
    finally:
        S.pool.close()


def _later(bg, fn):
    """fn() beside the search's maps (``bg`` the :class:`.search.Search`:
    :meth:`~.search.Search.beside`), or now (None); .result() and .exception() in every case."""
    return bg.beside(fn) if bg is not None else parallel.now(fn)


def _same_model(a, b) -> bool:
    """The same model for compare(): its file's content (the name and description aside)."""
    if a is b:
        return True
    da, db = a.to_dict(), b.to_dict()
    for d in (da, db):
        d.pop("name", None)
        d.pop("description", None)
    return repr(da) == repr(db)


def _diagnose(model, t, y, u, S, data, before_f, burn, say, bg, max_effects, t0, count=None) -> dict:
    phase = count.phase if count is not None else (lambda label, total=None: None)
    phase("fitting the model's free parameters")
    cur = S.start()
    steps, accepted, first, comps, step_models = [], [], None, [None], [model]
    start, step_cands = cur, []
    pending = []                       # (step index, future comparison) not yet collected
    i = 0
    while _spent(accepted) < max_effects and i < _step_cap(model, max_effects):
        budget = max_effects + i - _spent(accepted)         # the last step if no further refit comes
        phase(f"step {i + 1}/{budget}: candidates")
        cands = S.candidates(cur)
        if first is None:
            first = cands
        say("candidates: " + "; ".join(f"{c.mode} {c.effect} {c.score:.1f}" for c in cands[:6]))
        if not cands or cands[0].score < THRESHOLD:
            break
        best = cands[0]
        step_cands.append(cands)
        # a leader's fit is already the joint thorough refit: not repeated
        phase(f"step {i + 1}/{budget}: refitting with {best.effect}")
        new = best.fit if best.full else S.refit_all(best.fit, thorough=True)
        pending.append((len(steps), _later(bg, lambda m=new.model, rev=len(comps):
                                            _compare(S, m, t, y, u, burn, revision=rev))))
        comps.append(None)
        steps.append(step_entry(best, new.model, None, model.Ts))
        accepted.append(best)
        step_models.append(new.model)
        say(f"step {len(steps)}: {best.mode} {best.effect} (Delta BIC {best.score:.1f})")
        cur = new
        i += 1
    phase("comparing the models with the data")
    before = before_f.result()
    comps[0] = before
    say(f"model error before: {before.error:.3g}")
    _collect(pending, steps, comps, say)
    phase("checking exchanges and replacements")
    cur, swapped = _exchange(S, cur, accepted, step_cands, say)
    if swapped:      # the steps again, in order, with the exchanged effects
        steps, comps, step_models = _replayed_steps(S, start, cur, accepted, before, model, t, y, u, burn)
    cur = _prefer_replacements(S, cur, accepted, say)
    cur = _by_error(S, cur, accepted, steps, comps, step_models, max_effects, t, y, u, burn, say)
    final = cur.model
    after_f = None
    if accepted and comps[-1] is not None and _same_model(final, step_models[-1]):
        after_f = _later(None, lambda c=comps[-1]: c)   # the last step's comparison is of this model (same revision)
    elif accepted:
        after_f = _later(bg, lambda: _compare(S, final, t, y, u, burn, revision=len(comps) - 1))
    missing = []
    # the profile-likelihood intervals of the effects found, concurrently on long records
    tasks = [(i, key, f) for i, c in enumerate(accepted) for key, f in interval_tasks(
        S.H, cur, c.effect, line_hz=line_hz(c) if CATALOGUE[c.effect].repeatable else None)]
    phase("profile intervals")
    res = S._map(lambda task: task[2](), tasks)
    ivs = [merge_intervals([(key, r) for (i, key, _), r in zip(tasks, res) if i == k]) for k in range(len(accepted))]
    for c, (iv_c, per_c) in zip(accepted, ivs):
        missing.append(missing_entry(c, iv_c, per_c, cur, model, data))
    phase("comparing the fitted model with the data")
    after = after_f.result() if accepted else before
    if accepted:
        after.model_name = f"fitted ({len(accepted)} added)"
        comps[-1] = after
    reach = scale_factor_reach(S, cur, data)
    if reach is not None:
        data.notes.append(reach_sentence(reach))
        say(data.notes[-1])
    fitted = cur.model
    if accepted:
        fitted.description = (model.description + "; " if model.description else "") + \
            "extended by noiselab diagnose: " + ", ".join(c.effect for c in accepted)
    out = {
        "error_before": float(before.error),
        "error_after": float(after.error),
        "missing": missing,
        "steps": steps,
        "candidates": [candidate_entry(c, model.Ts) for c in (first or [])[:10]],
        "regions": [r.__dict__ for r in before.regions],
        "samples": int(len(y)),
        "Ts": model.Ts,
        "threshold": THRESHOLD,
        "seconds": round(time.perf_counter() - t0, 3),
        "fitted_model": fitted.to_toml(),
        "model": fitted,
        "step_models": step_models,      # the model before any step, then after each step
        "before": before,
        "after": after,
        "comparisons": comps,
        "notes": data.notes,
        "feedback": data.feedback,         # a closed-loop record's test (:mod:`.closed_loop`), or None
        "fed_back": data.fed_back,
        "scale_factor_reach": reach,       # the least scale factor this closed-loop record shows, or None
    }
    return out


def _given_back(rep: dict, users, model) -> dict:
    """The report with the user's command back in its models (the replayed one is internal)."""
    if model is users:
        return rep
    cmd = users.to_dict()["command"]
    rep["model"] = rep["model"].with_command(cmd)
    rep["fitted_model"] = rep["model"].to_toml()
    rep["step_models"] = [m.with_command(cmd) for m in rep["step_models"]]
    return rep


def _replayed_steps(S, start, cur, accepted, before, model, t, y, u, burn) -> tuple[list, list, list]:
    """The steps, comparisons and step models again, in order, after an exchange (:func:`_replay`)."""
    steps, comps, step_models = [], [before], [model]
    for i, fit in enumerate(_replay(S, start, cur, accepted), 1):
        c = accepted[i - 1]
        cmp = _compare(S, fit.model, t, y, u, burn, revision=i)
        cmp.model_name = f"+ {c.effect}"
        comps.append(cmp)
        step_models.append(fit.model)
        steps.append(step_entry(c, fit.model, cmp.error, model.Ts))
    return steps, comps, step_models


def _collect(pending: list, steps: list, comps: list, say) -> None:
    """The steps' comparisons computed in the background (``pending``: (step index, future)) into
    ``comps`` and the steps' model errors."""
    for i, fut in pending:
        cmp = fut.result()
        cmp.model_name = f"+ {steps[i]['effect']}"
        comps[i + 1] = cmp
        steps[i]["error"] = float(cmp.error)
        say(f"step {i + 1}: model error {cmp.error:.3g}")
