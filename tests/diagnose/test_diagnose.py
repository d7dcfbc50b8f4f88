"""Diagnosis (issue 5): every hidden-effect scenario pair, null scenarios over many seeds, the lesson
case, generated cases like the independent set, and `noiselab diagnose` end to end (JSON, fitted
model file, .rrd read back, bad input). Every record has a fixed seed."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.closed_loop import controlled
from helpers.models import ENCODER_TOML
from helpers.rrd import column, read_chunks

from noiselab.diagnose.data import Data, quantization_grid
from noiselab.diagnose.diagnose import diagnose
from noiselab.diagnose.modes import ADD
from noiselab.diagnose.search import Search
from noiselab.diagnose.thresholds import THRESHOLD
from noiselab.model import load_model, parse_model
from noiselab.model.controller import closed_loop_poles
from noiselab.model.effects import CATALOGUE
from noiselab.model.model import scenario_names

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "bench"))
from hidden_set import make_case, make_closed_case, make_sensor_case, score_case  # noqa: E402

def _pairs(group: str) -> list[str]:
    return sorted(n.split("/")[1] for n in scenario_names(group) if not n.endswith("-nominal") and "/null-" not in n)


PAIRS = _pairs("hidden")
# the closed-loop pairs: a servo under its [controller] (PD, PI or PI-D, a reference none, step or
# sine), recorded offline as the live loop runs (simulate_closed_loop)
CLOSED_PAIRS = _pairs("hidden-closed")
NULLS = [n for n in scenario_names("hidden") if "/null-" in n]
CLOSED_NULLS = [n for n in scenario_names("hidden-closed") if "/null-" in n]
DURATION = 180.0


def cli(*args, timeout=600):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "noiselab.cli", *map(str, args)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def _record(model, seed, duration=DURATION):
    """The model's record of ``duration`` s: open loop, or under its ``[controller]``, the applied
    command recorded."""
    n = int(round(duration / model.Ts))
    if model.controller is not None:
        return controlled(model, n, seed)
    return model.simulate(n, seed=seed)


# -- the scenario pairs: one per effect of the catalogue -------------------------------------------------
@pytest.mark.parametrize("group", ["hidden", "hidden-closed"])
def test_a_pair_for_every_effect_of_the_catalogue(group):
    """Open loop and closed loop alike: a pair per effect, the truth the nominal plus that effect.
    A closed-loop pair's command is external and its controller's loop stable in both models."""
    pairs = _pairs(group)
    assert set(pairs) == set(CATALOGUE)
    for eid in pairs:
        truth, nominal = load_model(f"{group}/{eid}"), load_model(f"{group}/{eid}-nominal")
        assert eid in truth.effects and eid not in nominal.effects
        assert set(truth.effects) - set(nominal.effects) == {eid}
        if group == "hidden-closed":
            for m in (truth, nominal):
                assert m.command.kind == "external" and m.controller is not None
                assert np.max(np.abs(closed_loop_poles(m, m.controller))) < 1.0
    if group == "hidden-closed":
        ctl = [load_model(n).controller for n in scenario_names(group)]
        assert {(c.ki > 0, c.kd > 0) for c in ctl} == {(False, True), (True, False), (True, True)}   # PD, PI, PI-D
        assert {c.reference for c in ctl} == {"none", "step", "sine"}


def _value(v):
    return float(np.max(v)) if isinstance(v, list) else float(v)


JITTER_UNDER_A_NOISY_COMMAND = (
    "the jitter's std_s reads about 2 % low under a command that carries broadband noise (a closed loop's: "
    "z = (truth - estimate) / standard error 2.2, 0.4, 2.3, 2.1, 2.1, 1.6, 0.9 over seeds 11-17, against -0.5 on "
    "average in open loop under the pair's sine); the same record simulated open loop under a closed loop's "
    "command reads as low (z 1.3 on average), so it is not the feedback; without the process and actuator "
    "noise it does not (z 0.1), and the model's Var(ydot) of those noises is right (1.83e-3 against 1.84e-3 "
    "simulated): the interval (+-2 %) misses 0.001 by 0.3 %")


def _pair_params():
    out = [("hidden", e) for e in PAIRS]
    for e in CLOSED_PAIRS:
        marks = [pytest.mark.xfail(strict=True, reason=JITTER_UNDER_A_NOISY_COMMAND)] if e == "sensor.jitter" else []
        out.append(pytest.param("hidden-closed", e, marks=marks))
    return out


@pytest.mark.slow
@pytest.mark.parametrize("group,eid", _pair_params())
def test_hidden_effect_ranked_first_and_recovered(group, eid):
    """3 minutes of the truth model: the hidden effect is ranked first, each planted parameter is
    inside its 95 % interval and within 30 %, and the model error falls to about 1. A parameter
    that is a choice (the sensor filter's kind, a moving average's taps: the search tries each) is
    the planted one. The same acceptance in closed loop, where the record is also said to be one."""
    truth, nominal = load_model(f"{group}/{eid}"), load_model(f"{group}/{eid}-nominal")
    rec = _record(truth, seed=11)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    assert (rep["feedback"] is not None) == (group == "hidden-closed"), rep["notes"]
    assert rep["missing"], rep["candidates"][:3]
    first = rep["missing"][0]
    assert first["effect"] == eid, [(m["effect"], m["score"]) for m in rep["missing"]]
    assert first["score"] > THRESHOLD and first["evidence"]
    for k, v in truth.effects[eid].param_dict().items():
        if isinstance(v, str) or (isinstance(v, int) and not isinstance(v, bool)):
            assert first["params"][k] == v, (k, first["params"][k], v)
            continue
        got, (lo, hi) = _value(first["params"][k]), first["interval"][k]
        true = _value(v)
        assert abs(got / true - 1) <= 0.3, (k, got, true)
        # intervals of deterministic effects are narrow: allow the last digits of a float
        assert lo - 1e-9 * abs(true) <= true <= hi + 1e-9 * abs(true), (k, true, lo, hi)
    assert rep["error_after"] < rep["error_before"]
    assert rep["error_after"] <= 1.5


# -- null scenarios: nothing reported ------------------------------------------------------------------------
def _null_runs(names, seeds, duration):
    """Each null scenario of ``names`` diagnosed against itself over ``seeds`` (records of
    ``duration`` s): (the reports, what they reported first, the best candidate's score)."""
    reps, reported, worst = [], [], -np.inf
    for name in names:
        model = load_model(name)
        for seed in seeds:
            rec = _record(model, seed=seed, duration=duration)
            rep = diagnose(model, rec.t, rec.y, rec.u, max_effects=1)
            reps.append(rep)
            worst = max(worst, max((c["score"] for c in rep["candidates"]), default=-np.inf))
            if rep["missing"]:
                reported.append((name, seed, rep["missing"][0]["effect"], rep["missing"][0]["score"]))
    return reps, reported, worst


@pytest.mark.slow
def test_nothing_reported_on_null_scenarios_over_many_seeds():
    """12 seeds of each null scenario (2 minutes each): a false report in at most 5 % of them (at
    the threshold Delta BIC > 10 the expected rate is far below that)."""
    reps, reported, worst = _null_runs(NULLS, range(100, 112), 120.0)
    assert len(reported) <= 0.05 * len(reps), (reported, worst)


@pytest.mark.slow
def test_nothing_reported_on_closed_loop_null_scenarios():
    """7 seeds of each closed-loop null scenario (PD with no reference, PI-D with a sine, a stiffer
    PI-D with a step; 90 s each): a false report in at most 5 % of them, and each record is said
    to be closed-loop."""
    reps, reported, worst = _null_runs(CLOSED_NULLS, range(200, 207), 90.0)
    assert len(reps) == 21 and all(rep["feedback"] is not None for rep in reps)
    assert len(reported) <= 0.05 * len(reps), (reported, worst)


@pytest.mark.slow
def test_tone_frequency_interval_has_the_cramer_rao_width():
    """The tone pair's 50 Hz line over 60 records of 30 s: the frequency's error in units of its
    reported standard error (the interval's half width / 1.96) has mean square chi2_60 / 60 if the
    interval is right. Bounds: the 0.1 % and 99.9 % points, 0.55 and 1.66. The bound used to be
    half the Cramer-Rao variance (12 S / (A^2 N^3) for 24 S / ...; mean square 2) and a Whittle
    veto kept the frequency at its grid start in a quarter of the records."""
    from scipy.stats import chi2
    truth, nominal = load_model("hidden/sensor.tone"), load_model("hidden/sensor.tone-nominal")
    z = []
    for seed in range(60):
        rec = _record(truth, seed=500 + seed, duration=30.0)
        first = diagnose(nominal, rec.t, rec.y, rec.u, max_effects=1)["missing"][0]
        assert first["effect"] == "sensor.tone"
        lo, hi = first["interval"]["frequency_hz"]
        z.append((_value(first["params"]["frequency_hz"]) - 50.0) / ((hi - lo) / (2 * 1.96)))
    ms = float(np.mean(np.square(z)))
    assert chi2.ppf(0.001, 60) / 60 < ms < chi2.ppf(0.999, 60) / 60, (ms, z)
    assert sum(abs(v) < 1e-6 for v in z) <= 3          # on the grid value (50 Hz is a bin here): 5 of 20 before


@pytest.mark.slow
def test_lesson_case_finds_colored_actuator_noise_in_place_of_white():
    """Against the lesson's nominal model, the first effect is the AR(1) actuator noise that the
    nominal model treats as white; its std is recovered within its 95 % interval and 30 %."""
    rec = load_model("seed").simulate(30000, seed=21)
    rep = diagnose(load_model("seed-nominal"), rec.t, rec.y, rec.u, max_effects=1)
    first = rep["missing"][0]
    assert first["effect"] == "actuator.ar1" and first["mode"] == "replace:actuator.white"
    lo, hi = first["interval"]["std"]
    assert lo <= 0.08 <= hi and abs(first["params"]["std"] / 0.08 - 1) < 0.3
    assert rep["error_after"] < rep["error_before"] / 100


@pytest.mark.slow
def test_prefix_screening_finds_what_the_whole_record_screening_finds(monkeypatch):
    """Records of 2 SCREEN_N samples or more are screened on their first SCREEN_N samples, then
    scored and (the leaders) fitted on the whole record. With SCREEN_N lowered so that a 60,000
    sample seed record takes that path, the diagnosis adds the same effects with the same scores
    (the leaders' joint refits search every parameter from a coarse grid either way) and the
    same final model error."""
    import noiselab.diagnose.search as S
    rec = load_model("seed").simulate(60000, seed=22)
    nominal = load_model("seed-nominal")
    whole = diagnose(nominal, rec.t, rec.y, rec.u)
    monkeypatch.setattr(S, "SCREEN_N", 8192)
    screened_on = []
    init = S.Search.__init__

    def spy(self, *a, **k):
        init(self, *a, **k)
        screened_on.append(self.Hs.data.N)
    monkeypatch.setattr(S.Search, "__init__", spy)
    part = diagnose(nominal, rec.t, rec.y, rec.u)
    assert screened_on == [8193]
    assert [(m["effect"], m["mode"]) for m in part["missing"]] == [(m["effect"], m["mode"]) for m in whole["missing"]]
    assert [m["effect"] for m in whole["missing"]] == ["actuator.ar1", "sensor.bias_walk"]
    for a, b in zip(part["steps"], whole["steps"]):
        assert a["score"] == pytest.approx(b["score"], abs=0.5)
    assert part["error_after"] == pytest.approx(whole["error_after"], rel=0.02)


@pytest.mark.slow
def test_nested_choice_statistic_is_half_chi2_0_half_chi2_1():
    """Search.choice charges CHIBAR2_95 = 2.71 per extra parameter because, between nested effects
    (white actuator noise and its AR(1), white at rho = 0 on the edge of tau_s > 0), the likelihood
    ratio's null distribution is 1/2 chi2_0 + 1/2 chi2_1 (Self & Liang 1987), not chi2_1. Checked on
    records whose truth is white: about half give 2 Delta l = 0 (binomial sd 0.05 at 100 records:
    +-0.15), the positive ones follow chi2_1 (KS; chi2_2 would fail), and at most 5 % exceed
    2.71 (+3 binomial sd)."""
    from scipy import stats

    from noiselab.diagnose.hypotheses import Hypotheses
    from noiselab.diagnose.thresholds import CHIBAR2_95

    model = parse_model("name = \"w\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-2.0]]\nB = [[2.0]]\n"
                        "C = [[1.0]]\n[actuator.white]\nstd = 0.5\n[sensor.white]\nstd = 0.05\n")
    alt = model.without_effect("actuator.white").with_effect("actuator.ar1", {"std": 0.5, "tau_s": 0.05})
    R = 100
    lr = np.empty(R)
    for r in range(R):
        rec = model.simulate(1000, seed=r)
        H = Hypotheses(Data(rec.y, rec.u, model.Ts, True), model)
        white = H.fit(model, {"actuator.white": ["std"], "sensor.white": ["std"]})
        ar1 = H.fit(alt, {"actuator.ar1": ["std", "tau_s"], "sensor.white": ["std"]}, new=("actuator.ar1",))
        lr[r] = 2 * (ar1.loglik - white.loglik)
    at_zero = float(np.mean(lr < 0.01))
    assert abs(at_zero - 0.5) < 0.15, at_zero
    pos = lr[lr >= 0.01]
    assert stats.kstest(pos, stats.chi2(1).cdf).pvalue > 1e-3
    assert stats.kstest(pos, stats.chi2(2).cdf).pvalue < 1e-3
    tail = float(np.mean(lr > CHIBAR2_95))
    assert tail <= 0.05 + 3 * math.sqrt(0.05 * 0.95 / R), tail


def test_a_drift_slower_than_the_plant_is_reported_as_a_sensor_bias():
    """A Gauss-Markov sensor bias of tau 20 s under a plant of time constant 0.1 s: an actuator
    AR(1) of the same tau reaches the output through the plant's DC gain alone, so the two tie (on
    this record the AR(1) is ahead by 0.2 in the choice units, inside TIE). Colored actuator noise
    slower than SLOW_DRIFT plant time constants is reported as the sensor bias when both are
    near-tied additions (the better supported of it and the walk, its long-tau limit); the AR(1) stays the
    alternative."""
    from noiselab.diagnose.search import plant_time_constant
    from noiselab.diagnose.thresholds import SLOW_DRIFT, TIE

    base = ("name = \"d\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-10.0]]\nB = [[10.0]]\nC = [[1.0]]\n"
            "[command]\nkind = \"sine\"\namplitude = 1.0\nfrequency_hz = 0.5\n"
            "[process.white]\nstd = 0.5\n[sensor.white]\nstd = 0.02\n")
    nominal = parse_model(base)
    assert plant_time_constant(nominal) == pytest.approx(0.1, rel=1e-12)
    assert plant_time_constant(load_model("seed")) == pytest.approx(2 * 1.2 / 0.35, rel=1e-9)   # 2 m / c
    truth = parse_model(base + "[sensor.bias_markov]\nstd = 0.05\ntau_s = 20.0\n")
    rec = truth.simulate(30_000, seed=0)
    S = Search(nominal, Data(rec.y, rec.u, nominal.Ts, True))
    cands = S.candidates(S.start())
    ar1 = next(c for c in cands if c.effect == "actuator.ar1" and c.mode == ADD)
    first = cands[0]
    assert first.effect == "sensor.bias_markov" and first.score > THRESHOLD
    tau = ar1.fit.model.effects["actuator.ar1"].param_dict()["tau_s"]
    assert tau > SLOW_DRIFT * 0.1 and abs(ar1.sel - first.sel) < TIE and ar1.sel > first.sel
    assert "actuator.ar1" in [a.effect for a in first.alternatives]


@pytest.mark.slow
def test_lr_spread_is_the_spread_of_the_likelihood_ratio_over_records():
    """lr_spread (the model-based standard deviation of 2 (l_A - l_B) over records, data drawn from
    A's spectrum) against 4000 Monte Carlo periodograms: one output with groups of 1 and 8 bins
    (a group's mean of n exponential ordinates, G = n), and two outputs (X ~ CN(0, E_A) per bin,
    I = X X^H). The sd of a sample sd is sd / sqrt(2 R): 1.1 % here; tolerance 5 %."""
    from noiselab.diagnose.hypotheses import Fit
    from noiselab.diagnose.inner import Inner
    from noiselab.diagnose.sandwich import lr_spread

    rng = np.random.default_rng(3)
    R, nb = 4000, 60
    f = np.linspace(0.02, 0.5, nb)
    EA = 1.0 / (f**2 + 0.01) + 5.0
    EB = EA * (1.0 + 0.3 * np.sin(12 * f))
    for n in (1, 8):
        G = np.full(nb, float(n))
        fits = [Fit(None, {}, 0.0, inner=Inner(EA, G, E, []), v=np.zeros(0)) for E in (EA, EB)]
        I = EA * rng.gamma(n, 1.0 / n, size=(R, nb))
        lr = 2 * np.sum(G * (np.log(EB / EA) + I / EB - I / EA), axis=1)
        assert lr_spread(*fits) == pytest.approx(np.std(lr), rel=0.05)
    # two outputs: E_A = L L^H with a complex cross term, E_B another Hermitian PD matrix
    L = np.zeros((nb, 2, 2), complex)
    L[:, 0, 0], L[:, 1, 1], L[:, 1, 0] = np.sqrt(EA), 1.0 + f, 0.7 * np.sqrt(EA) * np.exp(1j * 3 * f)
    EA2 = L @ np.conj(L.transpose(0, 2, 1))
    EB2 = EA2.copy()
    EB2[:, 0, 0] *= 1.4
    EB2[:, 1, 1] *= 0.8 + f
    G = np.ones(nb)
    X = np.einsum("bij,rbj->rbi", L, (rng.standard_normal((R, nb, 2)) + 1j * rng.standard_normal((R, nb, 2))) / np.sqrt(2))
    I2 = np.einsum("rbi,rbj->rbij", X, np.conj(X))
    fits = [Fit(None, {}, 0.0, inner=Inner(I2[0], G, E, []), v=np.zeros(0)) for E in (EA2, EB2)]

    def ll(E):
        Ei = np.linalg.inv(E)
        return -np.sum(np.linalg.slogdet(E)[1] + np.einsum("bij,rbji->rb", Ei, I2).real, axis=1)

    lr = 2 * (ll(EA2) - ll(EB2))
    assert lr_spread(*fits) == pytest.approx(np.std(lr), rel=0.05)
    # fits of different residuals (a mean effect moved one) are not compared
    other = Fit(None, {}, 0.0, inner=Inner(EA * 1.01, np.ones(nb), EB, []), v=np.zeros(0))
    assert lr_spread(Fit(None, {}, 0.0, inner=Inner(EA, np.ones(nb), EA, []), v=np.zeros(0)), other) is None


def _diagnose_hidden(truth, hidden: tuple, n: int, seed: int):
    """A record of ``truth`` (n samples, ``seed``) diagnosed against ``truth`` without the
    ``hidden`` effects: the report and the log lines."""
    nominal = truth
    for eid in hidden:
        nominal = nominal.without_effect(eid)
    rec = truth.simulate(n, seed=seed)
    logs = []
    return diagnose(nominal, rec.t, rec.y, rec.u, log=logs.append), logs


def test_a_constant_command_from_rest_is_a_step():
    """A record from rest whose command is constant and not zero (the default step, time_s = 0) has
    a command: the plant steps at t = 0, so the mean effects (lag, saturation, dead zone, scale
    factor) are candidates. A command that is zero throughout, or constant in a record that does
    not start at rest, has none."""
    y = np.zeros((400, 1))
    assert Data(y, np.ones((400, 1)), 0.01, True).has_command
    assert not Data(y, np.ones((400, 1)), 0.01, False).has_command
    assert not Data(y, np.zeros((400, 1)), 0.01, True).has_command
    assert not Data(y, None, 0.01, True).has_command
    u = np.zeros((400, 1))
    u[200:] = 1.0
    assert Data(y, u, 0.01, False).has_command


def test_a_saturation_under_a_step_at_t0_is_found_in_the_taper_ramp():
    """Generated case 15's truth (a first-order plant, a saturation at 0.787) under a unit step at
    t = 0 from rest: the mean response differs from the nominal's only in its first second, where
    the periodogram's taper weighs the record down to nothing; before the ramps' term
    (:class:`.whittle.Ramps`) no mean effect scored at all. Now the saturation is found at its
    limit, inside its interval, and the model error, which before the level view read the same
    with and without it (1.23), falls from 30 to 1.4."""
    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.02\n[plant]\nA = [[-4.882280066997175]]\n"
                        "B = [[2.9884213620332103]]\nC = [[1.0]]\nL = [[4.882280066997175]]\n"
                        "[command]\nkind = \"step\"\namplitude = 1.0\ntime_s = 0.0\n"
                        "[process.white]\nstd = 0.316\n[sensor.white]\nstd = 0.03821\n"
                        "[actuator.saturation]\nlimit = 0.7867\n")
    rep, logs = _diagnose_hidden(truth, ("actuator.saturation",), 25_000, 1015)
    assert [m["effect"] for m in rep["missing"]] == ["actuator.saturation"]
    sat = rep["missing"][0]
    assert sat["score"] >= THRESHOLD and sat["accepted_by"] == "bic"
    lo, hi = sat["interval"]["limit"]
    assert lo <= 0.7867 <= hi and abs(sat["params"]["limit"] / 0.7867 - 1) < 0.1
    # the level view sees the steady-state error that every other view removes with its means
    assert rep["before"].error_per_view["level"] > 10 * max(
        v for k, v in rep["before"].error_per_view.items() if k != "level")
    assert rep["error_before"] > 10 and rep["error_after"] <= 1.5


