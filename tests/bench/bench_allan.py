"""Benchmark: overlapping Allan deviation of 10^7 samples at octave taus, noiselab vs allantools.

Run on demand: `.venv/bin/python tests/bench/bench_allan.py [--n N] [--repeat R]`. Reports the best
of R runs for each (noiselab's includes noise identification, EDF and bounds; allantools' is the
deviations only) and checks both agree to 1e-9 relative. Target (issue 4): at least as fast.
"""

import argparse
import time

import allantools
import numpy as np

from noiselab.stats import oadev


def best_of(fn, repeat):
    best, out = np.inf, None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=10_000_000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    y = np.random.default_rng(1).standard_normal(args.n)
    t_ours, ours = best_of(lambda: oadev(y, 1.0, taus="octave"), args.repeat)
    t_peer, peer = best_of(lambda: allantools.oadev(y, rate=1.0, data_type="freq", taus=ours.taus), args.repeat)
    rel = np.max(np.abs(ours.dev - peer[1]) / peer[1])
    print(f"oadev, N = {args.n:,}, {ours.taus.size} octave taus, best of {args.repeat}")
    print(f"  noiselab  {t_ours:8.3f} s  (with noise ID, EDF, bounds)")
    print(f"  allantools{t_peer:8.3f} s  (deviations only)")
    print(f"  ratio allantools/noiselab {t_peer / t_ours:.2f}x, max relative difference {rel:.1e}")
    if rel > 1e-9:
        raise SystemExit("noiselab and allantools disagree beyond 1e-9")


if __name__ == "__main__":
    main()
