"""A generator of hidden-effect cases like the independent evaluation set of issue 5: random plants
(mass-spring-dampers and general A, B, C plants with one or two outputs), sample periods of 2 to
20 ms, records of 1 to 10 minutes, one or two effects hidden from the nominal model (absent, or
present with a wrong value), and null cases (nominal = truth).

Magnitudes are set relative to the nominal model's own noise (its predicted var_y; for a plant
that integrates, which has none, the variance its output accrues over 1 s), so that a hidden
effect is visible but not dominant: a test designer's "detectable" range, not ours to tune.
Used by ``bench_diagnose.py`` (hit rates, times) and, with a few fixed seeds, by the tests.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass

import numpy as np

from noiselab.model import parse_model
from noiselab.model.effects.base import _map
from noiselab.model.model import dumps_toml

PERIODS = (0.002, 0.005, 0.01, 0.02)
NEEDS_COMMAND = ("actuator.lag", "actuator.saturation", "actuator.deadzone", "sensor.scale_factor",
                 "sensor.jitter")
HIDEABLE = ("process.white", "actuator.white", "actuator.ar1", "actuator.lag", "actuator.saturation",
            "actuator.deadzone", "sensor.scale_factor", "sensor.bias_walk", "sensor.bias_markov",
            "sensor.white", "sensor.tone", "sensor.jitter", "sensor.quantization")


@dataclass
class Case:
    name: str
    truth: str                 # model file text
    nominal: str
    hidden: dict               # effect id -> planted params ({} for a null case)
    duration: float
    seed: int


def _plant(rng, Ts):
    """A plant whose dynamics sit well inside the band [1/T, Nyquist]."""
    kind = rng.choice(["msd", "msd", "general2", "general_two_outputs", "first_order", "two_mass"])
    fmax = 0.08 / Ts                      # natural frequencies up to ~1/12 of the sample rate
    if kind == "msd":
        fn = float(np.exp(rng.uniform(np.log(0.2), np.log(min(3.0, fmax)))))
        zeta = float(rng.uniform(0.05, 0.6))
        m = float(np.exp(rng.uniform(np.log(0.3), np.log(5.0))))
        k = m * (2 * np.pi * fn) ** 2
        c = 2 * zeta * math.sqrt(k * m)
        return {"m": round(m, 4), "c": round(c, 4), "k": round(k, 4)}, fn, 1
    if kind == "first_order":
        tau = float(np.exp(rng.uniform(np.log(0.05), np.log(3.0))))
        gain = float(rng.uniform(0.5, 3.0))
        return {"A": [[-1 / tau]], "B": [[gain / tau]], "C": [[1.0]], "L": [[1.0 / tau]]}, 1 / (2 * np.pi * tau), 1
    if kind == "two_mass":
        w1 = 2 * np.pi * float(rng.uniform(0.3, min(2.0, fmax)))
        k1, k2, m1, m2, c1, c2 = w1**2, w1**2 * rng.uniform(0.5, 2), 1.0, rng.uniform(0.5, 2), 0.3 * w1, 0.2 * w1
        A = [[0, 1, 0, 0], [-(k1 + k2) / m1, -(c1 + c2) / m1, k2 / m1, c2 / m1],
             [0, 0, 0, 1], [k2 / m2, c2 / m2, -k2 / m2, -c2 / m2]]
        return {"A": np.round(A, 5).tolist(), "B": [[0.0], [1.0], [0.0], [0.0]], "C": [[0.0, 0.0, 1.0, 0.0]],
                "L": [[0.0], [0.0], [0.0], [1.0 / m2]]}, w1 / (2 * np.pi), 1
    # general second order in modal-ish coordinates, one or two outputs
    wn = 2 * np.pi * float(np.exp(rng.uniform(np.log(0.2), np.log(min(3.0, fmax)))))
    zeta = float(rng.uniform(0.1, 0.8))
    A = [[0.0, 1.0], [-wn**2, -2 * zeta * wn]]
    B = [[0.0], [float(rng.uniform(0.5, 2.0)) * wn**2]]
    L = [[float(rng.uniform(0.1, 1.0)) * wn], [0.0]]            # disturbance enters the first state
    C = [[1.0, 0.0], [0.0, 0.1]] if kind == "general_two_outputs" else [[1.0, 0.0]]
    return {"A": np.round(A, 5).tolist(), "B": np.round(B, 5).tolist(), "C": C, "L": np.round(L, 5).tolist()}, \
        wn / (2 * np.pi), len(C)


def _mode(rng, w: float, p_pair: float, zeta_lo: float, room: bool = True) -> np.ndarray:
    """One modal block at angular frequency w: a complex pair (damping ratio log-uniform in
    [zeta_lo, 0.7]) with probability p_pair when there is room for two states, else a real pole."""
    if rng.random() < p_pair and room:
        zeta = float(np.exp(rng.uniform(np.log(zeta_lo), np.log(0.7))))
        return np.array([[-zeta * w, w * math.sqrt(1 - zeta**2)], [-w * math.sqrt(1 - zeta**2), -zeta * w]])
    return np.array([[-w]])


def _turned(rng, blocks, freqs):
    """(A, B, L, Tm, Tm^-1): the modal blocks on A's diagonal turned by a random similarity
    transform Tm (condition number at most 20), and an input and a disturbance input of the size
    of the median mode's angular frequency, in the turned coordinates."""
    n = sum(b.shape[0] for b in blocks)
    A = np.zeros((n, n))
    i = 0
    for b in blocks:
        A[i:i + b.shape[0], i:i + b.shape[0]] = b
        i += b.shape[0]
    Tm = np.eye(n) + 0.4 * rng.standard_normal((n, n))
    while np.linalg.cond(Tm) > 20:
        Tm = np.eye(n) + 0.4 * rng.standard_normal((n, n))
    Ti = np.linalg.inv(Tm)
    w0 = 2 * np.pi * float(np.median(freqs))
    B = Tm @ (w0 * rng.uniform(0.5, 2.0, (n, 1)) * rng.choice([-1, 1], (n, 1)))
    Lp = Tm @ (w0 * rng.uniform(0.1, 1.0, (n, 1)))
    return Tm @ A @ Ti, B, Lp, Tm, Ti