AR1_SAT = ("name = \"ar1sat\"\n[sampling]\nTs = 0.005\n[plant]\nA = [[0.0, 1.0], [-16.0, -2.0]]\n"
           "B = [[0.0], [16.0]]\nC = [[1.0, 0.0]]\nL = [[0.0], [4.0]]\n[command]\nkind = \"chirp\"\n"
           "amplitude = 0.8\nf0_hz = 0.1\nf1_hz = 3.0\nduration_s = 25\n[process.white]\nstd = 0.2\n"
           "[actuator.ar1]\nstd = 0.05\nrho = 0.98\n[actuator.saturation]\nlimit = 0.7\n[sensor.white]\nstd = 0.002\n")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 3])
def test_an_ar1_actuator_noise_behind_a_saturation_the_chirp_reaches_is_found_and_nothing_else(seed):
    """AR(1) actuator noise (tau 0.25 s) through a saturation a chirp (0.1-3 Hz) reaches a third of
    the time: the clipper's gain switches within the noise's correlation time, which widens the
    clipped noise's spectrum (``Predictor._gain_shadows``). Hidden from the nominal model, the
    AR(1) is found alone, std and tau within 30 %, tau within its interval; diagnosed against
    the truth itself, the record shows nothing. Before the gain's spectrum was modelled (rms gain
    on the AR(1)'s own spectrum) these records gave tau -32 % (seed 1) and a process-noise refit
    beside the AR(1) at Delta BIC 17 (seed 3), and against the truth process noise refitted at
    Delta BIC 72 (seed 3).

    The clipped noise is cyclostationary (its power follows the chirp): its periodogram spreads
    more than the stationary Whittle likelihood assumes, and the std's profile interval is widened
    by its sandwich factor (:func:`sandwich.godambe_factor`, as the jitter's). Without it seed 3's
    interval was (0.0506, 0.0563), and over seeds 20-39 16 of 20 held 0.05 (mean square z 1.50);
    with it seed 3's is (0.0497, 0.0556) and 18 of 20 hold it (mean square z 1.16)."""
    truth = parse_model(AR1_SAT, "ar1sat")
    rec = truth.simulate(30_000, seed=seed)
    rep = diagnose(truth.without_effect("actuator.ar1"), rec.t, rec.y, rec.u)
    assert [m["effect"] for m in rep["missing"]] == ["actuator.ar1"], rep["missing"]
    got, iv = rep["missing"][0]["params"], rep["missing"][0]["interval"]
    want = {"std": 0.05, "tau_s": -0.005 / math.log(0.98)}
    for k, v in want.items():
        assert abs(got[k] / v - 1) < 0.3, (k, got[k])
    for k in ("std", "tau_s"):
        assert iv[k][0] < want[k] < iv[k][1], (k, iv)
    assert rep["error_after"] < 1.5
    null = diagnose(truth, rec.t, rec.y, rec.u)
    assert null["missing"] == [] and max(c["score"] for c in null["candidates"]) < THRESHOLD, \
        [(c["effect"], c["score"]) for c in null["candidates"][:3]]


@pytest.mark.slow
def test_the_sandwich_factor_of_a_noise_behind_a_switching_saturation_is_its_monte_carlo_spread():
    """White actuator noise (std 0.1) through a saturation at 0.5 that a sine of amplitude 1 reaches
    two thirds of the time: the noise reaches the plant modulated by the switching gain, and over
    300 records (seeds 100-399) its fitted variance spreads by 1.84x the stationary likelihood's
    (H^-1)_aa. The sandwich factor, read from each record's own score, is that ratio: its mean
    within 3 standard errors of the Monte Carlo ratio (whose relative standard error is
    sqrt(2 / (R - 1)), 8 %). Measured: 2.10 against 1.84 +- 0.15. (With a sensor noise of 1e-4,
    near the edge of what the data identify, the factor read 2.9 against 1.8: the sensor's
    variance, its cross-term in H^-1, carries a slow record-wide pattern the blocks miss.) The same
    plant with the limit at 2 never clips: not gated, no factor."""
    from noiselab.diagnose.hypotheses import Hypotheses
    from noiselab.diagnose.sandwich import gated, godambe_factor

    text = ("name = \"g\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-2.0]]\nB = [[2.0]]\nC = [[1.0]]\n[command]\n"
            "kind = \"sine\"\namplitude = 1.0\nfrequency_hz = 0.2\n[actuator.white]\nstd = 0.1\n"
            "[actuator.saturation]\nlimit = {}\n[sensor.white]\nstd = 0.002\n")
    model = parse_model(text.format(0.5), "g")
    R = 300
    v, model_var, factor = np.empty(R), np.empty(R), np.empty(R)
    for r in range(R):
        rec = model.simulate(20_000, seed=100 + r)
        H = Hypotheses(Data(rec.y, rec.u, model.Ts, True), model)
        if r == 0:
            assert gated(model, "actuator.white", H.data) and not gated(model, "sensor.white", H.data)
            assert not gated(parse_model(text.format(2.0), "g"), "actuator.white", H.data)
        fit = H.fit(model, {"actuator.white": ["std"], "sensor.white": ["std"]})
        a = fit.scale_ids.index("actuator.white")
        v[r] = fit.v[a]
        model_var[r] = np.linalg.inv(fit.inner._info(fit.v))[a, a]
        factor[r] = godambe_factor(H, fit, a)
    ratio = np.var(v, ddof=1) / np.mean(model_var)
    se = ratio * math.sqrt(2.0 / (R - 1))
    assert ratio > 1 + 3 * se, (ratio, se)          # the stationary likelihood's interval is too narrow
    assert abs(np.mean(factor) - ratio) < 3 * se, (np.mean(factor), ratio, se)


