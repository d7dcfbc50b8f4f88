"""``noiselab predict MODEL``: a model's predicted steady-state statistics, per effect."""

from __future__ import annotations

import json

from ._common import load_model


def register(sub) -> None:
    sp = sub.add_parser("predict", help="predicted steady-state statistics of a model")
    sp.add_argument("model", help="model file (TOML) or built-in scenario name (seed, seed-nominal, ...)")
    sp.add_argument("--json", action="store_true", help="machine-readable output")
    sp.set_defaults(func=cmd_predict)


def _vec(v):
    """Per output, JSON-ready: NaN (no value at that output, e.g. where the plant integrates) as null."""
    import numpy as np

    return None if v is None else [float(x) if np.isfinite(x) else None for x in np.atleast_1d(v)]


def predict_report(model) -> dict:
    """The scriptable prediction (DESIGN.md, ``noiselab predict --json``)."""
    import numpy as np

    pr = model.predictor()
    st = pr.steady_state()
    modifiers = {}
    for eid, eff in model.effects.items():
        if eff.role == "modifier" and st.var_y is not None:
            other = model.without_effect(eid).predictor().steady_state()
            modifiers[eid] = None if other.var_y is None else _vec(st.var_y - other.var_y)
    return {
        "model": model.name,
        "source": model.source,
        "Ts": model.Ts,
        "discretization": model.discretization,
        "outputs": model.p,
        "output_names": list(model.output_names),
        "output_units": list(model.output_units),
        "var_y": _vec(st.var_y),
        "std_y": None if st.var_y is None else _vec(np.sqrt(st.var_y)),
        "bias_var_rate": _vec(st.bias_var_rate),
        "walk_var_rate": _vec(st.walk_var_rate),
        "P": None if st.P is None else st.P.tolist(),
        "state_names": list(model.plant.state_names),
        "contributions": {k: _vec(v) for k, v in st.contributions.items()},
        "modifiers": modifiers,
        "stable": st.stable,
        "notes": st.notes,
    }


def _fmt(v):
    return "null" if v is None else "  ".join("null" if x is None else f"{x:.4e}" for x in v)


def cmd_predict(args) -> int:
    model = load_model(args.model)
    rep = predict_report(model)
    if args.json:
        print(json.dumps(rep, indent=2))
        return 0
    print(f"model {rep['model']} ({rep['source']}), Ts = {rep['Ts']:g} s, {rep['discretization']}")
    print("outputs: " + ", ".join(model.outputs.label(j) for j in range(model.p)))
    print(f"{'effect':<24} {'variance added to y (unit^2)':>32}   share")
    total = rep["var_y"]
    for eid, v in rep["contributions"].items():
        share = "" if v is None or total is None else "  ".join(
            "  -    " if a is None or b is None else f"{100 * a / b:5.1f} %" for a, b in zip(v, total))
        print(f"{eid:<24} {_fmt(v):>32}   {share}")
    for eid, v in rep["modifiers"].items():
        print(f"{eid:<24} {_fmt(v):>32}   (change of var_y it causes)")
    print(f"{'var_y (steady state)':<24} {_fmt(total):>32}")
    print(f"{'std_y':<24} {_fmt(rep['std_y']):>32}")
    print(f"{'bias_var_rate (per s)':<24} {_fmt(rep['bias_var_rate']):>32}")
    if rep["walk_var_rate"] is not None:
        print(f"{'walk_var_rate (per s)':<24} {_fmt(rep['walk_var_rate']):>32}   (the plant integrates)")
    if rep["P"] is None:
        print("P: null (the plant integrates: no steady state, stationary increments)" if rep["walk_var_rate"]
              is not None else "P: null (the plant is not stable: no steady state)")
    elif not rep["P"]:
        print("P: [] (no plant states: a sensor-only model, y = reference + sensor effects)")
    else:
        print("P (plant state covariance, " + ", ".join(rep["state_names"]) + "):")
        for row in rep["P"]:
            print("   " + "  ".join(f"{x: .4e}" for x in row))
    for note in rep["notes"]:
        print(f"note: {note}")
    return 0