def _plant_other(rng, Ts, T):
    """Plants the generator above does not draw (``make_case(..., plants="other")``): general A, B, C,
    D plants of order 2 to 5 built from 1 to 3 modes (complex pairs with damping ratios down to 0.01,
    log-uniform, and real poles), turned by a random similarity transform so that A is full, with a
    feedthrough D in a third of them and one or two outputs; and lightly damped mass-spring-dampers
    (zeta 0.01 to 0.05). Modes sit between 10 / T and 1/12 of the sample rate."""
    fmax = min(3.0, 0.08 / Ts)
    fmin = min(max(0.1, 10.0 / T), fmax / 2)
    logf = lambda: float(np.exp(rng.uniform(np.log(fmin), np.log(fmax))))  # noqa: E731
    if rng.random() < 0.25:
        fn = logf()
        zeta = float(np.exp(rng.uniform(np.log(0.01), np.log(0.05))))
        m = float(np.exp(rng.uniform(np.log(0.3), np.log(5.0))))
        k = m * (2 * np.pi * fn) ** 2
        return {"m": round(m, 4), "c": float(f"{2 * zeta * math.sqrt(k * m):.4g}"), "k": round(k, 4)}, fn, 1
    blocks, freqs = [], []
    for _ in range(int(rng.integers(1, 4))):
        f = logf()
        freqs.append(f)
        w = 2 * np.pi * f
        blocks.append(_mode(rng, w, 0.7, 0.01, room=sum(b.shape[0] for b in blocks) <= 3))
    A, B, Lp, Tm, Ti = _turned(rng, blocks, freqs)
    n = A.shape[0]
    p = 2 if rng.random() < 0.3 else 1
    C = rng.uniform(-1, 1, (p, n)) @ Ti
    plant = {"A": _sig(A), "B": _sig(B), "C": _sig(C), "L": _sig(Lp)}
    if rng.random() < 1 / 3:
        # a direct term: of the order of the plant's own gain at its mode
        gain = np.abs(C @ np.linalg.solve(-A, B))
        plant["D"] = _sig(rng.uniform(0.05, 0.3, (p, 1)) * np.maximum(gain, 1e-3))
    return plant, float(np.min(freqs)), p


def _plant_integrator(rng, Ts, T):
    """Plants with an integrator (``make_case(..., plants="integrator")``), which the generator above
    never draws: a DC motor's position (a pole at 0 and one at -1/tau, the input a torque, the
    disturbance the same torque), with its velocity as a second output in a third of them; or a
    general A, B, C plant with an eigenvalue 0 beside one or two stable modes, turned by a random
    similarity transform (A kept to 9 significant digits so that the zero stays within 1e-8 of
    its modes). Modes sit between 10 / T and 1/12 of the sample rate."""
    fmax = min(3.0, 0.08 / Ts)
    fmin = min(max(0.1, 10.0 / T), fmax / 2)
    logf = lambda: float(np.exp(rng.uniform(np.log(fmin), np.log(fmax))))  # noqa: E731
    if rng.random() < 0.5:
        f = logf()
        a = 2 * np.pi * f
        K = float(rng.uniform(0.5, 3.0))
        p = 2 if rng.random() < 1 / 3 else 1
        C = [[1.0, 0.0], [0.0, 0.1]] if p == 2 else [[1.0, 0.0]]
        return {"A": [[0.0, 1.0], [0.0, float(f"{-a:.5g}")]], "B": [[0.0], [float(f"{K * a:.5g}")]], "C": C}, f, p
    blocks, freqs = [np.zeros((1, 1))], []
    for _ in range(int(rng.integers(1, 3))):
        f = logf()
        freqs.append(f)
        w = 2 * np.pi * f
        blocks.append(_mode(rng, w, 0.6, 0.05))
    A, B, Lp, Tm, Ti = _turned(rng, blocks, freqs)
    n = A.shape[0]
    C = rng.uniform(-1, 1, (1, n)) @ Ti
    C[0] += Ti[0] * np.sign(C[0] @ Tm[:, 0]) * 0.5      # the integrator seen at the output
    plant = {"A": [[float(f"{v:.9g}") for v in row] for row in A], "B": _sig(B), "C": _sig(C), "L": _sig(Lp)}
    return plant, float(np.min(freqs)), 1