def test_a_noise_behind_a_saturation_that_clips_the_whole_record_is_held_not_run_up():
    """A PRBS of +-1 through a saturation at 0.5 clips every sample: the AR(1) actuator noise behind
    it reaches nothing (its gain is 0 throughout, or rounding of 1e-68), so these data cannot see
    its variance. Its fit holds it at the model's value, with no RuntimeWarning on the way. Two-input
    bench case 21 ran such a trial when the diagnosis tried a saturation below its PRBS's level: the
    variance went to the bound 1e294 (std 1e147 times the model's), the 2 x 2 determinants overflowed
    and the likelihood turned NaN, and the gain's fluctuation (1e-136) underflowed its spectrum fit,
    each printing a RuntimeWarning; sensor and process noise are fitted as before."""
    import warnings

    from noiselab.diagnose.hypotheses import Hypotheses

    model = parse_model("name = \"clip\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[0.0, 1.0], [-16.0, -2.0]]\n"
                        "B = [[0.0], [16.0]]\nC = [[1.0, 0.0]]\nL = [[0.0], [4.0]]\n[command]\nkind = \"prbs\"\n"
                        "amplitude = 1.0\nbit_s = 0.5\norder = 9\n[process.white]\nstd = 0.2\n[actuator.ar1]\n"
                        "std = 0.05\ntau_s = 0.2\n[actuator.saturation]\nlimit = 0.5\n[sensor.white]\nstd = 0.002\n", "clip")
    rec = model.simulate(20_000, seed=4)
    H = Hypotheses(Data(rec.y, rec.u, model.Ts, True), model)
    free = {"actuator.ar1": ["std"], "process.white": ["std"], "sensor.white": ["std"]}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit = H.inner_fit(model, free)
        low = H.inner_fit(model.with_effect("actuator.ar1", {"std": 0.01, "tau_s": 0.2}), free)
    assert math.isfinite(fit.loglik) and fit.loglik == pytest.approx(low.loglik, abs=1e-6)
    assert fit.model.effects["actuator.ar1"].params["std"] == pytest.approx(0.05, rel=1e-9)
    assert low.model.effects["actuator.ar1"].params["std"] == pytest.approx(0.01, rel=1e-9)
    # the noises the data see: within 5 standard errors of their truth (20000 samples: 1-2 %)
    assert fit.model.effects["process.white"].params["std"] == pytest.approx(0.2, rel=0.1)
    assert fit.model.effects["sensor.white"].params["std"] == pytest.approx(0.002, rel=0.1)


TWO_OUTPUTS_SCALE = ("name = \"dev\"\n[sampling]\nTs = 0.005\n[plant]\nA = [[0.0, 1.0], [-16.0, -2.0]]\n"
                     "B = [[0.0], [16.0]]\nC = [[1.0, 0.0], [0.0, 0.25]]\nL = [[0.0], [4.0]]\n[command]\n"
                     "kind = \"sine\"\namplitude = 0.8\nfrequency_hz = 0.5\n[process.white]\nstd = 0.2\n"
                     "[sensor.white]\nstd = [0.002, 0.004]\n[sensor.scale_factor]\nerror = [0.1, -0.05]\n")
TWO_INPUTS_LIMIT = ("name = \"dev\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-1.0, 0.5], [0.0, -3.0]]\n"
                    "B = [[1.0, 0.0], [0.0, 2.0]]\nC = [[1.0, 1.0]]\nD = [[0.0, 0.1]]\n[command]\nkind = \"sine\"\n"
                    "amplitude = [1.0, 0.5]\nfrequency_hz = 0.3\n[process.white]\nstd = [0.1, 0.2]\n"
                    "[sensor.white]\nstd = 0.003\n[actuator.saturation]\nlimit = [0.8, 0.4]\n")


@pytest.mark.slow
@pytest.mark.parametrize("text,eid,name,want", [
    (TWO_OUTPUTS_SCALE, "sensor.scale_factor", "error", [0.1, -0.05]),
    (TWO_INPUTS_LIMIT, "actuator.saturation", "limit", [0.8, 0.4]),
], ids=["scale factor per output", "saturation limit per input"])
def test_a_mean_effects_value_per_channel_is_fitted_per_channel(text, eid, name, want):
    """A mean effect with one value per channel (a scale factor of +10 % on a position sensor and
    -5 % on a velocity sensor; saturation limits of 0.8 and 0.4 on two inputs whose commands
    reach 1.0 and 0.5), hidden (the audit's models, 120 s, seed 5). One value for all channels
    cannot fit them: the scale factor's record read error 1.1e5 -> 1.2 with an AR(1) added first
    and a spurious dead zone, the limits 0.703 with a lag and an AR(1) beside them. Fitted per
    channel (each limit over its own input's command range; the scale factor from each output's
    least-squares factor), the effect comes first and alone, each channel's value within 30 %,
    and the model error falls to about 1. The interval (the larger channel's, the other channel
    re-fitted along its profile) holds the truth: the two limits trade off through the one output;
    the two outputs' noise is coherent (both are the plant's one state), so their scale factors'
    ratio is known far better than either. The profile's re-fit of the other channel was a few
    golden steps in a bracket of 1/40 of the range, so it stayed put: the scale factor read 0.0992
    in (0.09913, 0.09930) when its least-squares estimate's spread over 30 records is 0.00056; now
    (0.0976, 0.1002), and over seeds 0-4 each interval holds 0.1 (width 0.0025-0.0028)."""
    truth = parse_model(text, "dev")
    rec = truth.simulate(int(round(120 / truth.Ts)), seed=5)
    rep = diagnose(truth.without_effect(eid), rec.t, rec.y, rec.u)
    assert [m["effect"] for m in rep["missing"]] == [eid], [(m["effect"], m["params"]) for m in rep["missing"]]
    got = rep["missing"][0]["params"][name]
    assert isinstance(got, list) and len(got) == 2, got
    for g, v in zip(got, want):
        assert abs(g / v - 1) < 0.3, (got, want)
    lo, hi = rep["missing"][0]["interval"][name]
    assert lo < want[0] < hi, (lo, hi)              # the largest channel's interval
    assert rep["error_after"] < 1.5 < rep["error_before"]


@pytest.mark.slow
def test_a_saturations_limit_under_a_step_is_fitted_to_the_records_level():
    """A mass-spring-damper (k = 4) stepped to 2 at t = 0 with its input clipped at 1.5, 120 s
    from rest (``tests/bench/bench_step_level.py``, seed 2). After the transient the plant input
    is the limit, so the output's level is limit / k: the record's mean pins the limit to
    k sqrt(V), V the mean's predicted variance (:func:`.whittle.level_density` of the truth).
    Differencing takes that level out of the Whittle likelihood; before the level entered the
    mean effects' fit (``Fit.level``) the interval was 12x wider (about +-8 %), the estimates
    spread 10x wider than the level's, and the model error after stayed above 1.5 in half the
    seeds. The 95 % interval must cover 1.5 and be no wider than 1.5 x 1.96 k sqrt(V) each side
    (the transient adds a little; nothing else informs the limit)."""
    from noiselab.diagnose import whittle as W
    base = ("name = \"stepsat\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 0.5\nk = 4.0\n"
            "[command]\nkind = \"step\"\namplitude = 2.0\n"
            "[process.white]\nstd = 0.5\n[sensor.white]\nstd = 0.002\n")
    truth = parse_model(base + "[actuator.saturation]\nlimit = 1.5\n")
    rep, _ = _diagnose_hidden(truth, ("actuator.saturation",), 12000, 2)
    assert [m["effect"] for m in rep["missing"]] == ["actuator.saturation"]
    lo, hi = rep["missing"][0]["interval"]["limit"]
    sd = 4.0 * math.sqrt(W.level_density(parse_model(base), 12000)[0][0, 0])
    assert lo <= 1.5 <= hi
    assert (hi - lo) / 2 <= 1.5 * 1.96 * sd, (lo, hi, sd)
    assert rep["error_after"] <= 1.5


def test_the_ramps_whitener_whitens():
    """The ramps' whitener (cepstral minimum phase of a Welch spectrum) turns a differenced AR(2)
    resonance plus white noise into white noise: lag-1..10 autocorrelations of the whitened series
    within 4 / sqrt(n) of zero (they are 0.3-0.9 before), and its spectrum flat where the input's
    spans four decades."""
    from scipy.signal import lfilter, welch

    from noiselab.diagnose.whittle import Ramps

    rng = np.random.default_rng(7)
    n = 200_000
    x = lfilter([1.0], [1.0, -1.8, 0.9], rng.standard_normal(n + 1)) + 0.5 * rng.standard_normal(n + 1)
    d = np.diff(x)[:, None]
    h = Ramps(d, True).h[0]
    e = lfilter(h, [1.0], d[:, 0])[h.size:]

    def acf(z, k):
        z = z - z.mean()
        return float(z[k:] @ z[:-k] / (z @ z))

    assert max(abs(acf(d[:, 0], k)) for k in range(1, 11)) > 0.3
    assert max(abs(acf(e, k)) for k in range(1, 11)) < 4 / math.sqrt(e.size)
    assert h[0] == 1.0
    # flat within 10 % in octave bands above the lowest 4 of 4097 bins (where the floor holds the
    # whitener's gain), while the input's band powers span four decades there
    S, Sd = welch(e, nperseg=8192)[1], welch(d[:, 0], nperseg=8192)[1]
    bands = [(4, 8), (8, 16), (16, 64), (64, 256), (256, 1024), (1024, 4097)]
    assert max(Sd[a:b].mean() for a, b in bands) > 1e3 * min(Sd[a:b].mean() for a, b in bands)
    assert all(abs(S[a:b].mean() / S.mean() - 1) < 0.1 for a, b in bands)


@pytest.mark.slow
def test_a_drift_the_views_see_is_added_when_bic_alone_would_stop():
    """Generated case 21 (an actuator AR(1) and a Gauss-Markov bias of tau 18 s hidden; Ts 5 ms,
    390 s): after the AR(1) the bias scored Delta BIC -1.5 (2 Delta l = 21 for 2 parameters, but
    ln n = 11.3 each), and the search stopped with the model error at 1.84, the Allan view 11x
    off. The views' rule adds the best candidate when the error stays above ERROR_OK, its
    likelihood-ratio test passes at 1 % family-wise over the candidates, and the error falls by a
    third with it: the bias, at its planted tau."""
    from noiselab.diagnose.diagnose import ERROR_FALL, ERROR_OK

    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.005\n[plant]\nA = [[-1.0936947349271349]]\n"
                        "B = [[0.7904620537341346]]\nC = [[1.0]]\nL = [[1.0936947349271349]]\n"
                        "[command]\nkind = \"prbs\"\namplitude = 1.9373996680487635\nbit_s = 1.4362\norder = 9\n"
                        "[process.white]\nstd = 0.3011\n[sensor.white]\nstd = 0.009348\n"
                        "[sensor.bias_markov]\nstd = 0.01484\ntau_s = 17.96\n[actuator.ar1]\nstd = 0.06944\ntau_s = 0.2019\n")
    rep, logs = _diagnose_hidden(truth, ("sensor.bias_markov", "actuator.ar1"), 78_000, 1021)
    assert [m["effect"] for m in rep["missing"]] == ["actuator.ar1", "sensor.bias_markov"]
    ar1, bias = rep["missing"]
    assert ar1["accepted_by"] == "bic" and ar1["score"] >= THRESHOLD
    assert bias["accepted_by"] == "error" and bias["score"] < THRESHOLD and "views' word" in bias["evidence"]
    assert abs(bias["params"]["tau_s"] / 17.96 - 1) < 0.3 and abs(bias["params"]["std"] / 0.01484 - 1) < 0.3
    e1, e2 = rep["steps"][0]["error"], rep["steps"][1]["error"]
    assert e1 > ERROR_OK and e2 <= ERROR_FALL * e1 and rep["error_after"] <= ERROR_OK
    assert [s["accepted_by"] for s in rep["steps"]] == ["bic", "error"]


def test_a_tone_must_stand_out_from_the_data_around_it():
    """tone_peaks offers a bin only where it stands out from the model (P < 1e-3 over all bins)
    and from the data's own spectrum around it. A missing walk (flat in the differenced residual,
    where the model's noises rise as f^2 from DC) lifts the lowest bins far over the model, but
    they are no line; a line at bin 400 is one. Periodograms drawn as E_true Exp(1), seeded."""
    from noiselab.diagnose.tones import tone_peaks

    rng = np.random.default_rng(7)
    nf, M, Ts = 20_000, 40_000, 0.01
    k = np.arange(nf, dtype=float)
    E_model = 1e-3 * (2 * np.sin(np.pi * k / M)) ** 2 * 1e6 + 1e-6     # differenced stationary noise
    E_true = E_model + 0.05                                            # ... and a walk, white here
    I = (E_true * rng.exponential(size=nf))[:, None]
    ratio = I[:, 0] / E_model
    assert ratio[1:4].max() > math.log(nf / 1e-3)           # the walk's lowest bins pass the model test
    assert tone_peaks(I, E_model[:, None], M, Ts) == []
    I_line = I.copy()
    I_line[400, 0] = 200 * E_true[400]
    assert tone_peaks(I_line, E_model[:, None], M, Ts) == [(0, 400 / (M * Ts))]


def test_a_bias_walk_is_not_taken_for_a_tone_of_one_cycle():
    """Generated case 47, its fifth record (a bias walk hidden; 470 s at 2 ms): the walk's lowest
    bins, far over a model without it, gave a "tone" at 0.0025 Hz (1.2 cycles in the record),
    whose 3 parameters fitted the drift better than the walk's 1 (choice score 55.9 against
    46.3). It is the walk now. (Its std is not checked: this walk is weak beside the other noises
    and its estimate spreads widely, 0.0026-0.0066 over six records for 0.0045 planted.)"""
    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.002\n[plant]\nA = [[-2.977615660718576]]\n"
                        "B = [[2.2609410120794426]]\nC = [[1.0]]\nL = [[2.977615660718576]]\n"
                        "[command]\nkind = \"sine\"\namplitude = 1.2697191358782347\nfrequency_hz = 0.2441\n"
                        "[process.white]\nstd = 1.138\n[sensor.white]\nstd = 0.03396\n"
                        "[sensor.bias_walk]\nstd = 0.004469\n")
    rep, logs = _diagnose_hidden(truth, ("sensor.bias_walk",), 235_000, 1047 + 7919 * 4)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.bias_walk"]
    assert rep["error_after"] <= 1.5 and rep["error_after"] < rep["error_before"]


