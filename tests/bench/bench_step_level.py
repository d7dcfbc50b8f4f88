"""Benchmark: a mean effect under a step command, diagnose against the record's level (issue 5).

Run on demand: ``.venv/bin/python tests/bench/bench_step_level.py [--seeds K]``.

A mass-spring-damper (m = 1, c = 0.5, k = 4; Ts = 0.01 s, 120 s from rest) driven by a step of 2
at t = 0, its input clipped at 1.5 (``actuator.saturation``), process and sensor white noise. The
nominal model lacks the saturation. After the step the plant input is the constant limit, so the
limit is the record's level times k: the peer estimator is k times the mean measurement after
the first 10 s, whose spread is S_y(0) / T (the plant averages its noise out). The diagnosis
estimates the limit from the likelihood it ranks effects with: a Whittle likelihood of the
differenced, tapered residual, plus the tapered ends in the time domain (``whittle.Ramps``).
Differencing and the taper leave out the level of the middle of the record, so its spread is
larger. Printed per seed: what the diagnosis reports, the limit and its 95 % interval, the model
error after, the peer's limit; then the spreads (sample standard deviations over the seeds), their
ratio, the intervals' coverage and how often the error after exceeds 1.5.
"""

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from noiselab.diagnose.diagnose import diagnose  # noqa: E402
from noiselab.model import parse_model  # noqa: E402

LIMIT, K = 1.5, 4.0
BASE = ("name = \"stepsat\"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 0.5\nk = 4.0\n"
        "[command]\nkind = \"step\"\namplitude = 2.0\n"
        "[process.white]\nstd = 0.5\n[sensor.white]\nstd = 0.002\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=12)
    args = ap.parse_args(argv)
    truth = parse_model(BASE + f"[actuator.saturation]\nlimit = {LIMIT}\n", "truth")
    nominal = parse_model(BASE, "nominal")
    n, k0 = 12000, 1000
    ours, peer, inside, high, secs = [], [], 0, 0, []
    for seed in range(1, args.seeds + 1):
        rec = truth.simulate(n, seed=seed)
        t0 = time.perf_counter()
        rep = diagnose(nominal, rec.t, rec.y, rec.u)
        secs.append(time.perf_counter() - t0)
        got = {m["effect"]: m for m in rep["missing"]}
        sat = got.get("actuator.saturation")
        lim = float(sat["params"]["limit"]) if sat else float("nan")
        lo, hi = sat["interval"]["limit"] if sat else (float("nan"), float("nan"))
        inside += bool(lo <= LIMIT <= hi)
        high += rep["error_after"] > 1.5
        lvl = K * float(np.mean(rec.y[k0:, 0]))
        ours.append(lim)
        peer.append(lvl)
        print(f"seed {seed:2d}: reported {list(got)}, limit {lim:.4f} [{lo:.4f}, {hi:.4f}], "
              f"error {rep['error_before']:.3g} -> {rep['error_after']:.3g}; level x k {lvl:.4f} ({secs[-1]:.1f} s)")
    ours, peer = np.array(ours), np.array(peer)
    s_ours, s_peer = float(np.nanstd(ours, ddof=1)), float(np.std(peer, ddof=1))
    print(f"limit {LIMIT}: diagnose mean {np.nanmean(ours):.4f} sd {s_ours:.4f}; level x k mean {peer.mean():.4f} "
          f"sd {s_peer:.4f}; sd ratio {s_ours / s_peer:.1f}x")
    print(f"95 % intervals cover the limit {inside}/{len(ours)}; error after > 1.5 in {high}/{len(ours)}; "
          f"median time {np.median(secs):.1f} s")


if __name__ == "__main__":
    main()