def _plant_inputs(rng, Ts, T):
    """Plants with two inputs (``make_case(..., plants="inputs")``), which the generators above never
    draw: a general A, B, C plant of order 1 to 4 from 1 or 2 modes (a real pole or a pair each), turned by a random similarity
    transform, each input reaching the states through its own random column of B, one or two
    outputs; the process noise enters through its own input L in half of them and through both
    command inputs (L = B, the default) in the other half. The command drives both inputs alike.
    Modes sit between 10 / T and 1/12 of the sample rate."""
    fmax = min(3.0, 0.08 / Ts)
    fmin = min(max(0.1, 10.0 / T), fmax / 2)
    blocks, freqs = [], []
    for _ in range(int(rng.integers(1, 3))):
        f = float(np.exp(rng.uniform(np.log(fmin), np.log(fmax))))
        freqs.append(f)
        blocks.append(_mode(rng, 2 * np.pi * f, 0.7, 0.05))
    A, B1, Lp, Tm, Ti = _turned(rng, blocks, freqs)
    n = A.shape[0]
    w0 = 2 * np.pi * float(np.median(freqs))
    B2 = Tm @ (w0 * rng.uniform(0.5, 2.0, (n, 1)) * rng.choice([-1, 1], (n, 1)))
    p = 2 if rng.random() < 0.4 else 1
    C = rng.uniform(-1, 1, (p, n)) @ Ti
    plant = {"A": _sig(A), "B": _sig(np.hstack([B1, B2])), "C": _sig(C)}
    if rng.random() < 0.5:
        plant["L"] = _sig(Lp)
    return plant, float(np.min(freqs)), p


def _sig(X) -> list:
    """A matrix as nested lists of floats to 5 significant digits (what a model file holds)."""
    return [[float(f"{v:.5g}") for v in row] for row in np.atleast_2d(X)]


def _command(rng, fn, Ts, T, with_command):
    if not with_command:
        return {"kind": "none"}
    kind = rng.choice(["sine", "sine", "chirp", "prbs"])
    amp = float(rng.uniform(0.5, 2.0))
    if kind == "sine":
        return {"kind": "sine", "amplitude": amp, "frequency_hz": round(float(fn * rng.uniform(0.3, 1.5)), 4)}
    if kind == "chirp":
        return {"kind": "chirp", "amplitude": amp, "f0_hz": round(fn * 0.2, 4),
                "f1_hz": round(min(fn * 3, 0.2 / Ts), 4), "duration_s": round(float(min(T / 3, 60.0)), 2)}
    return {"kind": "prbs", "amplitude": amp, "bit_s": round(float(max(Ts * 2, 0.25 / fn)), 4), "order": 9}


def _doc(name, Ts, plant, command, effects):
    d = {"name": name, "sampling": {"Ts": Ts}, "plant": plant, "command": command}
    for eid, params in effects.items():
        g, s = eid.split(".")
        d.setdefault(g, {})[s] = params
    return dumps_toml(d)


def _contribution(text, eid):
    """The variance effect ``eid`` adds to the output: its steady-state one; for a plant that
    integrates, the variance its part of the output accrues over one second, 2 gamma(1 s)."""
    m = parse_model(text)
    st = m.predictor().steady_state()
    c = st.contributions.get(eid)
    if (c is None or np.any(np.isnan(c))) and eid in st.contributions and not st.stable:
        # (NaN: at an output the plant's walk reaches; the growth over 1 s, as for every output)
        g = m.predictor().variogram(int(round(1.0 / m.Ts)) + 1, quantization=False).get(eid)
        c = None if g is None else 2.0 * g[-1]
    return None if c is None else float(np.max(c))


def _scale(text) -> float:
    """The nominal model's output variance (steady state; for a plant that integrates, over 1 s)."""
    st = parse_model(text).predictor().steady_state()
    if st.var_y is not None and np.all(np.isfinite(st.var_y)):
        return float(np.max(st.var_y))
    return sum(_contribution(text, eid) for eid in st.contributions)