def test_a_bias_walks_evidence_names_the_band_where_it_dominates():
    """The walk's evidence says below which frequency it holds most of the differenced residual's
    power: there its increments (white, s^2 Ts per sample) exceed the differenced sensor noise's
    2 sigma_v^2 (1 - cos 2 pi f Ts), so f_c = arccos(1 - s^2 Ts / (2 sigma_v^2)) / (2 pi Ts), from
    the reported values (the process noise is 1e-3 of the sensor noise's power there). The
    sentence took its band from the parts at their scaling references (the walk at unit std,
    "below 49.8 Hz", the Nyquist frequency) before their fitted factors were applied."""
    truth = parse_model("name = \"w\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-1.0]]\nB = [[1.0]]\n"
                        "C = [[1.0]]\n[command]\nkind = \"sine\"\namplitude = 0.5\nfrequency_hz = 0.2\n"
                        "[process.white]\nstd = 0.001\n[sensor.white]\nstd = 0.01\n"
                        "[sensor.bias_walk]\nstd = 0.003\n")
    rep, _ = _diagnose_hidden(truth, ("sensor.bias_walk",), 30_000, 5)
    walk = [m for m in rep["missing"] if m["effect"] == "sensor.bias_walk"]
    assert walk, rep["missing"]
    fitted = parse_model(rep["fitted_model"], "fitted")
    s, sv, Ts = walk[0]["params"]["std"], float(np.max(fitted.effects["sensor.white"].params["std"])), 0.01
    f_c = math.acos(1.0 - s**2 * Ts / (2.0 * sv**2)) / (2.0 * math.pi * Ts)
    edge = float(walk[0]["evidence"].split("below ", 1)[1].split(" Hz", 1)[0])
    # the edge is the centre of the last group the walk dominates: groups at most 1 % of f wide
    assert abs(edge - f_c) <= 0.02 * f_c + 1.0 / (30_000 * Ts), (edge, f_c)


@pytest.mark.slow
def test_a_wrong_tau_that_the_views_see_is_refitted_when_the_fall_reaches_explained():
    """Generated case 48 with its Gauss-Markov bias in the model at 4x its tau (60.9 s for 15.2 s;
    Ts 2 ms, 380 s): the refit to the right tau passes the likelihood-ratio test with room
    (2 Delta l about 29 for 2 parameters) but not Delta BIC's threshold (ln n = 12.2 per
    parameter), and takes the model error from 1.58 to 1.16: a fall of 27 %, short of the views'
    rule's third, but from a model the views call failed to one they call explained. That counts
    as the views' word; the refit is reported, at the planted tau."""
    from noiselab.diagnose.diagnose import ERROR_FALL, ERROR_OK

    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.002\n[plant]\nA = [[0.0, 1.0], [-25.52539, -5.92271]]\n"
                        "B = [[0.0], [37.74555]]\nC = [[1.0, 0.0]]\nL = [[4.42985], [0.0]]\n"
                        "[command]\nkind = \"prbs\"\namplitude = 0.6576141691101576\nbit_s = 0.3109\norder = 9\n"
                        "[process.white]\nstd = 0.3369\n[sensor.white]\nstd = 0.014\n"
                        "[sensor.bias_markov]\nstd = 0.03582\ntau_s = 15.23\n[actuator.white]\nstd = 0.2008\n")
    nominal = truth.with_params("sensor.bias_markov", {"std": 0.03582, "tau_s": 60.92})
    rec = truth.simulate(190_000, seed=1048)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    assert [(m["effect"], m["mode"], m["accepted_by"]) for m in rep["missing"]] == [
        ("sensor.bias_markov", "refit", "error")]
    bias = rep["missing"][0]
    assert bias["score"] < THRESHOLD
    assert abs(bias["params"]["tau_s"] / 15.23 - 1) < 0.3 and abs(bias["params"]["std"] / 0.03582 - 1) < 0.3
    lo, hi = bias["interval"]["tau_s"]
    assert lo <= 15.23 <= hi
    e0, e1 = rep["error_before"], rep["error_after"]
    # the new clause is what admits it: a fall short of ERROR_FALL, to an explained model
    assert e0 > ERROR_OK >= e1 > ERROR_FALL * e0
    # the sentence says what changed (a refit is no excess over nothing: the bias's low-frequency
    # level 2 std^2 tau falls here) and what the data say
    assert bias["evidence"].startswith("the model's value does not fit the data (") and \
        "tau_s 60.9 -> " in bias["evidence"], bias["evidence"]
    assert "excess" not in bias["evidence"] and "refitted: a Gauss-Markov bias" in bias["evidence"]


def test_the_views_rule_adds_nothing_to_a_null_record_its_slow_bias_makes_look_wrong():
    """The same truth (case 48: a Gauss-Markov bias of tau 15 s in 380 s) diagnosed against
    itself, on record 1825 (``bench_null_rich``'s): its model error is 1.59 by chance (the slow
    bias's ACF and Allan views spread more than their formulas say), and the best candidate, an
    AR(1) in place of the white actuator noise, gains 2 Delta l = 11.9 with 2 parameters: past the
    5 % family-wise point over the candidates offered, short of the 1 % point the views' rule
    asks. Nothing is reported."""
    from scipy.stats import chi2

    from noiselab.diagnose.diagnose import BY_ERROR_ALPHA, ERROR_OK

    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.002\n[plant]\nA = [[0.0, 1.0], [-25.52539, -5.92271]]\n"
                        "B = [[0.0], [37.74555]]\nC = [[1.0, 0.0]]\nL = [[4.42985], [0.0]]\n"
                        "[command]\nkind = \"prbs\"\namplitude = 0.6576141691101576\nbit_s = 0.3109\norder = 9\n"
                        "[process.white]\nstd = 0.3369\n[sensor.white]\nstd = 0.014\n"
                        "[sensor.bias_markov]\nstd = 0.03582\ntau_s = 15.23\n[actuator.white]\nstd = 0.2008\n")
    rep, logs = _diagnose_hidden(truth, (), 190_000, 1825)
    assert rep["missing"] == [] and rep["error_before"] > ERROR_OK
    said = [s for s in logs if "no candidate passes the likelihood-ratio test" in s]
    assert len(said) == 1, logs
    lr = float(said[0].split("2 Delta l = ")[1].split(" ")[0])
    m = int(said[0].split(" over ")[1].split(" ")[0])
    assert "actuator.ar1" in said[0] and BY_ERROR_ALPHA == 0.01
    assert chi2.isf(0.05 / m, 2) < lr < chi2.isf(BY_ERROR_ALPHA / m, 2), (lr, m)


def test_a_gauss_markov_bias_beats_a_walk_when_its_likelihood_ratio_test_passes():
    """Generated case 36 (a Gauss-Markov bias of tau 14 s hidden; no command; 280 s at 5 ms). The
    walk (1 parameter) and the Gauss-Markov bias (2) scored within 0.1 of each other by the
    choice score, 2 Delta l - 2.71 k, which for these nested alternatives is the likelihood-ratio
    test of 1/tau > 0. The rule for an exact tie (identical spectra: the signal chain's order)
    took it, and the walk came first in the chain. A tie of two fits of different sizes is not
    that: the test decides, and here it passes."""
    from noiselab.diagnose.thresholds import CHIBAR2_95

    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.005\n[plant]\nm = 2.0495\nc = 15.7568\nk = 409.7569\n"
                        "[command]\nkind = \"none\"\n[process.white]\nstd = 22.3\n[sensor.white]\nstd = 0.006171\n"
                        "[sensor.bias_markov]\nstd = 0.01275\ntau_s = 14.23\n[actuator.white]\nstd = 17.07\n")
    rep, logs = _diagnose_hidden(truth, ("sensor.bias_markov",), 56_000, 1036)
    first = {c["effect"]: c["score"] for c in rep["candidates"]}
    ln_n = math.log(56_000)
    lr_extra = (first["sensor.bias_markov"] + 2 * ln_n) - (first["sensor.bias_walk"] + ln_n)
    assert lr_extra > CHIBAR2_95
    assert [m["effect"] for m in rep["missing"]] == ["sensor.bias_markov"]
    assert "sensor.bias_walk" in [a["effect"] for a in rep["missing"][0]["alternatives"]]


def _quiet_white_and_walk():
    """bench_noise_density's case O2: a sensor's white noise (N = 0.002 sqrt(s)) and bias walk
    (K = 0.00346 / sqrt(s)) on a quiet first-order plant, 30 min at 20 ms."""
    sigma = 0.002 / math.sqrt(0.02)
    return parse_model("name = \"quiet\"\n[sampling]\nTs = 0.02\n[plant]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\n"
                       f"L = [[1.0]]\n[command]\nkind = \"none\"\n[process.white]\nstd = {0.05 * sigma!r}\n"
                       f"[sensor.white]\nstd = {sigma!r}\n[sensor.bias_walk]\nstd = {math.sqrt(3.0) * 0.002!r}\n")


def test_a_walk_first_taken_for_a_gauss_markov_bias_is_exchanged_once_it_leads(monkeypatch):
    """A sensor's white noise and bias walk on a quiet plant, both missing (bench_noise_density's
    case O2, seed 502: N = 0.002 sqrt(s), K = 0.00346 / sqrt(s), 30 min at 20 ms). With the white
    noise still missing, a Gauss-Markov bias led step 1; once the white noise was in, its tau ran to
    644 s, a walk in all but name, and the walk led it by 1.7 in the choice units (its extra
    parameter fails the likelihood-ratio test: 2 Delta l = 1.0 < 2.71). The exchange pass kept
    the incumbent within its margin of 2, and the model error stayed at 2.04. Between these two
    nested drift models the choice units decide, as in a step's ranking. The exchange is tested
    among the catalogue's white, walk and Gauss-Markov drifts: with the flicker bias a candidate too,
    the flicker leads step 1 in the Gauss-Markov's place on this record (the test below)."""
    monkeypatch.delitem(CATALOGUE, "sensor.bias_instability")
    rep, logs = _diagnose_hidden(_quiet_white_and_walk(), ("sensor.white", "sensor.bias_walk"), 90_000, 502)
    assert any(x.startswith("exchange: sensor.bias_walk in place of sensor.bias_markov") for x in logs), logs
    got = {m["effect"]: m for m in rep["missing"]}
    assert set(got) == {"sensor.white", "sensor.bias_walk"}
    assert "sensor.bias_markov" in [a["effect"] for a in got["sensor.bias_walk"]["alternatives"]]
    assert got["sensor.bias_walk"]["params"]["std"] == pytest.approx(math.sqrt(3.0) * 0.002, rel=0.3)
    assert rep["error_after"] <= 1.5


def test_a_flicker_bias_that_led_while_the_white_noise_was_missing_is_dropped():
    """The same record with the whole catalogue: while the white noise is missing, every slow noise
    scores far above zero (the residual's white power is taken by whatever noise is tried) and the
    flicker bias leads step 1; once the white noise and the walk are in, its Delta BIC is below
    zero and the drop pass removes it. The report is the truth's: the white noise and the walk,
    the walk's K within 30 % and the model error at most 1.5."""
    rep, logs = _diagnose_hidden(_quiet_white_and_walk(), ("sensor.white", "sensor.bias_walk"), 90_000, 502)
    assert any(x.startswith("step 1: add sensor.bias_instability") for x in logs), logs
    assert any(x.startswith("drop: sensor.bias_instability") for x in logs), logs
    got = {m["effect"]: m for m in rep["missing"]}
    assert set(got) == {"sensor.white", "sensor.bias_walk"}
    assert got["sensor.bias_walk"]["params"]["std"] == pytest.approx(math.sqrt(3.0) * 0.002, rel=0.3)
    assert rep["error_after"] <= 1.5


@pytest.mark.slow
def test_a_slow_drift_stays_the_sensor_bias_when_the_ar1_leads_within_its_spread():
    """Generated case 323 (a Gauss-Markov bias of tau 26 s and a quantization hidden; no command;
    plant time constant 0.12 s): after the quantization, an actuator AR(1) of tau 17 s led the
    Gauss-Markov bias by 2.2 in 2 Delta l, beyond TIE, and was reported. Over six records of this
    truth that lead ranged from -4.9 to +2.2 (mean -2.1): a coin flip, which lr_spread measures
    (about 2 here). The AR(1) must now beat the bias by DISTINCT_Z of those spreads, in the step's
    ranking and in the exchange pass."""
    from noiselab.diagnose.thresholds import DISTINCT_Z, TIE

    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.02\n[plant]\nm = 0.4225\nc = 6.8061\nk = 130.3085\n"
                        "[command]\nkind = \"none\"\n[process.white]\nstd = 8.322\n[sensor.white]\nstd = 0.01154\n"
                        "[actuator.white]\nstd = 5.029\n[sensor.quantization]\nstep = 0.0334\n"
                        "[sensor.bias_markov]\nstd = 0.05556\ntau_s = 26.47\n")
    rep, logs = _diagnose_hidden(truth, ("sensor.bias_markov", "sensor.quantization"), 25_500, 1323)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.quantization", "sensor.bias_markov"]
    kept = [x for x in logs if "kept: a drift this slow" in x]
    assert len(kept) == 1
    trial = next(x for x in logs if "exchange trial sensor.bias_markov -> actuator.ar1" in x)
    lead = float(trial.split(":")[1].split()[0])
    margin = float(kept[0].split("within ")[1].split()[0])
    assert TIE < lead < margin and margin > DISTINCT_Z * 1.5


