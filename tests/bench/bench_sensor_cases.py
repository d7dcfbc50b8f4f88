"""Generated sensor-only cases (``hidden_set.make_sensor_case``; ``--family closed``: the closed-loop
cases of ``hidden_set.make_closed_case``, a mass-spring-damper under a PID on its measurement with
any effect of the catalogue hidden): a rate sensor at rest whose model
is a white noise, with one or two of the sensor effects hidden (white noise at a wrong value, walk,
Gauss-Markov bias, flicker bias B, the integral's white noise Q, tone, quantization, the sensor's
own filter), scored by the generator's criteria (``hidden_set.score_case``: planted effects on top,
parameters within 30 % (a choice, such as a filter's kind and taps, exactly), model error after at
most 1.5 and below before; nothing reported on a null case).

Run: ``.venv/bin/python tests/bench/bench_sensor_cases.py [--cases N] [--write]``; ``--write``
replaces its block in RESULTS.md.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))      # tests/: helpers.closed_loop
from hidden_set import make_closed_case, make_sensor_case, score_case  # noqa: E402
from results_block import write_block  # noqa: E402

from noiselab.diagnose.diagnose import diagnose  # noqa: E402
from noiselab.model import parse_model  # noqa: E402

BEGIN = "<!-- bench_sensor_cases: begin -->"
END = "<!-- bench_sensor_cases: end -->"
HEADING = "## Generated sensor-only cases"
CLOSED_BEGIN = "<!-- bench_sensor_cases closed: begin -->"
CLOSED_END = "<!-- bench_sensor_cases closed: end -->"
CLOSED_HEADING = "## Generated closed-loop cases"


def run(seeds, log, family: str = "sensor") -> list[dict]:
    rows = []
    for seed in seeds:
        case = make_sensor_case(seed) if family == "sensor" else make_closed_case(seed)
        if not getattr(case, "stable", True):
            log(f"case {seed}: the PID does not stabilize the truth's loop: no case")
            continue
        truth, nominal = parse_model(case.truth, "truth"), parse_model(case.nominal, "nominal")
        rec = truth.simulate(int(round(case.duration / truth.Ts)), seed=case.seed) if family == "sensor" \
            else case.record()
        t0 = time.perf_counter()
        rep = diagnose(nominal, rec.t, rec.y, rec.u)
        sc = score_case(case, rep)
        sc.update(seed=seed, seconds=time.perf_counter() - t0, Ts=truth.Ts, duration=case.duration,
                  hidden=case.hidden, got={m["effect"]: m["params"] for m in rep["missing"]},
                  closed=rep["feedback"] is not None)
        # the planted effect named as an exact-tie alternative (process and actuator white noise
        # through the command's input: one spectrum) counts as found
        sc["ok_tied"] = sc["ok"] or (bool(sc["planted"]) and set(sc["planted"]) - set(sc["reported"]) <= set(sc["tied"])
                                     and sc["error_ok"] and len(rep["missing"]) == len(sc["planted"]))
        rows.append(sc)
        log(f"case {seed}: {'OK ' if sc['ok'] else 'BAD'} planted {sc['planted']} reported {sc['reported']} "
            f"error {sc['error_before']:.3g} -> {sc['error_after']:.3g} ({sc['seconds']:.1f} s)")
    return rows


def render(rows, meta, family: str = "sensor") -> str:
    planted = [r for r in rows if not r["null"]]
    nulls = [r for r in rows if r["null"]]
    begin, end = (BEGIN, END) if family == "sensor" else (CLOSED_BEGIN, CLOSED_END)
    L = [begin, "", f"Run: {meta['date']} (UTC), seeds 0..{meta['seeds'] - 1} ({len(rows)} cases); machine: nproc "
         f"{os.cpu_count()}, {platform.platform()}; load average at start {meta['load0']}; wall {meta['wall']:.0f} s.", ""]
    if family == "closed":
        L += [f"Said to be closed-loop: {sum(r['closed'] for r in rows)}/{len(rows)}. Found, counting the exact tie "
              f"of process and actuator white noise through the command's input: "
              f"{sum(r['ok_tied'] for r in planted)}/{len(planted)}.", ""]
    L += [f"Cases with hidden effects: {sum(r['ok'] for r in planted)}/{len(planted)} meet all criteria (planted on top "
         f"{sum(r['ranked'] for r in planted)}, parameters within 30 % {sum(r['params_ok'] for r in planted)}, error "
         f"{sum(r['error_ok'] for r in planted)}); planted values inside their 95 % intervals "
         f"{sum(c for r in planted for c in r['covered'])}/{sum(len(r['covered']) for r in planted)}. Null cases clean: "
         f"{sum(r['ok'] for r in nulls)}/{len(nulls)}.", "",
         "| effect planted | cases | all criteria met |", "|---|---|---|"]
    by = Counter(e for r in planted for e in r["planted"])
    for eid in sorted(by):
        rs = [r for r in planted if eid in r["planted"]]
        L.append(f"| `{eid}` | {len(rs)} | {sum(r['ok'] for r in rs)} |")
    L += ["", "Cases that miss a criterion:", ""]
    for r in rows:
        if not r["ok"]:
            L.append(f"- seed {r['seed']} ({r['duration']:.0f} s at {r['Ts'] * 1e3:g} ms): planted {r['hidden']}, "
                     f"reported {r['got']}, error {r['error_before']:.3g} -> {r['error_after']:.3g}")
    L += ["", "Reproduce: `.venv/bin/python tests/bench/bench_sensor_cases.py --cases "
          f"{meta['seeds']}" + (" --family closed" if family == "closed" else "") + " --write`", end]
    return "\n".join(L)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=80)
    ap.add_argument("--family", choices=("sensor", "closed"), default="sensor",
                    help="sensor-only cases, or closed-loop ones (hidden_set.make_closed_case)")
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args(argv)
    meta = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M"),
            "load0": " ".join(f"{x:.2f}" for x in os.getloadavg()), "seeds": a.cases}
    t0 = time.perf_counter()
    rows = run(range(a.cases), lambda s: print(s, flush=True), a.family)
    meta["wall"] = time.perf_counter() - t0
    block = render(rows, meta, a.family)
    print(block)
    if a.write:
        if a.family == "sensor":
            write_block(block, BEGIN, END, HEADING)
        else:
            write_block(block, CLOSED_BEGIN, CLOSED_END, CLOSED_HEADING)


if __name__ == "__main__":
    main()