def make_case(seed: int, n_hidden: int | None = None, null: bool | None = None, plants: str = "generator") -> Case:
    """Case ``seed``. ``plants="other"``: the plant drawn by :func:`_plant_other` (its own random
    stream), everything else drawn as for the generator's plant (so the same effects are hidden)."""
    rng = np.random.default_rng(seed)
    Ts = float(rng.choice(PERIODS))
    T = float(np.round(rng.uniform(60, 600) / 10) * 10)
    plant, fn, p = _plant(rng, Ts)
    if plants == "other":
        plant, fn, p = _plant_other(np.random.default_rng([seed, 17]), Ts, T)
    elif plants == "integrator":
        plant, fn, p = _plant_integrator(np.random.default_rng([seed, 19]), Ts, T)
    elif plants == "inputs":
        plant, fn, p = _plant_inputs(np.random.default_rng([seed, 23]), Ts, T)
    elif plants != "generator":
        raise ValueError(f"plants: expected 'generator', 'other', 'integrator' or 'inputs', got {plants!r}")
    null = bool(rng.random() < 0.2) if null is None else null
    n_hidden = (1 if rng.random() < 0.6 else 2) if n_hidden is None else n_hidden
    with_command = bool(rng.random() < 0.85)
    command = _command(rng, fn, Ts, T, with_command)
    base = {"process.white": {"std": 1.0}, "sensor.white": {"std": 1.0}}
    if rng.random() < 0.3:
        base["actuator.white"] = {"std": 1.0}
    # scale the nominal noise: process noise to a chosen output variance, sensor noise a fraction of it
    text = _doc("case", Ts, plant, command, base)
    c_proc = _contribution(text, "process.white")
    target = 1e-4 * float(np.exp(rng.uniform(0, np.log(100))))
    base["process.white"]["std"] = float(f"{math.sqrt(target / c_proc):.4g}")
    base["sensor.white"]["std"] = float(f"{math.sqrt(target * rng.uniform(0.05, 0.5)):.4g}")
    if "actuator.white" in base:
        c_act = _contribution(_doc("case", Ts, plant, command, {"actuator.white": {"std": 1.0}}), "actuator.white")
        base["actuator.white"]["std"] = float(f"{math.sqrt(target * rng.uniform(0.3, 1.0) / c_act):.4g}")
    nominal = dict(base)
    var0 = _scale(_doc("case", Ts, plant, command, nominal))
    sd0 = math.sqrt(var0)
    truth = {k: dict(v) for k, v in nominal.items()}
    hidden: dict = {}
    if not null:
        pool = [e for e in HIDEABLE if with_command or e not in NEEDS_COMMAND]
        if command.get("kind") == "prbs":
            # a two-level command passes a saturation or a dead zone as a pure gain on the command
            # (+-A -> +-L, +-(A - d)): a scale factor of the same size, so no data can tell them
            # apart; such a case tests nothing but a tie-break
            pool = [e for e in pool if e not in ("actuator.saturation", "actuator.deadzone")]
        order = rng.permutation(pool)
        for eid in order:
            if len(hidden) >= n_hidden:
                break
            if eid in ("sensor.bias_walk", "sensor.bias_markov") and any(
                    h in hidden for h in ("sensor.bias_walk", "sensor.bias_markov")):
                continue
            if eid in ("actuator.saturation", "actuator.deadzone") and any(
                    h in hidden for h in ("actuator.saturation", "actuator.deadzone")):
                continue
            params = _hidden_params(rng, eid, Ts, T, plant, command, nominal, var0, sd0, fn)
            if params is None:
                continue
            hidden[eid] = params
            params = {k: v for k, v in params.items() if not k.startswith("_")}
            if eid in ("process.white", "sensor.white") and eid in nominal:
                # present with a wrong value: the truth's is larger
                truth[eid] = params
            elif eid == "actuator.ar1" and "actuator.white" in nominal and rng.random() < 0.5:
                truth.pop("actuator.white")             # white actuator noise that is really colored
                truth[eid] = params
                hidden[eid] = dict(params, mode="replace:actuator.white")
            else:
                truth[eid] = params
    for eid in ("process.white", "sensor.white"):
        if eid in hidden and hidden[eid].get("_absent"):
            nominal.pop(eid)
            hidden[eid] = {k: v for k, v in hidden[eid].items() if k != "_absent"}
            truth[eid] = hidden[eid]
    name = f"case{seed}" + ("" if plants == "generator" else f"-{plants}")
    return Case(name, _doc("case", Ts, plant, command, truth), _doc("case", Ts, plant, command, nominal),
                {k: {kk: vv for kk, vv in v.items() if not kk.startswith("_")} for k, v in hidden.items()},
                T, seed + 1000)


def _hidden_params(rng, eid, Ts, T, plant, command, nominal, var0, sd0, fn):
    f = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))       # contribution relative to var0
    umax = float(command.get("amplitude", 0.0))
    if eid == "sensor.white":
        cur = nominal["sensor.white"]["std"]
        if rng.random() < 0.5:                                      # absent from the nominal
            return {"std": float(f"{math.sqrt(cur**2 + f * var0):.4g}"), "_absent": True}
        return {"std": float(f"{math.sqrt(cur**2 + f * var0):.4g}")}
    if eid == "process.white":
        cur = nominal["process.white"]["std"]
        return {"std": float(f"{cur * math.sqrt(1 + f):.4g}"), "_absent": rng.random() < 0.5}
    if eid in ("actuator.white", "actuator.ar1"):
        if "actuator.white" in nominal and eid == "actuator.white":
            return None
        tau = None
        if eid == "actuator.ar1":
            tau = float(np.exp(rng.uniform(np.log(5 * Ts), np.log(max(6 * Ts, 0.5 / fn)))))
        params = {"std": 1.0} if tau is None else {"std": 1.0, "tau_s": float(f"{tau:.4g}")}
        m = len(plant["B"][0]) if "B" in plant else 1
        if m > 1:
            # several inputs: each its own std, the smaller 0.1 to 1 times the larger
            params["std"] = [float(x) for x in rng.permutation([1.0] + list(rng.uniform(0.1, 1.0, m - 1)))]
        c = _contribution(_doc("c", Ts, plant, command, {eid: params}), eid)
        params["std"] = _map(lambda s: float(f"{s * math.sqrt(f * var0 / c):.4g}"), params["std"])
        return params
    if eid == "sensor.bias_walk":
        return {"std": float(f"{math.sqrt(f * var0 / T) * 2:.4g}")}
    if eid == "sensor.bias_markov":
        tau = float(np.exp(rng.uniform(np.log(T / 60), np.log(T / 6))))
        return {"std": float(f"{math.sqrt(f * var0):.4g}"), "tau_s": float(f"{tau:.4g}")}
    if eid == "sensor.tone":
        nyq = 0.5 / Ts
        ftone = float(rng.uniform(0.05, 0.8) * nyq)
        return {"amplitude": float(f"{math.sqrt(2 * f * var0) * 0.5:.4g}"), "frequency_hz": float(f"{ftone:.4g}")}
    if eid == "sensor.quantization":
        return {"step": float(f"{sd0 * rng.uniform(0.2, 1.0):.3g}")}
    if eid == "sensor.scale_factor":
        return {"error": float(f"{rng.choice([-1, 1]) * rng.uniform(0.03, 0.15):.3g}")}
    if eid == "actuator.lag":
        fc = command.get("frequency_hz") or command.get("f1_hz") or (0.5 / command.get("bit_s", 1.0))
        phi = np.deg2rad(rng.uniform(10, 40))
        tau = max(math.tan(phi) / (2 * np.pi * fc), 2 * Ts)
        return {"tau_s": float(f"{tau:.4g}")}
    if eid == "actuator.saturation":
        return {"limit": float(f"{umax * rng.uniform(0.5, 0.85):.4g}")} if umax else None
    if eid == "actuator.deadzone":
        return {"width": float(f"{umax * rng.uniform(0.05, 0.3):.4g}")} if umax else None
    if eid == "sensor.jitter":
        m = parse_model(_doc("c", Ts, plant, command, nominal))
        yd = m.predictor().mean_response(int(min(T, 60) / Ts)).ydot
        ydot2 = float(np.mean(yd**2))
        sv = nominal["sensor.white"]["std"] ** 2
        if ydot2 <= 0:
            return None
        std_s = math.sqrt(f * sv / ydot2)
        if std_s > Ts / 3:
            return None
        return {"std_s": float(f"{std_s:.4g}")}
    return None