@pytest.mark.slow
def test_a_slow_ar1_that_only_led_while_an_effect_was_missing_gives_way_to_the_bias():
    """Generated case 300 (a Gauss-Markov bias of tau 7.6 s and a scale factor of +7.5 % hidden;
    plant time constant 0.24 s): with the scale factor still missing, an actuator AR(1) of tau
    6.8 s led the bias by 290 in Delta BIC and was added; once the scale factor is in, the two tie
    exactly (2 Delta l 0.0). The exchange pass now applies the drift rule in this direction too
    (the bias unless the AR(1) beats it by drift_margin), then the backward pass runs again: the
    process-noise refit that step 3 added beside the AR(1) (std 0.437 for the model's 0.4406) is
    no longer needed and goes back to the model's value. Before: AR(1), scale factor and that
    refit were reported."""
    truth = parse_model("name = \"c\"\n[sampling]\nTs = 0.002\n[plant]\nA = [[-4.223873242258644]]\n"
                        "B = [[4.770707580783538]]\nC = [[1.0]]\nL = [[4.223873242258644]]\n"
                        "[command]\nkind = \"sine\"\namplitude = 1.27309662106284\nfrequency_hz = 0.6503\n"
                        "[process.white]\nstd = 0.4406\n[sensor.white]\nstd = 0.01937\n[actuator.white]\nstd = 0.38\n"
                        "[sensor.bias_markov]\nstd = 0.06688\ntau_s = 7.567\n[sensor.scale_factor]\nerror = 0.0746\n")
    rep, logs = _diagnose_hidden(truth, ("sensor.bias_markov", "sensor.scale_factor"), 180_000, 1300)
    assert any(x.startswith("exchange: sensor.bias_markov in place of actuator.ar1") for x in logs)
    assert any(x.startswith("drop: process.white back at the model's values") for x in logs)
    got = {m["effect"]: m for m in rep["missing"]}
    assert set(got) == {"sensor.bias_markov", "sensor.scale_factor"}
    assert "actuator.ar1" in [a["effect"] for a in got["sensor.bias_markov"]["alternatives"]]
    assert got["sensor.bias_markov"]["params"]["tau_s"] == pytest.approx(7.567, rel=0.3)
    assert got["sensor.scale_factor"]["params"]["error"] == pytest.approx(0.0746, rel=0.3)
    assert rep["error_after"] < 1.5


@pytest.mark.slow
def test_a_mean_candidate_is_searched_beside_the_fitted_mean_effects_before_they_move():
    """Generated case 229 (a lag of 0.417 s and a scale factor of +3.4 % hidden, under a sine):
    after the lag is in, the scale factor is screened jointly with it. It starts mid-range
    (+25 %); searched second, the lag first ran its coarse grid against that gain and both ended
    on the ridge they share (tau 0.449 s, +6.2 %), 120 below the truth in 2 Delta l, so
    the scale factor scored -86 and was never offered. The candidate's own coarse grid now comes
    first: the screen reaches the truth's likelihood. Searched in the old order, pattern moves
    along the ridge reach it too."""

    base = ("name = \"c\"\n[sampling]\nTs = 0.01\n[plant]\n"
            "A = [[0.0, 1.0, 0.0, 0.0], [-7.44572, -0.97604, 3.63507, 0.39042], [0.0, 0.0, 0.0, 1.0], "
            "[2.54125, 0.27294, -2.54125, -0.27294]]\nB = [[0.0], [1.0], [0.0], [0.0]]\n"
            "C = [[0.0, 0.0, 1.0, 0.0]]\nL = [[0.0], [0.0], [0.0], [0.6990936790619721]]\n"
            "[command]\nkind = \"sine\"\namplitude = 1.6698769717127342\nfrequency_hz = 0.2689\n"
            "[process.white]\nstd = 0.3885\n[sensor.white]\nstd = 0.02674\n[actuator.white]\nstd = 0.6688\n")
    truth = parse_model(base + "[sensor.scale_factor]\nerror = 0.0343\n[actuator.lag]\ntau_s = 0.4172\n")
    nominal = parse_model(base)
    rec = truth.simulate(55_000, seed=1229)
    S = Search(nominal, Data(rec.y, rec.u, nominal.Ts, True))
    H = S.H
    lag = H.fit(nominal.with_effect("actuator.lag", {"tau_s": 0.01}), {"actuator.lag": ["tau_s"]}, new=("actuator.lag",))
    st = S._noise_or_mean(lag, "sensor.scale_factor", ADD)[0]
    assert st.model.effects["sensor.scale_factor"].param_dict()["error"] == pytest.approx(0.25)
    fit = H.fit(st.model, st.free, new=("sensor.scale_factor", "actuator.lag"),
                only=("sensor.scale_factor", "actuator.lag"))
    at_truth = H.inner_fit(truth, {}).loglik
    assert 2 * (fit.loglik - at_truth) > -2.0
    assert 2 * (fit.loglik - lag.loglik) - math.log(S.data.n_bic) > THRESHOLD
    assert fit.model.effects["sensor.scale_factor"].param_dict()["error"] == pytest.approx(0.0343, rel=0.3)
    # the other order (the lag's coarse grid first, against the +25 % start) climbs the ridge by
    # pattern moves and up to MORE_ROUNDS extra rounds: without them it stopped 120 below the truth
    zig = H.fit(st.model, st.free, new=("actuator.lag", "sensor.scale_factor"),
                only=("sensor.scale_factor", "actuator.lag"))
    assert 2 * (zig.loglik - at_truth) > -2.0


def test_a_local_refit_follows_a_shape_parameter_beyond_its_first_bracket():
    """A refit searches a shape parameter locally (golden section in one step either side of its
    value) when it starts from a fitted value: after another effect is added, a correlation time
    can have to move further. Started 10x below, the local refit of a Gauss-Markov tau (120 s of
    the pair's truth) must reach the maximum the coarse grid finds (before: stuck at 0.16 s, the
    log-likelihood 280 lower)."""
    from noiselab.diagnose.edits import _set
    from noiselab.diagnose.hypotheses import Hypotheses
    eid = "sensor.bias_markov"
    truth = load_model(f"hidden/{eid}")
    rec = truth.simulate(int(round(120 / truth.Ts)), seed=7)
    H = Hypotheses(Data(rec.y, rec.u, truth.Ts, True), truth)
    free = {eid: ["std", "tau_s"]}
    coarse = H.fit(truth, free, new=(eid,))
    local = H.fit(_set(truth, eid, {"tau_s": 0.1}), free)
    assert local.loglik > coarse.loglik - 0.05, (local.loglik, coarse.loglik)
    tau = [f.model.effects[eid].param_dict()["tau_s"] for f in (coarse, local)]
    assert abs(tau[1] / tau[0] - 1) < 0.02, tau


def test_a_right_model_with_jitter_under_a_chirp_reads_about_one():
    """Generated case 258 (servo at 1.5 Hz, a chirp 0.3-4.6 Hz repeated over 530 s, 1.8 ms of
    jitter). The jitter's power follows the slope, concentrated where the chirp crosses the
    resonance: the views must take its level over this record's command (the predictor's is over
    one sweep from rest, 12 % high here) and the spreads of their estimators under the modulation.
    The truth model's error over 10 records must be 1 within 3 standard errors of their mean (it
    read 2.0-2.7: PSD 3-4.7, Allan 4-7)."""
    from noiselab.diagnose.compare import compare
    case = make_case(258)
    truth = parse_model(case.truth, "truth")
    errors = []
    for k in range(10):
        rec = truth.simulate(int(round(case.duration / truth.Ts)), seed=case.seed + k)
        errors.append(compare(truth, rec.t, rec.y, rec.u, burn=None).error)
    se = np.std(errors, ddof=1) / math.sqrt(len(errors))
    assert abs(np.mean(errors) - 1) < 3 * se, (np.mean(errors), se, errors)


@pytest.mark.slow
def test_modulation_kappa_against_monte_carlo():
    """White noise whose variance follows 1 + 0.9 sin(2 pi k / 200): the variance of a Welch band
    average (1024-sample Hann segments, bands of 1, 8 and 64 bins) over 800 records, against the same
    for stationary noise, must be modulation_kappa's factor within 3 sd of the ratio (sd 2 / sqrt(799)
    of it: two sample variances). One bin resolves 526 samples and sees no modulation (1.00); 64 bins
    resolve 8 and see its mean square (1.40)."""
    from noiselab.diagnose.compare import modulation_kappa
    from noiselab.stats import welch
    N, L, R, bands = 16384, 1024, 800, (1, 8, 64)
    m = 1 + 0.9 * np.sin(2 * np.pi * np.arange(N) / 200)
    rng = np.random.default_rng(1)
    est = np.empty((2, R, len(bands)))
    for r in range(R):
        e = rng.standard_normal(N)
        for i, x in enumerate((e, e * np.sqrt(m))):
            P = welch(x, 1.0, nperseg=L).psd
            est[i, r] = [P[100:100 + K].mean() for K in bands]
    ratio = est[1].var(axis=0) / est[0].var(axis=0)
    kappa = modulation_kappa(m, [int(round(0.514 * L / K)) for K in bands], np.ones(len(bands)))
    assert np.all(np.abs(kappa - ratio) < 3 * ratio * 2 / math.sqrt(R - 1)), (kappa, ratio)
    assert ratio[-1] > 1 + 3 * 2 / math.sqrt(R - 1) and kappa[-1] > 1.3, (ratio, kappa)


def test_quantization_grid_detected():
    step = 0.001
    y = step * np.round(np.random.default_rng(1).normal(0, 0.01, (5000, 1)) / step)
    assert quantization_grid(y) == [pytest.approx(step, rel=1e-9)]
    assert quantization_grid(np.random.default_rng(2).normal(0, 1, (5000, 1))) == [None]


@pytest.mark.slow
def test_a_coarse_quantizer_on_a_slow_signal_is_found_alone():
    """A quantizer of step 0.02 beside a sensor noise of 0.002 on a signal that crosses a step every
    ~10 samples (an undithered encoder): its error is a sawtooth, correlated over ~5 samples, not
    step^2/12 of white noise. With the error taken as white, the true model read a model error of
    about 41 and the search added a Gauss-Markov "bias" of tau 0.01 s and a zero sensor noise to
    imitate the correlation (error after 7.3). With the correlated error predicted
    (:func:`noiselab.model.effects.sensor_quantization.quantization_acf`) the quantizer alone is
    reported and the error falls to about 1."""
    truth = parse_model('name = "q"\n[sampling]\nTs = 0.005\n[plant]\nm = 1.0\nc = 1.0\nk = 10.0\n'
                        '[command]\nkind = "sine"\namplitude = 1.0\nfrequency_hz = 0.4\n'
                        "[process.white]\nstd = 0.5\n[sensor.white]\nstd = 0.002\n"
                        "[sensor.quantization]\nstep = 0.02\n", "truth")
    from noiselab.diagnose.compare import compare

    rec = truth.simulate(24_000, seed=1)
    assert compare(truth, rec.t, rec.y, rec.u, burn=None, level=True).error < 1.5
    rep, _ = _diagnose_hidden(truth, ("sensor.quantization",), 24_000, 1)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.quantization"]
    assert rep["missing"][0]["params"]["step"] == pytest.approx(0.02, rel=1e-6)
    assert rep["error_after"] < 1.5 < rep["error_before"]


@pytest.mark.slow
def test_an_encoder_like_quantizer_is_found_alone_and_explains_the_record():
    """A step of 0.5 over a sensor noise of 0.08 step on a sine across ~11 steps: most of the
    quantizer's error is its conditional mean E[Q(x)] - mu, a function of the mean response. With it
    in the mean response (and the variance about it following the mean's place between the levels)
    the quantizer alone is reported and the model error falls to about 1; with it left in the
    residual as noise the error after was 10.5 on this record."""
    truth = parse_model(ENCODER_TOML, "encoder")
    rep, _ = _diagnose_hidden(truth, ("sensor.quantization",), 24_000, 1)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.quantization"]
    assert rep["missing"][0]["params"]["step"] == pytest.approx(0.5, rel=1e-6)
    assert rep["error_after"] < 1.5 < rep["error_before"]