SENSOR_HIDEABLE = ("sensor.white", "sensor.bias_walk", "sensor.bias_markov", "sensor.bias_instability",
                   "sensor.integral_white", "sensor.tone", "sensor.quantization", "sensor.filter")
DRIFTS = ("sensor.bias_walk", "sensor.bias_markov", "sensor.bias_instability")


def _sensor_doc(name, Ts, effects) -> str:
    """A sensor-only model (one rate output at rest, no [plant]) with ``effects``."""
    d = {"name": name, "sampling": {"Ts": Ts}, "outputs": {"names": ["rate"], "units": ["rad/s"]},
         "command": {"kind": "none"}}
    for eid, params in effects.items():
        g, s = eid.split(".")
        d.setdefault(g, {})[s] = params
    return dumps_toml(d)


def make_sensor_case(seed: int, n_hidden: int | None = None, null: bool | None = None) -> Case:
    """Case ``seed`` of the sensor-only family: a rate sensor at rest (a gyro axis: no plant, no
    command), sample periods of 2 to 20 ms, records of 1 to 10 minutes, its nominal model a white
    noise, and one or two of :data:`SENSOR_HIDEABLE` hidden (at most one slow drift: a walk, a
    Gauss-Markov bias and a flicker bias over the same band are the Allan practice's own ambiguity).

    Magnitudes relative to the white noise (per-sample std s, one-sided density 2 s^2 Ts), as for
    the generator's cases, by where the hidden effect meets it (the sensor's own filter: a kind
    drawn, a moving average of 2 to 8 taps or a cutoff at 5 % to 30 % of the sample rate, shaping
    the white noise): a flicker bias's Allan floor
    0.664 B crosses the white descent s sqrt(Ts / tau) at tau_c log-uniform in [30 Ts, T / 30] (a
    decade of floor or more in the record); the integral's white noise is f times the white density
    at Nyquist (8 Q^2 / Ts = f 2 s^2 Ts, f in [0.3, 3]); the other effects as :func:`make_case`
    draws them against the same variance. Its own random stream (``[seed, 29]``): the generator's
    cases are unchanged."""
    rng = np.random.default_rng([seed, 29])
    Ts = float(rng.choice(PERIODS))
    T = float(np.round(rng.uniform(60, 600) / 10) * 10)
    null = bool(rng.random() < 0.2) if null is None else null
    n_hidden = (1 if rng.random() < 0.6 else 2) if n_hidden is None else n_hidden
    sd = float(f"{10 ** rng.uniform(-4, -2):.4g}")          # rad/s per sample
    nominal = {"sensor.white": {"std": sd}}
    truth = {k: dict(v) for k, v in nominal.items()}
    hidden: dict = {}
    for eid in ([] if null else [str(e) for e in rng.permutation(SENSOR_HIDEABLE)]):
        if len(hidden) >= n_hidden:
            break
        if eid in DRIFTS and any(h in DRIFTS for h in hidden):
            continue
        f = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
        var0 = sd**2
        if eid == "sensor.bias_instability":
            tau_c = float(np.exp(rng.uniform(np.log(30 * Ts), np.log(T / 30))))
            params = {"B": float(f"{sd * math.sqrt(Ts / tau_c) / 0.6643:.4g}")}
        elif eid == "sensor.integral_white":
            params = {"Q": float(f"{sd * Ts * math.sqrt(f) / 2:.4g}")}
        elif eid == "sensor.filter":
            kind = str(rng.choice(["lowpass1", "lowpass2", "average"]))
            params = {"kind": kind, "taps": int(rng.integers(2, 9))} if kind == "average" else \
                {"kind": kind, "cutoff_hz": float(f"{rng.uniform(0.05, 0.3) / Ts:.4g}")}
        else:
            params = _hidden_params(rng, eid, Ts, T, None, {}, nominal, var0, sd, None)
        if params is None:
            continue
        params.pop("_absent", None)          # the white noise stays in the nominal model, at a wrong value
        hidden[eid] = params
        truth[eid] = params
    return Case(f"case{seed}-sensor", _sensor_doc("case", Ts, truth), _sensor_doc("case", Ts, nominal),
                {k: dict(v) for k, v in hidden.items()}, T, seed + 2000)


@dataclass
class ClosedCase(Case):
    """A case recorded under a discrete PID on the measurement (tests/helpers/closed_loop.py):
    gains ``kp``, ``ki``, ``kd`` and the reference ``ref`` (none, step or sine of ``amplitude`` at
    ``frequency_hz``)."""
    kp: float = 0.0
    ki: float = 0.0
    kd: float = 0.0
    ref: str = "none"
    amplitude: float = 0.0
    frequency_hz: float = 0.0
    stable: bool = True          # the truth's loop is stable (:func:`_stable_loop`)

    def record(self):
        """The truth's closed-loop record (t, y, u, r) of the case's duration and seed."""
        from helpers.closed_loop import closed_loop
        truth = parse_model(self.truth, "truth")
        return closed_loop(truth, int(round(self.duration / truth.Ts)), self.kp, self.ki, self.kd, self.seed,
                           self.ref, self.amplitude, self.frequency_hz)


CLOSED_HIDEABLE = HIDEABLE + ("sensor.bias_instability", "sensor.integral_white", "sensor.filter")


STABLE_RADIUS = 0.9995     # the loop's slowest pole: settled within a few thousand samples


def _stable_loop(text: str, kp: float, ki: float, kd: float) -> bool:
    """Whether the loop of the model ``text`` (its linear part: plant, lag, sensor gain) under the
    PID has every pole inside :data:`STABLE_RADIUS` (:func:`noiselab.model.controller.closed_loop_poles`)."""
    from helpers.closed_loop import spec

    from noiselab.model.controller import closed_loop_poles
    return bool(np.max(np.abs(closed_loop_poles(parse_model(text), spec(kp, ki, kd)))) < STABLE_RADIUS)


def make_closed_case(seed: int, n_hidden: int | None = None, null: bool | None = None) -> ClosedCase:
    """Case ``seed`` of the closed-loop family: a mass-spring-damper (the generator's ranges) whose
    command external is a PD or a PI-D on its measurement (kp = a k, a in [0.5, 5]; kd adding a
    damping ratio of 0.2 to 0.8; half of them with ki = kp w_cl / b, b in [3, 10]; gains redrawn
    until the loop settles), a reference none, step or sine; its nominal model process and sensor
    white noise, one or two of :data:`CLOSED_HIDEABLE` hidden (every effect of the catalogue), drawn
    as :func:`make_case` draws them against the open-loop variance, a saturation's or dead zone's
    size against the closed loop's own command (its 95th percentile of |u| on the nominal); a sensor
    scale factor only with a reference (step or sine) to carry it. Its own random stream
    (``[seed, 31]``)."""
    rng = np.random.default_rng([seed, 31])
    Ts = float(rng.choice(PERIODS))
    T = float(np.round(rng.uniform(60, 600) / 10) * 10)
    fn = float(np.exp(rng.uniform(np.log(0.2), np.log(min(3.0, 0.08 / Ts)))))
    zeta = float(rng.uniform(0.05, 0.6))
    mass = float(np.exp(rng.uniform(np.log(0.3), np.log(5.0))))
    k = mass * (2 * np.pi * fn) ** 2
    c = 2 * zeta * math.sqrt(k * mass)
    plant = {"m": round(mass, 4), "c": round(c, 4), "k": round(k, 4)}
    for _ in range(20):
        kp = float(k * rng.uniform(0.5, 5.0))
        wcl = math.sqrt((k + kp) / mass)
        kd = max(0.0, float(2 * rng.uniform(0.2, 0.8) * math.sqrt(mass * (k + kp)) - c * 0.0))
        ki = float(kp * wcl / rng.uniform(3.0, 10.0)) if rng.random() < 0.5 else 0.0
        if _stable_loop(_doc("c", Ts, plant, {"kind": "external"}, {}), kp, ki, kd):
            break
    else:
        kp, ki, kd = float(k), 0.0, 0.0
    ref = str(rng.choice(["none", "step", "sine"]))
    amp = float(rng.uniform(0.2, 1.0)) / (1.0 + kp / k) if ref != "none" else 0.0
    f_ref = round(float(fn * rng.uniform(0.1, 0.5)), 4) if ref == "sine" else 0.0
    null = bool(rng.random() < 0.2) if null is None else null
    n_hidden = (1 if rng.random() < 0.6 else 2) if n_hidden is None else n_hidden
    base = {"process.white": {"std": 1.0}, "sensor.white": {"std": 1.0}}
    proxy = {"kind": "sine", "amplitude": 1.0, "frequency_hz": round(fn * 0.5, 4)}
    text = _doc("case", Ts, plant, proxy, base)
    target = 1e-4 * float(np.exp(rng.uniform(0, np.log(100))))
    base["process.white"]["std"] = float(f"{math.sqrt(target / _contribution(text, 'process.white')):.4g}")
    base["sensor.white"]["std"] = float(f"{math.sqrt(target * rng.uniform(0.05, 0.5)):.4g}")
    nominal = {kk: dict(v) for kk, v in base.items()}
    case = ClosedCase(f"case{seed}-closed", _doc("case", Ts, plant, {"kind": "external"}, nominal),
                      _doc("case", Ts, plant, {"kind": "external"}, nominal), {}, T, seed + 3000,
                      kp, ki, kd, ref, amp, f_ref)
    umax = float(np.percentile(np.abs(case.record().u[: int(round(min(T, 30.0) / Ts))]), 95)) \
        if not null else 0.0
    var0 = _scale(_doc("case", Ts, plant, proxy, nominal))
    sd0 = math.sqrt(var0)
    truth = {kk: dict(v) for kk, v in nominal.items()}
    hidden: dict = {}
    command = {"kind": "sine", "amplitude": umax, "frequency_hz": round(fn * 0.5, 4)}
    for eid in ([] if null else [str(e) for e in rng.permutation(CLOSED_HIDEABLE)]):
        if len(hidden) >= n_hidden:
            break
        if eid in DRIFTS and any(h in DRIFTS for h in hidden):
            continue
        if eid == "sensor.scale_factor" and ref == "none":
            # with no reference the command is the controller's answer to the noise alone: a
            # sensor gain is then read only from the noise's shape (the residual y - G u of a
            # gain error (1 + e) is e G u plus the noise, and u is a filter of that noise), which
            # carries next to nothing (Ljung 1999, sec. 13.4: no external excitation); the
            # reference's response carries the gain, as an open loop's command does
            continue
        if eid in ("actuator.saturation", "actuator.deadzone") and any(
                h in hidden for h in ("actuator.saturation", "actuator.deadzone")):
            continue
        f = float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
        if eid == "sensor.bias_instability":
            tau_c = float(np.exp(rng.uniform(np.log(30 * Ts), np.log(T / 30))))
            sv = nominal["sensor.white"]["std"]
            params = {"B": float(f"{sv * math.sqrt(Ts / tau_c) / 0.6643:.4g}")}
        elif eid == "sensor.integral_white":
            params = {"Q": float(f"{nominal['sensor.white']['std'] * Ts * math.sqrt(f) / 2:.4g}")}
        elif eid == "sensor.filter":
            params = {"kind": "average", "taps": int(rng.integers(2, 6))}
        else:
            params = _hidden_params(rng, eid, Ts, T, plant, command, nominal, var0, sd0, fn)
        if params is None:
            continue
        params.pop("_absent", None)
        hidden[eid] = params
        truth[eid] = params
    case.truth = _doc("case", Ts, plant, {"kind": "external"}, truth)
    case.hidden = hidden
    # a hidden lag (or a scale factor) changes the loop: a case whose truth the PID does not
    # stabilize records nothing a user would diagnose
    case.stable = _stable_loop(case.truth, kp, ki, kd)
    return case