def test_command_lines_and_their_harmonics_are_no_tone():
    """A sine command has one line (its frequency, to a bin); a chirp and PRBS none, also when they
    repeat within the record (a comb of thousands of weak lines up to the Nyquist frequency, whose
    harmonics covered every frequency: generated case 318's tone at 55 Hz was never offered); a
    residual line at the sine's 3rd harmonic (a saturation's) is not offered as a tone, one
    elsewhere is."""
    Ts, N = 0.01, 20000
    t = np.arange(N) * Ts
    f0 = 0.7

    def command(text):
        return parse_model("name = \"c\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 2.0\nk = 20.0\n"
                           "[command]\n" + text).command.values(0, N, Ts)[:, 0]
    for u, lines in [(0.8 * np.sin(2 * np.pi * f0 * t), [f0]),
                     (np.sin(2 * np.pi * (0.1 + 0.02 * t) * t), []),
                     (np.where(np.random.default_rng(4).random(N // 50).repeat(50) > 0.5, 1.0, -1.0), []),
                     (command('kind = "chirp"\namplitude = 1.0\nf0_hz = 0.4\nf1_hz = 5.0\nduration_s = 20.0\n'), []),
                     (command('kind = "prbs"\namplitude = 1.0\nbit_s = 0.05\norder = 9\n'), [])]:
        d = Data(np.zeros((N, 1)), u[:, None], Ts, True)
        got = d.command_lines()
        assert len(got) == len(lines) and np.allclose(got, lines, atol=1.0 / (N * Ts)), got
    # a square wave keeps its strong odd harmonics (power 0.81 / k^2 of the total: 9 % at the 3rd)
    got = Data(np.zeros((N, 1)), np.sign(np.sin(2 * np.pi * 0.5 * t + 0.1))[:, None], Ts, True).command_lines()
    odd = 0.5 * np.arange(1, 200, 2)
    assert np.allclose(got[:4], odd[:4], atol=1.0 / (N * Ts)) and len(got) <= 6, got
    model = parse_model("name = \"c\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 2.0\nk = 20.0\n"
                        "[command]\nkind = \"sine\"\namplitude = 0.8\nfrequency_hz = 0.7\n"
                        "[sensor.white]\nstd = 0.01\n")
    rng = np.random.default_rng(5)
    mean = model.predictor().mean_response(N)
    for f, offered in [(3 * f0, False), (5.3, True)]:
        y = mean.y + 0.01 * rng.standard_normal((N, 1)) + 0.02 * np.sin(2 * np.pi * f * t)[:, None]
        S = Search(model, Data(y, model.command.values(0, N, Ts), Ts, True))
        tones = S._tones(S.start(), "sensor.tone", ADD)
        assert bool(tones) == offered and all(abs(st.model.effects["sensor.tone"].params["frequency_hz"] - f) < 0.01
                                              for st in tones)


# -- generated cases like the independent set -----------------------------------------------------------------
AMBIGUOUS_1002 = ("a Gauss-Markov bias of tau 5.9 s in a 250 s record under a PRBS command: it is now reported as a "
                  "Gauss-Markov bias (the likelihood-ratio choice over the walk), but with tau 11.2 s: the likelihood "
                  "is flat in tau (3 to 50 s within 1.5 in log-likelihood); process.white is refitted as a third "
                  "effect (Delta BIC 13.3); the scale factor is found")


AMBIGUOUS_1006 = ("a Gauss-Markov bias of tau 19.9 s in a 380 s record: found, with process.white, but tau 26.2 s "
                  "(+32 %): with 19 correlation times in the record the relative std of a tau estimate is about "
                  "sqrt(2 tau / T) = 32 %, so the 30 % criterion fails about a third of the time by estimation "
                  "theory alone")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1001, pytest.param(1002, marks=pytest.mark.xfail(strict=True, reason=AMBIGUOUS_1002)),
                                  1003, 1004, 1005,
                                  pytest.param(1006, marks=pytest.mark.xfail(strict=True, reason=AMBIGUOUS_1006))])
def test_generated_cases(seed):
    """Random plants, periods, durations and hidden effects (tests/bench/hidden_set.py), fixed seeds:
    the planted effects on top, parameters within 30 %, error after at most 1.5 and below before;
    nothing on a null case."""
    case = make_case(seed, null=(seed == 1001), n_hidden=1 if seed % 2 else 2)
    truth, nominal = parse_model(case.truth, "truth"), parse_model(case.nominal, "nominal")
    rec = truth.simulate(int(round(case.duration / truth.Ts)), seed=case.seed)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    sc = score_case(case, rep)
    assert sc["ok"], (case.hidden, sc, [(m["effect"], m["params"]) for m in rep["missing"]])


SLOW_MARKOV = ("a Gauss-Markov bias of tau {tau} s in a {T:.0f} s record ({n:.0f} correlation times) is found as a "
               "bias walk, the model error after {err}: the relative sd of a tau estimate is about sqrt(2 tau / T) = "
               "{sd:.0f} %, so the record cannot hold tau within 30 %, and a walk is its limit")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [
    8, 9, 10, 11, 12, 13, 14, 15, 16,
    pytest.param(17, marks=pytest.mark.xfail(strict=True, reason=SLOW_MARKOV.format(
        tau=56.4, T=350, n=350 / 56.4, err=0.92, sd=100 * math.sqrt(2 * 56.4 / 350)))),
    18, 19, 20, 21, 22, 23])
def test_generated_sensor_cases(seed):
    """The sensor-only family of generated cases (a rate sensor at rest, its model a white noise;
    hidden: white noise at a wrong value, walk, Gauss-Markov bias, flicker bias, the integral's white
    noise, tone, quantization, the sensor's own filter; tests/bench/hidden_set.py
    ``make_sensor_case``), with the generator's acceptance: the planted effects on top, parameters
    within 30 % (a filter's kind and taps exactly), error after at most 1.5 and below before;
    nothing on a null case. Seeds 8-23 hold a flicker bias (11, 23), the integral's white noise (9,
    16, 22), a filter (9, 10, 18) and null records (13, 20)."""
    case = make_sensor_case(seed)
    truth, nominal = parse_model(case.truth, "truth"), parse_model(case.nominal, "nominal")
    rec = truth.simulate(int(round(case.duration / truth.Ts)), seed=case.seed)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    sc = score_case(case, rep)
    assert sc["ok"], (case.hidden, sc, [(m["effect"], m["params"]) for m in rep["missing"]])


SCALE_AT_REACH = ("a sensor scale factor of -14.4 % under a PI-D with a 0.068 m step reference: the integral holds "
                  "y at the step's level, so the scale factor shows in the level (which places a mean effect's "
                  "parameter but does not score it) and in the step's transient alone; the report's "
                  "scale_factor_reach for this record is 14.6 % (Delta BIC -4.5 for it)")


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 13, 14, 15,
                                  pytest.param(16, marks=pytest.mark.xfail(strict=True, reason=SCALE_AT_REACH))])
def test_generated_closed_loop_cases(seed):
    """The closed-loop family of generated cases (tests/bench/hidden_set.py ``make_closed_case``: a
    mass-spring-damper under a PD or PI-D on its measurement, several gains, a reference none, step
    or sine, one or two effects of the whole catalogue hidden; seed 11's truth loop is unstable and
    is not a case), with the generator's acceptance: the planted effects on top, parameters within
    30 %, error after at most 1.5 and below before; nothing on a null case. Process and actuator
    white noise entering through the command's input have the same spectrum: where the report
    names the planted one as an exact-tie alternative (``tied``: seeds 9, 10), that is what the data
    say. Every record is said to be closed-loop."""
    case = make_closed_case(seed)
    assert case.stable
    rec = case.record()
    rep = diagnose(parse_model(case.nominal, "nominal"), rec.t, rec.y, rec.u)
    assert rep["feedback"] is not None and rep["feedback"].closed
    sc = score_case(case, rep)
    tied_ok = bool(sc["planted"]) and set(sc["planted"]) - set(sc["reported"]) <= set(sc["tied"]) \
        and sc["error_ok"] and len(rep["missing"]) == len(sc["planted"])
    assert sc["ok"] or tied_ok, (case.hidden, sc, [(m["effect"], m["params"]) for m in rep["missing"]])


def test_the_bench_scores_a_value_per_input_each():
    """hidden_set plants an actuator noise of two inputs with one std per input: each is held to the
    30 % criterion (one std for both inputs, or the smaller input's 60 % off, fails), and the
    reported interval (the largest input's) is checked against the largest planted value."""
    from hidden_set import Case
    case = Case("c", "", "", {"actuator.white": {"std": [0.3, 0.05]}}, 60.0, 1)

    def rep(std, iv):
        return {"missing": [{"effect": "actuator.white", "mode": "add", "params": {"std": std},
                             "interval": {"std": iv}, "score": 10.0}], "error_before": 5.0, "error_after": 1.0}
    good = score_case(case, rep([0.31, 0.06], [0.28, 0.33]))
    assert good["ok"] and good["covered"] == [True]
    assert score_case(case, rep([0.31, 0.06], [0.31, 0.33]))["covered"] == [False]
    assert not score_case(case, rep([0.31, 0.08], [0.28, 0.33]))["ok"]
    assert not score_case(case, rep(0.31, [0.28, 0.33]))["params_ok"]


# -- the command line ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def walk_recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("diag") / "walk.mcap"
    r = cli("simulate", "hidden/sensor.bias_walk", "--duration", 180, "--seed", 3, "--out", out)
    assert r.returncode == 0, r.stderr
    return out