def within_30_chance(iv) -> float:
    """P(0.7 <= estimate / truth <= 1.3) for an unbiased estimator, normal in log, whose 95 %
    interval is ``iv`` (its log-width / (2 x 1.96) the standard deviation): what the data allow."""
    from scipy.stats import norm
    sd = (np.log(iv[1]) - np.log(iv[0])) / (2 * 1.959964)
    if sd <= 0:
        return 1.0
    return float(norm.cdf(np.log(1.3) / sd) - norm.cdf(np.log(0.7) / sd))


def score_case(case: Case, rep: dict) -> dict:
    """The issue's criteria for one case."""
    planted = set(case.hidden)
    missing = rep["missing"]
    top = [m["effect"] for m in missing[:max(len(planted), 1)]]
    out = {"null": not planted, "reported": [m["effect"] for m in missing], "planted": sorted(planted),
           "error_before": rep["error_before"], "error_after": rep["error_after"]}
    if not planted:
        out["ok"] = not missing
        return out
    out["ranked"] = set(top) == planted and len(missing) >= len(planted)
    within, covered, chance = [], [], []
    for m in missing:
        if m["effect"] not in planted:
            continue
        for k, v in case.hidden[m["effect"]].items():
            if k == "mode":
                continue
            if isinstance(v, str) or (isinstance(v, int) and not isinstance(v, bool)):
                within.append(m["params"].get(k) == v)      # a choice (a filter's kind, its taps): exactly
                continue
            if not isinstance(v, (float, list)):
                continue
            got = m["params"].get(k)
            if got is None:
                within.append(False)
                continue
            if isinstance(v, list):
                # one value per channel: each within 30 %; the interval is the largest channel's
                g = np.broadcast_to(np.asarray(got, float), (len(v),))
                within.append(all(abs(gi / vi - 1) <= 0.3 for gi, vi in zip(g, v) if vi > 0))
                v = float(np.max(v))
            else:
                got = float(np.max(got)) if isinstance(got, list) else float(got)
                within.append(abs(got / v - 1) <= 0.3)
            iv = m.get("interval", {}).get(k)
            if iv is not None and v > 0 and iv[0] > 0:
                covered.append(bool(iv[0] <= v <= iv[1]))
                chance.append(within_30_chance(iv))
    out["params_ok"] = bool(within) and all(within)
    # the "recovered within its interval": the planted value inside the reported 95 % interval;
    # and the chance that an unbiased estimator of the interval's precision lands within 30 %
    out["covered"] = covered
    out["chance30"] = float(np.prod(chance)) if chance else None
    out["error_ok"] = rep["error_after"] <= 1.5 and rep["error_after"] < rep["error_before"]
    out["ok"] = out["ranked"] and out["params_ok"] and out["error_ok"]
    # planted effects not reported but named as an exact-tie alternative of a reported one (the same
    # likelihood to 0.5: identical spectra, e.g. process and actuator white noise through one input)
    got = {m["effect"] for m in missing}
    out["tied"] = sorted(e for e in planted - got if any(
        a["effect"] == e and abs(a["score"] - m["score"]) <= 0.5 for m in missing for a in m.get("alternatives", [])))
    return out


MEAN_EFFECTS = ("actuator.lag", "actuator.saturation", "actuator.deadzone", "sensor.scale_factor")


def with_step(case: Case, time_s: float = 0.0) -> Case:
    """The case under a step command of the same amplitude at ``time_s`` (the catalogue's step;
    at 0 the default): its mean effects then show only in the step's transient and level."""
    def step(text):
        d = tomllib.loads(text)
        amp = float(d["command"].get("amplitude", 1.0))
        d["command"] = {"kind": "step", "amplitude": amp, "time_s": float(time_s)}
        return dumps_toml(d)
    return Case(case.name + "-step", step(case.truth), step(case.nominal), case.hidden, case.duration, case.seed)



# "present with a wrong value" (issue 5: "an effect absent from the model, or present with a wrong
# parameter"): the generator itself does that only for white process and sensor noise and for
# white actuator noise that is really AR(1); these put any other hidden effect into the nominal at a
# wrong value (the case's seed picks one of the two)
WRONG = {"actuator.ar1": (("tau_s", 3.0), ("std", 0.4)), "actuator.lag": (("tau_s", 0.4), ("tau_s", 2.5)),
         "actuator.saturation": (("limit", 1.25), ("limit", 0.8)), "actuator.deadzone": (("width", 0.4), ("width", 2.0)),
         "sensor.scale_factor": (("error", 0.3), ("error", -1.0)), "sensor.bias_walk": (("std", 0.3), ("std", 3.0)),
         "sensor.bias_markov": (("tau_s", 4.0), ("std", 0.4)), "sensor.tone": (("amplitude", 0.4), ("amplitude", 2.0)),
         "sensor.quantization": (("step", 0.5), ("step", 2.0)), "sensor.jitter": (("std_s", 0.4), ("std_s", 2.5))}


def with_wrong_value(case: Case) -> Case | None:
    """The case with its first hidden effect that :data:`WRONG` lists in the nominal at a wrong
    value (one parameter times a factor; a saturation's limit kept below the command's
    amplitude); a replaced effect (white actuator noise that is really AR(1)) leaves the nominal.
    None when no hidden effect is listed. The expected report is unchanged: every hidden effect,
    at its planted values."""
    eid = next((e for e in case.hidden if e in WRONG), None)
    if eid is None:
        return None
    nominal, truth = tomllib.loads(case.nominal), tomllib.loads(case.truth)
    g, s = eid.split(".")
    params = dict(truth[g][s])
    key, factor = WRONG[eid][case.seed % 2]
    params[key] = params[key] * factor
    if eid == "actuator.saturation" and params["limit"] >= 0.98 * float(truth["command"].get("amplitude", 1.0)):
        params["limit"] = truth[g][s]["limit"] * 0.8
    mode = case.hidden[eid].get("mode", "")
    if mode.startswith("replace:"):
        rg, rs = mode.split(":", 1)[1].split(".")
        nominal.get(rg, {}).pop(rs, None)
    nominal.setdefault(g, {})[s] = params
    return Case(case.name + "-wrong", case.truth, dumps_toml(nominal), case.hidden, case.duration, case.seed)


def with_coarse_quantizer(case: Case) -> Case | None:
    """The case with its planted quantizer made coarse: the step is 10x the sensor's white noise
    (an undithered encoder or ADC), at most 0.7x the std of the signal (its random part and its mean
    response over the first minute: so that it still spans the steps and the uniform model's
    variance holds), and the case is left out (None) when
    that is under 3x the sensor noise. The generator's own steps sit beside a sensor noise of 0.35
    to several steps, where the quantizer's error is white; here it is correlated whenever the
    signal crosses few steps per sample. None also when no quantizer is planted."""
    if "sensor.quantization" not in case.hidden:
        return None
    truth = tomllib.loads(case.truth)
    m = parse_model(case.truth)
    st = m.predictor().steady_state()
    sw = float(np.max(np.broadcast_to(truth.get("sensor", {}).get("white", {}).get("std", 0.0), (m.p,))))
    rand = np.asarray(st.var_y, float) - sum(np.asarray(st.contributions.get(e, 0.0), float)
                                              for e in ("sensor.white", "sensor.quantization"))
    motion = np.var(m.predictor().mean_response(int(min(case.duration, 60.0) / m.Ts)).y, axis=0)
    step = min(10.0 * sw, 0.7 * float(np.sqrt(np.min(rand + motion))))
    if not step > 3.0 * sw:
        return None
    step = float(f"{step:.3g}")
    truth["sensor"]["quantization"] = {"step": step}
    hidden = {k: dict(v) for k, v in case.hidden.items()}
    hidden["sensor.quantization"]["step"] = step
    return Case(case.name + "-coarse", dumps_toml(truth), case.nominal, hidden, case.duration, case.seed)


def with_bias_pair(case: Case) -> Case:
    """The case's nominal with a bias random walk and a Gauss-Markov bias hidden together, in place
    of its own hidden effects (the generator never pairs them): a gyro's rate random walk and bias
    instability, the pair an Allan deviation plot is read for. Magnitudes drawn by the generator's
    laws (a walk whose growth over the record and a Gauss-Markov variance of 0.3 to 3x the nominal's
    var_y, tau from T/60 to T/6), from the case's own seed."""
    nominal = tomllib.loads(case.nominal)
    m = parse_model(case.nominal)
    var0 = float(np.max(m.predictor().steady_state().var_y))
    rng = np.random.default_rng([case.seed, 99])
    T = case.duration
    # the generator's own draws (the two biases need only rng, T and var0 of its arguments)
    walk, markov = (_hidden_params(rng, eid, m.Ts, T, None, {}, None, var0, None, None)
                    for eid in ("sensor.bias_walk", "sensor.bias_markov"))
    truth = {k: (dict(v) if isinstance(v, dict) else v) for k, v in nominal.items()}
    truth["sensor"] = dict(truth.get("sensor", {}), bias_walk=walk, bias_markov=markov)
    return Case(case.name + "-biaspair", dumps_toml(truth), case.nominal,
                {"sensor.bias_walk": walk, "sensor.bias_markov": markov}, T, case.seed)