def test_cli_json_fitted_model_and_rrd(walk_recording, tmp_path):
    fit, rrd = tmp_path / "fitted.toml", tmp_path / "diag.rrd"
    r = cli("diagnose", walk_recording, "--model", "hidden/sensor.bias_walk-nominal", "--json",
            "--fit-out", fit, "--rrd", rrd)
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    for key in ("error_before", "error_after", "missing"):
        assert key in rep
    m = rep["missing"][0]
    assert set(m) >= {"effect", "params", "score", "evidence"}
    assert m["effect"] == "sensor.bias_walk" and abs(m["params"]["std"] / 0.004 - 1) < 0.3
    assert m["evidence"].endswith(f"{m['params']['std']:.3g} per sqrt(s)")
    assert rep["error_after"] < rep["error_before"]
    # the fitted model file holds the effect, and analysing with it gives the reported error
    fitted = load_model(str(fit))
    assert fitted.effects["sensor.bias_walk"].param_dict()["std"] == pytest.approx(m["params"]["std"])
    r2 = cli("analyze", walk_recording, "--model", fit, "--json")
    assert r2.returncode == 0, r2.stderr
    assert json.loads(r2.stdout)["error"] == pytest.approx(rep["error_after"], rel=1e-12)
    # the .rrd: the model error per revision (before, after each step) as in the JSON
    ch = read_chunks(rrd)
    errs = np.concatenate(column(ch["/error/overall"], "Scalars:scalars")).tolist()
    assert errs == pytest.approx([rep["error_before"]] + [s["error"] for s in rep["steps"]])
    assert rrd.with_suffix(".png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_text_report(walk_recording):
    r = cli("diagnose", walk_recording, "--model", "hidden/sensor.bias_walk-nominal")
    assert r.returncode == 0, r.stderr
    assert "missing, most likely first" in r.stdout and "[sensor.bias_walk]" in r.stdout
    assert "model error:" in r.stdout


def test_cli_nothing_missing(walk_recording):
    r = cli("diagnose", walk_recording, "--model", "hidden/sensor.bias_walk", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert rep["missing"] == [] and rep["error_after"] == rep["error_before"]
    # the text names the best candidate below the threshold with its fitted values
    best = rep["candidates"][0]
    r = cli("diagnose", walk_recording, "--model", "hidden/sensor.bias_walk")
    assert r.returncode == 0, r.stderr
    line = next(ln for ln in r.stdout.splitlines() if "best candidate" in ln)
    assert f"{best['mode']} {best['effect']}, Delta BIC {best['score']:.1f}: " in line
    present = load_model("hidden/sensor.bias_walk").effects.get(best["effect"])
    keys = set(present.param_dict()) if present is not None else set(best["params"])   # as the file spells them
    for k, v in best["params"].items():
        if k in keys and not isinstance(v, list):
            assert f"{k} = {float(v):.4g}" in line, (k, line)


@pytest.mark.parametrize("args, needle", [
    (["nope.mcap", "--model", "seed"], "no such file"),
    (["{rec}", "--model", "nope-model"], "no such model"),
    (["{rec}", "--model", "hidden/sensor.tone-nominal"], "Ts"),
    (["{rec}", "--model", "seed", "--max-effects", "0"], "max-effects"),
    (["{bad}", "--model", "seed"], "MCAP"),
    (["{rec}", "--model", "seed", "--fit-out", "{rec}"], "exists"),
    (["{rec}", "--model", "seed", "--fit-out", "{bad}/fitted.toml"], "bad.mcap is a file, not a directory"),
    (["{rec}", "--model", "seed", "--rrd", "{tmp}"], "is a directory"),
    (["{rec}", "--model", "seed", "--rrd", "/"], "/: is a directory"),
    (["{bad}", "--model", "nope-model", "--rrd", "/"], "no such model"),      # the model's error first
])
def test_cli_bad_input_one_line_exit_2(walk_recording, tmp_path, args, needle):
    bad = tmp_path / "bad.mcap"
    bad.write_text("not an mcap file")
    args = [a.format(rec=walk_recording, bad=bad, tmp=tmp_path) for a in args]
    r = cli("diagnose", *args)
    assert r.returncode == 2, (r.returncode, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and needle.lower() in lines[0].lower(), r.stderr
    assert walk_recording.stat().st_size > 0


@pytest.mark.slow
def test_a_plant_that_integrates_end_to_end(tmp_path):
    """A DC motor's angle (a pole at 0: the angle is a random walk plus a stationary part) with a
    sensor bias walk hidden: `simulate`, then `diagnose` against the model without the bias. The
    plant's own walk dominates the lowest frequencies; the bias walk shows where the plant's walk
    falls as 1/f^4 above the motor's pole (0.64 Hz) and the bias walk's as 1/f^2. Its interval must
    hold the true value; the truth model reports nothing; a double integrator (no stationary
    increments) is refused in one line, exit 2."""
    motor = (ROOT / "service" / "scenarios" / "motor-nominal.toml").read_text()
    nominal = tmp_path / "nominal.toml"
    nominal.write_text(motor)
    truth = tmp_path / "truth.toml"
    truth.write_text(motor + "\n[sensor.bias_walk]\nstd = 0.0015\n")
    rec = tmp_path / "motor.mcap"
    r = cli("simulate", truth, "--duration", 120, "--seed", 4, "--out", rec)
    assert r.returncode == 0, r.stderr
    r = cli("diagnose", rec, "--model", nominal, "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.bias_walk"], rep["missing"]
    m = rep["missing"][0]
    lo, hi = m["interval"]["std"]
    assert lo <= 0.0015 <= hi and abs(m["params"]["std"] / 0.0015 - 1) < 0.3, m
    assert rep["error_after"] <= 1.5 < rep["error_before"]
    r = cli("diagnose", rec, "--model", truth, "--json")
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["missing"] == []
    double = tmp_path / "double.toml"
    double.write_text(motor.replace("[0.0, -4.0]", "[0.0, 0.0]"))
    r = cli("diagnose", rec, "--model", double)
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 1
    assert "chain of integrators" in r.stderr, r.stderr


_QJ_DOC = """name = "qj"
[sampling]
Ts = 0.002
[plant]
A = [[-11.81]]
B = [[9.26]]
C = [[1.0]]
L = [[11.81]]
[command]
kind = "sine"
amplitude = 1.575
frequency_hz = 1.63
[process.white]
std = 0.2
[sensor.white]
std = 0.0063
[sensor.quantization]
step = 0.0627
"""


def test_a_quantizers_slope_modulation_is_not_a_jitter():
    """Coarse case 23's regime (step 0.0627; the noise changes by a sixth of a step between samples
    while the sine moves up to 0.3 step): the quantizer's error decorrelates as the signal moves,
    so the squared differenced residual grows with the slope as a jitter's would. The jitter's
    modulation term subtracts the model's prediction of it (Hypotheses._quant_slope): on a record
    without jitter its slope is within 3 standard errors of 0 (without the prediction it read
    jitters of about 1.1 ms, reported on 2 of 3 such records); with a 1.5 ms jitter it is std_s^2
    within 3 standard errors; and the diagnosis of the record without jitter reports nothing."""
    from noiselab.diagnose.hypotheses import Hypotheses
    from noiselab.diagnose.modulation import Modulation
    nominal = parse_model(_QJ_DOC, "nominal")
    jittered = parse_model(_QJ_DOC + "[sensor.jitter]\nstd_s = 0.0015\n", "jitter")
    out = {}
    for label, model in (("none", nominal), ("jitter", jittered)):
        rec = model.simulate(30_000, seed=1)
        H = Hypotheses(Data(y=rec.y, u=rec.u, Ts=model.Ts, at_rest=True), nominal)
        base = H._quant_slope(model)
        assert base is not None and base.shape == (H.data.M, 1) and np.ptp(base) > 0
        dd = np.diff(H.ev.residual(nominal, False)[0], axis=0)
        ydot = H.ev.mean(nominal)[1]
        out[label] = (Modulation(dd, ydot, 0, 1.0), Modulation(dd, ydot, 0, 1.0, base))
    bare, with_q = out["none"]
    assert bare.slope / math.sqrt(bare.se2) > 4            # the confound, left in: a jitter "seen"
    assert abs(with_q.slope) < 3 * math.sqrt(with_q.se2)
    m = out["jitter"][1]
    assert abs(m.slope - 0.0015**2) < 3 * math.sqrt(m.se2) and m.slope > 3 * math.sqrt(m.se2)
    rec = nominal.simulate(30_000, seed=1)
    assert diagnose(nominal, rec.t, rec.y, rec.u)["missing"] == []


def test_the_text_report_gives_intervals_and_scores_the_digits_they_need():
    """A tone's frequency interval is parts in 10^6 wide: printed to 4 digits it read
    "50 [50, 50]"; it gets the digits that tell its ends apart. A sensor noise 100x over the
    model's scores Delta BIC ~5e13: 14 digits of it said nothing; small scores keep one decimal,
    as the evidence sentences print them."""
    from noiselab.diagnose.report import _with_interval
    from noiselab.diagnose.results import fmt_score
    assert _with_interval("frequency_hz", 50.00001, (49.99992, 50.00004)) == \
        "frequency_hz = 50.00001 [49.99992, 50.00004]"
    assert _with_interval("std", 0.0123456, (0.011, 0.0135)) == "std = 0.01235 [0.011, 0.0135]"
    assert fmt_score(52354402782748.0) == "5.24e+13" and fmt_score(4.83) == "4.8" and fmt_score(-1.46) == "-1.5"


@pytest.mark.slow
def test_a_sensor_noise_of_two_outputs_is_fitted_per_output():
    """A position and a velocity sensor (noise 1 : 10). (a) The model has their white noise at a
    quarter of its value: the refit finds each output's, [0.004, 0.04] within 3 %. The scale was
    one value set on every output (the largest), so the refit made them equal, fitted badly and
    lost to an actuator noise and a jitter that the data do not have (model error 98 after).
    (b) A bias walk of [0.002, 0.02] / sqrt(s) missing: found per output (one std for both read
    0.0067, model error 8.9 after); one variance per output counts as one parameter each. (c) The
    same for a Gauss-Markov bias."""
    doc = ("name = \"pv\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[0.0, 1.0], [-4.0, -0.6]]\nB = [[0.0], [1.0]]\n"
           "C = [[1.0, 0.0], [0.0, 1.0]]\n[command]\nkind = \"sine\"\namplitude = 1.0\nfrequency_hz = 0.3\n"
           "[process.white]\nstd = 0.5\n[sensor.white]\nstd = SW\n")
    truth = parse_model(doc.replace("SW", "[0.004, 0.04]"), "truth")
    nominal = parse_model(doc.replace("SW", "[0.001, 0.01]"), "nominal")
    rec = truth.simulate(12_000, seed=2)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    assert [(m["effect"], m["mode"]) for m in rep["missing"]] == [("sensor.white", "refit")]
    std = rep["missing"][0]["params"]["std"]
    assert std == [pytest.approx(0.004, rel=0.03), pytest.approx(0.04, rel=0.03)]
    lo, hi = rep["missing"][0]["interval"]["std"]          # the largest output's
    assert lo <= 0.04 <= hi and hi / lo < 1.1
    assert rep["error_after"] <= 1.5

    walk = parse_model(doc.replace("SW", "[0.004, 0.04]") + "[sensor.bias_walk]\nstd = [0.002, 0.02]\n", "walk")
    rep, _ = _diagnose_hidden(walk, ("sensor.bias_walk",), 18_000, 4)
    assert [(m["effect"], m["mode"]) for m in rep["missing"]] == [("sensor.bias_walk", "add")]
    got = rep["missing"][0]["params"]["std"]
    lo, hi = rep["missing"][0]["interval"]["std"]
    assert lo <= 0.02 <= hi and lo <= got[1] <= hi
    # the smaller output's std, its walk in the same ratio to its sensor noise: within the larger's
    # relative precision, the interval's full width (about 4 standard errors)
    assert got[0] == pytest.approx(0.002, rel=(hi - lo) / got[1])
    assert rep["error_after"] <= 1.5

    # (c) a Gauss-Markov bias of [0.003, 0.03], tau 5 s (one value for both read 0.025, tau 34 s,
    # model error 3.2 after): per output, tau within its interval; the std's interval is the
    # profile of the largest output's alone, the other's variance and tau re-optimized at every
    # value (held at its fit instead, with tau free, it came out 10 % narrower in hi / lo)
    gm = parse_model(doc.replace("SW", "[0.004, 0.04]") + "[sensor.bias_markov]\nstd = [0.003, 0.03]\ntau_s = 5.0\n",
                     "gm")
    rep, _ = _diagnose_hidden(gm, ("sensor.bias_markov",), 12_000, 4)
    assert [m["effect"] for m in rep["missing"]] == ["sensor.bias_markov"]
    m = rep["missing"][0]
    lo, hi = m["interval"]["std"]
    assert lo <= 0.03 <= hi and lo <= m["params"]["std"][1] <= hi
    assert m["params"]["std"][0] == pytest.approx(0.003, rel=(hi - lo) / m["params"]["std"][1])
    assert m["interval"]["tau_s"][0] <= 5.0 <= m["interval"]["tau_s"][1]
    assert rep["error_after"] <= 1.5


@pytest.mark.slow
def test_an_actuator_noise_of_two_inputs_is_fitted_per_input():
    """Two masses, each driven by its own input, each position measured; AR(1) actuator noise of
    std [0.3, 0.05] (tau 0.2 s) missing. One factor over the inputs (their proportions taken as
    equal, the file giving none) found a Gauss-Markov sensor bias first and an AR(1) of one std
    0.03, model error 8.4 after. Each input's variance is fitted (its part through the plant
    computed apart: it reaches both outputs), each counted as a parameter. One factor over the
    inputs is fitted beside it, and Delta BIC chooses."""
    doc = ('name = "two"\n[sampling]\nTs = 0.01\n[plant]\n'
           'A = [[0.0, 1.0, 0.0, 0.0], [-4.0, -0.6, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0], [1.0, 0.0, -9.0, -0.8]]\n'
           'B = [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]\nC = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]\n'
           '[command]\nkind = "sine"\namplitude = 1.0\nfrequency_hz = 0.3\n[sensor.white]\nstd = [0.004, 0.004]\n')
    truth = parse_model(doc + "[actuator.ar1]\nstd = [0.3, 0.05]\ntau_s = 0.2\n", "truth")
    nominal = parse_model(doc, "nominal")
    rec = truth.simulate(30_000, seed=1)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    assert [(m["effect"], m["mode"]) for m in rep["missing"]] == [("actuator.ar1", "add")]
    m = rep["missing"][0]
    lo, hi = m["interval"]["std"]                          # the largest input's
    assert lo <= 0.3 <= hi and lo <= m["params"]["std"][0] <= hi
    assert m["params"]["std"][1] == pytest.approx(0.05, rel=0.3)
    assert m["interval"]["tau_s"][0] <= 0.2 <= m["interval"]["tau_s"][1]
    assert rep["error_after"] <= 1.5 < rep["error_before"]

    # the same noise on both inputs: one factor over them is as good with a parameter fewer, and
    # Delta BIC keeps it (per input, an equal noise on inputs the output sees alike was put all on
    # one of them: hidden_set's two-input case 17 read [0.0148, 0.0] for [0.0117, 0.0108])
    same = parse_model(doc + "[actuator.ar1]\nstd = 0.2\ntau_s = 0.2\n", "same")
    rec = same.simulate(30_000, seed=1)
    rep = diagnose(nominal, rec.t, rec.y, rec.u)
    assert [(m["effect"], m["mode"]) for m in rep["missing"]] == [("actuator.ar1", "add")]
    m = rep["missing"][0]
    assert isinstance(m["params"]["std"], float)
    assert m["interval"]["std"][0] <= 0.2 <= m["interval"]["std"][1]
    assert rep["error_after"] <= 1.5


def test_a_profile_the_data_do_not_bound_ends_at_zero_or_the_largest_value_tried():
    """An input's variance the data hardly see (two-input case 16 of the bench): the profile's
    likelihood never fell below its threshold, the search's factor was squared 30 times and
    overflowed a float (OverflowError, the diagnosis lost). The lower end is 0, the upper the
    largest value tried (beyond 1 / UNBOUNDED times the estimate); a likelihood that falls still
    gives a finite end between."""
    from types import SimpleNamespace

    from noiselab.diagnose import intervals as S
    doc = ('name = "two"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-1.0, 0.0], [0.0, -2.0]]\n'
           'B = [[1.0, 0.0], [0.0, 1.0]]\nC = [[1.0, 1.0]]\n[actuator.ar1]\nstd = [0.3, 0.05]\ntau_s = 0.2\n')
    fit = SimpleNamespace(free={"actuator.ar1": ["std", "tau_s"]}, loglik=0.0, model=parse_model(doc, "two"))
    flat = SimpleNamespace(fit=lambda model, free, rounds=1: SimpleNamespace(loglik=0.0))
    assert S._profile_scale_shaped(flat, fit, "actuator.ar1", "std", 0.3, -1) == 0.0
    assert S._profile_scale_shaped(flat, fit, "actuator.ar1", "std", 0.3, +1) >= 0.3 / S.UNBOUNDED

    def quadratic(model, free, rounds=1):        # l = -((s - 0.3) / 0.01)^2 / 2: ends at 0.3 +- 0.0196
        s = model.effects["actuator.ar1"].params["std"][0]
        return SimpleNamespace(loglik=-0.5 * ((s - 0.3) / 0.01) ** 2)
    bowl = SimpleNamespace(fit=quadratic)
    assert S._profile_scale_shaped(bowl, fit, "actuator.ar1", "std", 0.3, -1) == pytest.approx(0.3 - 0.0196, abs=5e-4)
    assert S._profile_scale_shaped(bowl, fit, "actuator.ar1", "std", 0.3, +1) == pytest.approx(0.3 + 0.0196, abs=5e-4)

    # a std fitted at 0 (the model's effect absent from the data): divided by it before (the bound's
    # ratio raised ZeroDivisionError); now [0, the upper end], found from below and from above
    none = SimpleNamespace(free=fit.free, loglik=0.0, model=parse_model(doc.replace("[0.3, 0.05]", "[0.0, 0.0]"), "none"))
    for width in (0.02, 1e-5):                   # ends above and below a new effect's start (1e-3)
        def at_zero(model, free, rounds=1, width=width):
            s = model.effects["actuator.ar1"].params["std"][0]
            return SimpleNamespace(loglik=-0.5 * (s / width) ** 2)
        H0 = SimpleNamespace(fit=at_zero, data=SimpleNamespace(Ts=0.01))
        assert S._profile_scale_shaped(H0, none, "actuator.ar1", "std", 0.0, -1) == 0.0
        assert S._profile_scale_shaped(H0, none, "actuator.ar1", "std", 0.0, +1) == pytest.approx(1.96 * width, rel=0.02)


def test_a_profile_crossing_from_the_estimate_lands_on_a_quadratic_profiles_end_in_one_fit():
    """The profile's edge searched from its peak by regula falsi on the squared distance from the
    estimate: a profile quadratic in ln x (or in x) is a straight line there, so the first fit lands
    on 2 Delta l = 3.84 (the bisection of the shape parameters took 12 fits, regula falsi on ln x
    4-5); without the peak, the plain regula falsi needs more than one."""
    from noiselab.diagnose import intervals as S

    for log, z, back in ((True, math.log, math.exp), (False, (lambda v: v), (lambda v: v))):
        x_hat, sd = 0.3, 0.05
        calls = []

        def l_at(x):
            calls.append(x)
            return -0.5 * ((z(x) - z(x_hat)) / sd) ** 2
        target = -S.CHI2_95 / 2
        for direction in (+1, -1):
            want = back(z(x_hat) + direction * sd * math.sqrt(S.CHI2_95))
            out = back(z(x_hat) + direction * 3 * sd)
            calls.clear()
            got = S._crossing(l_at, x_hat, 0.0, out, l_at(out), target, log=log, peak=x_hat)
            assert len(calls) == 2 and got == pytest.approx(want, rel=1e-9), (log, direction, calls, got, want)
            calls.clear()
            plain = S._crossing(l_at, x_hat, 0.0, out, l_at(out), target, log=log)
            assert len(calls) > 2 and abs(l_at(plain) - target) < 0.02


def test_an_exact_add_refit_tie_goes_to_the_addition_whichever_candidate_leads():
    """Actuator white noise hidden on a plant whose process noise enters through the same input (L
    = B): adding it and refitting the process noise are the same spectra (scores equal to 1e-9).
    On this record an AR(1) leads both in the choice score, by its second parameter's near-level
    likelihood ratio; the tie rule (the user's value kept, the effect added) must still apply.
    Before, the tie was looked for beside the leader only, and the refit was reported."""
    from noiselab.diagnose.thresholds import EXACT_TIE
    base = ("name = \"m2\"\n[sampling]\nTs = 0.01\n[plant]\n"
            "A = [[0, 1, 0, 0], [-6, -0.6, 2, 0.3], [0, 0, 0, 1], [2, 0.3, -2, -0.3]]\n"
            "B = [[0], [1], [0], [0]]\nC = [[1, 0, 0, 0]]\n"
            "[command]\nkind = \"sine\"\namplitude = 1.0\nfrequency_hz = 0.3\n"
            "[process.white]\nstd = 0.5\n[sensor.white]\nstd = 0.003\n")
    nominal = parse_model(base)
    rec = parse_model(base + "[actuator.white]\nstd = 0.4\n").simulate(6000, seed=2)
    S = Search(nominal, Data(rec.y, rec.u, nominal.Ts, True))
    cands = S.candidates(S.start())
    by = {(c.effect, str(c.mode)): c for c in cands}
    add, refit = by[("actuator.white", "add")], by[("process.white", "refit")]
    assert add.score == pytest.approx(refit.score, rel=1e-9, abs=1e-9) and add.score > THRESHOLD
    assert max(c.sel for c in cands) > add.sel + EXACT_TIE          # the case: a third candidate leads
    assert cands[0] is add
    assert "process.white" in [a.effect for a in add.alternatives]


def test_the_leaders_exact_add_refit_tie_goes_before_the_mode_order():
    """Generated case 8: process noise hidden (absent from the nominal, which has actuator white
    noise through the same input). Adding it and refitting the actuator noise tie exactly and lead;
    a replacement of the actuator noise by a near-white AR(1) sits within the near-tie margin, and
    the mode order alone would take it. The leader's tie comes first: the process noise is added
    (the first version of the chosen-candidate rule reported the AR(1))."""
    from noiselab.diagnose.thresholds import TIE
    case = make_case(8)
    truth, nominal = parse_model(case.truth, "truth"), parse_model(case.nominal, "nominal")
    assert "process.white" not in nominal.effects and "actuator.white" in nominal.effects
    rec = truth.simulate(int(round(case.duration / truth.Ts)), seed=case.seed)
    S = Search(nominal, Data(rec.y, rec.u, nominal.Ts, True))
    cands = S.candidates(S.start())
    assert (cands[0].effect, str(cands[0].mode)) == ("process.white", "add")
    assert any(c.mode.kind == "replace" and abs(c.sel - cands[0].sel) < TIE for c in cands[1:])


def test_a_candidate_ties_with_itself_at_any_score():
    """A model without sensor noise scores adding it at Delta BIC ~7e15, where floats are spaced by
    1: 'key(c) > key(lead) - 0.5' was False for c = lead, and the ranking's min() over the tied
    candidates crashed (a two-output motor of the integrator bench, seed 9)."""
    from types import SimpleNamespace

    from noiselab.diagnose.search import exact_tie
    for s in (12.5, 7432835967802488.0, 1e17):
        c = SimpleNamespace(score=s, k=2)
        assert exact_tie(c, c, lambda x: x.score)
        assert not exact_tie(SimpleNamespace(score=s - 1.0 - 0.01 * s, k=2), c, lambda x: x.score)


def test_ceiling_crb_matches_the_gauss_markov_closed_form():
    """tests/bench/bench_ceiling.py bounds the 30 % criterion with a Whittle Cramer-Rao bound. For a
    Gauss-Markov bias (AR(1), phi = exp(-Ts / tau)) observed over N samples, with its std a nuisance
    parameter and a sensor noise 1e4 below it, the bound on tau is the AR(1)'s: Var(phi) =
    (1 - phi^2) / N (the AR(1) maximum-likelihood estimate, Brockwell & Davis 1991 ch. 8), so
    sd(ln tau) = sqrt((1 - phi^2) / N) tau / (phi Ts) ~ sqrt(2 tau / T). A nuisance of the same
    spectral shape as the planted parameter is left out: with a process noise and an actuator noise
    through one input, the planted one stands for both (its bound finite, not singular)."""
    from bench_ceiling import crb_log_sd, within_30

    Ts, tau, N = 0.01, 1.0, 200_000
    m = parse_model("name = \"gm\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-1.0]]\nB = [[1.0]]\nC = [[1.0]]\n"
                    "[sensor.bias_markov]\nstd = 0.1\ntau_s = 1.0\n[sensor.white]\nstd = 1e-5\n")
    sd = crb_log_sd(m, N * Ts, ("sensor.bias_markov",))
    phi = math.exp(-Ts / tau)
    want = math.sqrt((1 - phi**2) / N) * tau / (phi * Ts)
    assert sd[("sensor.bias_markov", "tau_s")] == pytest.approx(want, rel=0.02)
    assert want == pytest.approx(math.sqrt(2 * tau / (N * Ts)), rel=0.01)
    assert within_30(1e-3) == pytest.approx(1.0) and within_30(10.0) < 0.05
    tie = parse_model("name = \"tie\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 0.5\nk = 4.0\n"
                      "[process.white]\nstd = 0.5\n[actuator.white]\nstd = 0.5\n[sensor.white]\nstd = 0.01\n")
    assert set(crb_log_sd(tie, 600.0, ("process.white",))) == {("process.white", "std"), ("sensor.white", "std")}
    assert crb_log_sd(tie, 600.0, ("process.white",))[("process.white", "std")] < 0.1
    # a std per input: one parameter per element, bounded where the inputs reach the output through
    # modes of their own, unbounded where they share one column (only their sum is seen)
    two = lambda B: parse_model("name = \"two\"\n[sampling]\nTs = 0.01\n[plant]\nA = [[-1.0, 0.0], [0.0, -10.0]]\n"
                                f"B = {B}\nC = [[1.0, 1.0]]\n[actuator.white]\nstd = [0.1, 0.2]\n[sensor.white]\nstd = 0.001\n")
    own = crb_log_sd(two("[[1.0, 0.0], [0.0, 1.0]]"), 600.0, ("actuator.white",))
    shared = crb_log_sd(two("[[1.0, 1.0], [0.0, 0.0]]"), 600.0, ("actuator.white",))
    assert {k for k in own if k[0] == "actuator.white"} == {("actuator.white", "std[0]"), ("actuator.white", "std[1]")}
    assert max(own[("actuator.white", "std[0]")], own[("actuator.white", "std[1]")]) < 0.1
    assert min(shared[("actuator.white", "std[0]")], shared[("actuator.white", "std[1]")]) > 100


def test_a_command_of_the_wrong_width_is_bad_input():
    """A recorded command with another number of components than the model's inputs is named as
    bad input (the CLI's exit 2), before any fitting; it crashed in the mean response."""
    from noiselab.diagnose.compare import AnalysisError

    model = parse_model("name = \"w\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.2\nc = 0.35\nk = 4.0\n"
                        "[command]\nkind = \"sine\"\namplitude = 2.0\nfrequency_hz = 0.7\n[sensor.white]\nstd = 0.001\n")
    rec = model.simulate(2000, seed=3)
    for u in (np.zeros((2000, 2)), np.zeros((2000, 0))):
        with pytest.raises(AnalysisError, match=f"command has {u.shape[1]} components, the model 1 inputs"):
            diagnose(model, rec.t, rec.y, u)


def test_a_driven_record_that_does_not_start_at_rest_skips_the_mean_responses_transient():
    """A record cut from the middle of a stream (the longest run after a gap) is no longer at
    rest, but its command's predicted mean response still starts from zero: the views skip that
    transient. The right model on the cut record reads about 1 (it read 109 when the views
    started at its first sample: the transient's mismatch against a sensor noise of 0.001)."""
    model = parse_model("name = \"msd\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.2\nc = 0.35\nk = 4.0\n"
                        "[command]\nkind = \"sine\"\namplitude = 2.0\nfrequency_hz = 0.7\n[sensor.white]\nstd = 0.001\n"
                        "[actuator.white]\nstd = 0.02\n[process.white]\nstd = 0.2\n")
    rec = model.simulate(13_000, seed=5)
    cut = slice(1000, None)
    from noiselab.diagnose.compare import compare

    whole = compare(model, rec.t, rec.y, rec.u, burn=None, level=True)
    assert whole.error < 1.5
    at0 = compare(model, rec.t[cut] - rec.t[1000], rec.y[cut], rec.u[cut], burn=0)
    assert at0.error > 10                       # the transient left in: the mismatch this avoids
    rep = diagnose(model, rec.t[cut] - rec.t[1000], rec.y[cut], rec.u[cut], at_rest=False)
    assert rep["missing"] == [] and rep["error_before"] < 1.5


@pytest.mark.slow
def test_a_fast_plant_cut_mid_stream_starts_from_its_fitted_mean_state():
    """The audit's fast plant with feed-through (poles at -2 +- 4.6j rad/s, D = 0.05; here behind
    an actuator lag of 50 ms) under a sine of 1, sensor noise 0.002, cut mid-stream. The burn
    (the model's covariance within 1 % of stationary) leaves 10 % of the transient between the
    command's mean response from zero and the plant, 50x the noise: the right model read 4013 on
    the audit's record. The mean state where the analysis starts (the plant's and the lag's) is
    now fitted by least squares, one regressor per state. The right model then reads about 1: the
    mean of 6 records within 3 standard errors of 1 (one record's error spread 0.29, measured over
    10 seeds); and a missing lag is found with its time constant inside its interval, the model
    error falling to about 1."""
    from noiselab.diagnose.compare import compare
    plant = ('name = "g"\n[sampling]\nTs = 0.005\n[plant]\nA = [[0.0, 1.0], [-25.0, -4.0]]\nB = [[0.0], [25.0]]\n'
             'C = [[1.0, 0.0]]\nD = [[0.05]]\nL = [[0.5], [2.0]]\n[command]\nkind = "sine"\namplitude = 1.0\n'
             'frequency_hz = 0.5\n[process.white]\nstd = 0.05\n[sensor.white]\nstd = 0.002\n')
    truth = parse_model(plant + "[actuator.lag]\ntau_s = 0.05\n", "truth")
    errors = []
    for seed in range(6):
        rec = truth.simulate(20_000, seed=seed)
        t, y, u = rec.t[3000:] - rec.t[3000], rec.y[3000:], rec.u[3000:]
        assert compare(truth, t, y, u, burn=None).error > 100            # the transient left after the burn
        cmp = compare(truth, t, y, u, burn=None, free_start=True)
        assert any("mean state fitted" in n for n in cmp.notes), cmp.notes
        errors.append(cmp.error)
    assert np.mean(errors) < 1 + 3 * 0.29 / np.sqrt(6), errors
    rec = truth.simulate(20_000, seed=4)
    rep = diagnose(truth.without_effect("actuator.lag"), rec.t[3000:] - rec.t[3000], rec.y[3000:], rec.u[3000:],
                   at_rest=False)
    assert [m["effect"] for m in rep["missing"]] == ["actuator.lag"]
    lo, hi = rep["missing"][0]["interval"]["tau_s"]
    assert lo <= 0.05 <= hi and rep["error_after"] <= 1.5 < rep["error_before"]


def test_refitting_what_the_model_has_does_not_spend_the_budget_of_what_it_lacks():
    """A gyro read through a quantizer, with a line, whose model has only a white noise written 2x
    too high (a datasheet's typical value): the quantizer is added, the white noise refitted, and
    the line added. With a budget of two additions (``max_effects=2``) both missing effects are
    reported beside the refit: the refit finds no new physics and is not counted."""
    truth = parse_model('name = "g"\n[sampling]\nTs = 0.01\n[outputs]\nnames = ["gyro_x"]\nunits = ["rad/s"]\n'
                        "[sensor.white]\nstd = 0.0013\n[sensor.tone]\namplitude = 0.0006\nfrequency_hz = 31.0\n"
                        "[sensor.quantization]\nstep = 0.002\n")
    nominal = parse_model(truth.without_effect("sensor.quantization").without_effect("sensor.tone").to_toml()
                          .replace("std = 0.0013", "std = 0.0026"))
    rec = truth.simulate(18_000, seed=44)
    logs = []
    rep = diagnose(nominal, rec.t, rec.y, rec.u, max_effects=2, log=logs.append)
    modes = {m["effect"]: m["mode"] for m in rep["missing"]}
    assert modes == {"sensor.quantization": "add", "sensor.white": "refit", "sensor.tone": "add"}, (modes, logs)
    got = {m["effect"]: m for m in rep["missing"]}
    assert got["sensor.white"]["params"]["std"] == pytest.approx(0.0013, rel=0.05)
    assert got["sensor.tone"]["params"]["frequency_hz"] == pytest.approx(31.0, abs=0.01)
    assert rep["error_after"] <= 1.5
    # the same diagnosis with a budget of one addition stops after it (and the refit, if it came first)
    one = diagnose(nominal, rec.t, rec.y, rec.u, max_effects=1)
    assert sum(m["mode"] != "refit" for m in one["missing"]) == 1
