"""Noise coefficients (issue 5): noiselab's diagnosis against the Allan-slope reading.

On the same recordings, the white-noise density N and the bias random walk K of a sensor are
estimated (a) by ``noiselab diagnose`` and (b) by the common practice of reading the overlapping
Allan deviation at tau = 1 s and tau = 3 s (IEEE Std 952-1997 Annex C, the usual gyro practice),
and both are compared with the true values.

Run on demand, not by pytest (``pyproject.toml`` ignores ``tests/bench``)::

    .venv/bin/python tests/bench/bench_noise_density.py            # full run, ~8-10 min on 2 cores
    .venv/bin/python tests/bench/bench_noise_density.py --write    # ... and update RESULTS.md
    .venv/bin/python tests/bench/bench_noise_density.py --quick    # 2 seeds of the small cases, never writes
    .venv/bin/python tests/bench/bench_noise_density.py --cases S1 O1 --seeds 1 2 --json out.json

Recordings
----------
A sensor reads a quiet plant: first-order plant A = -1, B = C = L = 1, command kind "none",
``process.white`` std q = 0.05 sigma (its contribution to the low-frequency PSD is q^2/sigma^2 =
0.25 % of the white floor, and it is in both the truth and the nominal model). The truth model adds

- ``sensor.white`` std sigma per sample at period Ts: white-noise density N = sigma sqrt(Ts)
  (units sqrt(s), the angle/velocity random walk coefficient), Allan variance N^2 / tau;
- ``sensor.bias_walk`` std K (units / sqrt(s)): b_{k+1} = b_k + K sqrt(Ts) eta_k, Allan variance
  K^2 tau / 3 (+ K^2 Ts^2 / (6 tau) for the sampled walk, negligible here);
- in the M rows, a ``sensor.bias_markov`` (Gauss-Markov bias) of std s and correlation time T, Allan
  variance (2 s^2 T / tau) [1 - T / (2 tau) (3 - 4 e^{-tau/T} + e^{-2 tau/T})], bump near 1.9 T.

The two Allan terms cross at tau_c = sqrt(3) N / K; each case is given by N, tau_c (hence K),
Ts and the record length. "Separated" cases have tau_c = 20 s (white alone at 1 s, the walk
visible within the record); "overlap" cases tau_c = 1-2 s (both terms at 1 s and 3 s); W has a
tiny walk (tau_c = 200 s). Every case runs the fixed seeds s = 1..5 as ``Model.simulate(n,
seed=100 i + s)`` for the i-th case (1-based): a seed gives the same normals whatever the
parameters, so distinct seeds keep the cases' errors independent.
The exact expected Allan deviation of each truth model (``Predictor.allan``, from the sampled
process's variogram) is printed beside the readings: the raw readings' bias follows from it.

(a) noiselab
------------
``noiselab.diagnose.diagnose.diagnose(nominal, t, y, u)`` (what ``noiselab diagnose REC.mcap
--model NOMINAL --json`` runs on the same samples), with the nominal model = the truth minus
``sensor.white``, ``sensor.bias_walk`` and ``sensor.bias_markov`` (rows ``nominal = none``), or in
row R with ``sensor.white`` at twice its true std and no walk (``nominal = white x2``: the white
noise is then refitted, mode ``refit``). Read from the report: the fitted model's
``sensor.white`` std -> N_hat = std sqrt(Ts), ``sensor.bias_walk`` std -> K_hat, with their 95 %
profile intervals from ``missing[i]["interval"]["std"]`` (N's scaled by sqrt(Ts)). An effect the
diagnosis does not report counts as estimate 0 (the nominal's value for a refit) and as not
covered. Timed: the ``diagnose()`` call (it screens the whole catalogue, fits and computes
intervals; ``seconds`` of its report).

(b) Allan-slope reading
-----------------------
Overlapping Allan deviation sigma_A(tau) with ``allantools.oadev(y, rate=1/Ts, data_type="freq",
taus=m Ts)`` of the measurement y (rate data), m on the grid of MathWorks' "Inertial Sensor Noise
Analysis Using Allan Variance" example: unique(ceil(logspace(0, log10(M), 100))) with
M = 2^floor(log2(n / 2)), plus m = round(1/Ts) and round(3/Ts) so that tau = 1 s and 3 s are on
the grid exactly. Three readings, all from the same sigma_A:

- raw: N_raw = sigma_A(1 s), K_raw = sigma_A(3 s), read off the curve. Under the model
  sigma_A(1 s)^2 = N^2 + K^2 / 3 and sigma_A(3 s)^2 = K^2 + N^2 / 3 (+ the Markov term): the raw
  reading includes the other term.
- line (IEEE 952 Annex C as usually implemented, the MathWorks example's code): local log-log
  slopes s_i = (log sigma_i+1 - log sigma_i) / (log tau_i+1 - log tau_i) over the whole grid;
  the point i with s_i closest to -1/2 anchors the line sigma = sigma_i (tau / tau_i)^(-1/2),
  read at tau = 1 s: N_line = sigma_i sqrt(tau_i); the point j with s_j closest to +1/2 anchors
  sigma = sigma_j (tau / tau_j)^(1/2), read at tau = 3 s: K_line = sigma_j sqrt(3 / tau_j)
  (the +1/2 line sigma_A = K sqrt(tau / 3) equals K at tau = 3 s). tau_i and tau_j are reported.
- fit (an extra, not the slope practice; a careful user's Allan-based estimate): weighted
  non-negative least squares of AVAR_hat(tau) = a / tau + b tau over the grid, weights
  edf / AVAR_pred(tau)^2 with edf = max(3 (n - 1) / (2 m) - 2 (n - 2) / n, 1) (NIST SP 1065's
  white-FM approximation for the overlapping estimator), AVAR_pred from the previous iteration
  (5 iterations from AVAR_hat); N_fit = sqrt(a), K_fit = sqrt(3 b).

Timed: the ``allantools.oadev`` call plus the readings.

Reported per run (seed) and per case: true N, K; estimates and relative errors (est - true) /
true; noiselab's interval coverage; the effects noiselab added; times. Summary over seeds: median
|relative error|, median relative error (bias), coverage k/n.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests" / "bench"))

import allantools  # noqa: E402
from results_block import RESULTS, write_block  # noqa: E402
from scipy.optimize import nnls  # noqa: E402

from noiselab.diagnose.diagnose import diagnose  # noqa: E402
from noiselab.model import parse_model  # noqa: E402

HEADING = "## Noise coefficients: diagnose against the Allan-slope reading"
BEGIN = "<!-- BEGIN bench_noise_density: generated by tests/bench/bench_noise_density.py --write -->"
END = "<!-- END bench_noise_density -->"
SEEDS = (1, 2, 3, 4, 5)


@dataclass
class Case:
    name: str
    kind: str              # a phrase for the table
    Ts: float              # s
    minutes: float
    N: float               # white-noise density, units sqrt(s)
    tau_c: float           # s, where N^2 / tau = K^2 tau / 3
    markov: tuple | None = None   # (std, tau_s)
    nominal: str = "none"  # "none" | "white x2"
    seed0: int = 0         # the recording of seed s uses simulate(seed=seed0 + s)

    @property
    def K(self) -> float:
        return float(np.sqrt(3.0) * self.N / self.tau_c)

    @property
    def sigma(self) -> float:
        return float(self.N / np.sqrt(self.Ts))

    @property
    def n(self) -> int:
        return int(round(self.minutes * 60.0 / self.Ts))


N0 = 2e-3
CASES = [
    Case("S1", "separated", 0.010, 10, N0, 20.0),
    Case("S2", "separated, long, fast", 0.002, 30, N0, 20.0),
    Case("S3", "separated, short", 0.020, 1, N0, 20.0),
    Case("O1", "overlap", 0.005, 5, N0, 2.0),
    Case("O2", "overlap, long", 0.020, 30, N0, 1.0),
    Case("O3", "overlap, short", 0.002, 1, N0, 2.0),
    Case("W", "tiny walk", 0.010, 30, N0, 200.0),
    Case("M1", "separated + Markov T = 2 s", 0.010, 10, N0, 20.0, markov=(2e-3, 2.0)),
    Case("M2", "separated + Markov T = 10 s", 0.005, 30, N0, 20.0, markov=(1e-3, 10.0)),
    Case("R", "separated, nominal white x2", 0.010, 10, N0, 20.0, nominal="white x2"),
]
for _i, _c in enumerate(CASES):
    _c.seed0 = 100 * (_i + 1)     # independent recordings across cases (same seed -> same normals)

QUICK = ("S1", "S3", "O1")

BASE = """name = "quiet"
description = "sensor on a quiet first-order plant (bench_noise_density)"
[sampling]
Ts = {Ts!r}
[plant]
A = [[-1.0]]
B = [[1.0]]
C = [[1.0]]
L = [[1.0]]
[command]
kind = "none"
[process.white]
std = {q!r}
"""


def truth_text(c: Case) -> str:
    s = BASE.format(Ts=c.Ts, q=0.05 * c.sigma)
    s += f"[sensor.white]\nstd = {c.sigma!r}\n[sensor.bias_walk]\nstd = {c.K!r}\n"
    if c.markov:
        s += f"[sensor.bias_markov]\nstd = {c.markov[0]!r}\ntau_s = {c.markov[1]!r}\n"
    return s


def nominal_text(c: Case) -> str:
    s = BASE.format(Ts=c.Ts, q=0.05 * c.sigma)
    if c.nominal == "white x2":
        s += f"[sensor.white]\nstd = {2 * c.sigma!r}\n"
    return s


def allan_grid(n: int, Ts: float) -> np.ndarray:
    M = 2 ** int(np.floor(np.log2(n / 2)))
    m = np.unique(np.ceil(np.logspace(0, np.log10(M), 100)).astype(np.int64))
    return np.unique(np.r_[m, round(1 / Ts), round(3 / Ts)])


def theory_adev(truth, m: np.ndarray) -> np.ndarray:
    """Exact expected Allan deviation of the truth model's sampled output at factors m."""
    parts = truth.predictor().allan(m)
    return np.sqrt(sum(v[:, 0] for v in parts.values() if v is not None))


def slope_readings(y: np.ndarray, Ts: float) -> dict:
    n = y.size
    m = allan_grid(n, Ts)
    t0 = time.perf_counter()
    taus, ad, _, _ = allantools.oadev(y, rate=1.0 / Ts, data_type="freq", taus=m * Ts)
    m_used = np.rint(taus / Ts).astype(np.int64)
    i1 = int(np.flatnonzero(m_used == round(1 / Ts))[0])
    i3 = int(np.flatnonzero(m_used == round(3 / Ts))[0])
    lt, la = np.log10(taus), np.log10(ad)
    s = np.diff(la) / np.diff(lt)
    iN = int(np.argmin(np.abs(s + 0.5)))
    iK = int(np.argmin(np.abs(s - 0.5)))
    # extra: weighted NNLS two-term fit of the Allan variance
    av = ad**2
    edf = np.maximum(3 * (n - 1) / (2 * m_used) - 2 * (n - 2) / n, 1.0)
    X = np.c_[1.0 / taus, taus]
    pred = av.copy()
    coef = np.zeros(2)
    for _ in range(5):
        w = np.sqrt(edf) / np.maximum(pred, 1e-300)
        coef, _ = nnls(X * w[:, None], av * w)
        pred = np.maximum(X @ coef, 1e-300)
    dt = time.perf_counter() - t0
    return {
        "N_raw": float(ad[i1]), "K_raw": float(ad[i3]),
        "N_line": float(ad[iN] * np.sqrt(taus[iN])), "tau_N": float(taus[iN]),
        "K_line": float(ad[iK] * np.sqrt(3.0 / taus[iK])), "tau_K": float(taus[iK]),
        "N_fit": float(np.sqrt(coef[0])), "K_fit": float(np.sqrt(3.0 * coef[1])),
        "tau_max": float(taus[-1]), "allan_s": dt,
    }


def noiselab_readings(rep: dict, Ts: float) -> dict:
    eff = rep["model"].effects
    out = {"added": [f"{m['effect']}" + ("" if m["mode"] == "add" else f" ({m['mode']})") for m in rep["missing"]],
           "diag_s": float(rep["seconds"]), "error_before": rep["error_before"], "error_after": rep["error_after"]}
    byid = {m["effect"]: m for m in rep["missing"]}
    for key, eid, scale in (("N", "sensor.white", np.sqrt(Ts)), ("K", "sensor.bias_walk", 1.0)):
        std = float(np.ravel(eff[eid].params["std"])[0]) if eid in eff else 0.0
        out[f"{key}_nl"] = std * scale
        iv = byid.get(eid, {}).get("interval", {}).get("std")
        if iv is not None:
            lo, hi = np.ravel(np.asarray(iv, float))[:2]
            out[f"{key}_lo"], out[f"{key}_hi"] = float(lo * scale), float(hi * scale)
        else:
            out[f"{key}_lo"] = out[f"{key}_hi"] = None
    return out


def run_case(c: Case, seeds, log) -> list[dict]:
    truth, nominal = parse_model(truth_text(c)), parse_model(nominal_text(c))
    th = theory_adev(truth, np.array([round(1 / c.Ts), round(3 / c.Ts)]))
    rows = []
    for s in seeds:
        rec = truth.simulate(c.n, seed=c.seed0 + s)
        y = np.asarray(rec.y, float)
        r = {"case": c.name, "seed": c.seed0 + s, "N": c.N, "K": c.K, "th_adev1": float(th[0]), "th_adev3": float(th[1])}
        r.update(slope_readings(y[:, 0], c.Ts))
        t0 = time.perf_counter()
        rep = diagnose(nominal, rec.t, y, rec.u)
        r["diag_wall_s"] = time.perf_counter() - t0
        r.update(noiselab_readings(rep, c.Ts))
        for key in ("N", "K"):
            tru = r[key]
            for meth in ("nl", "raw", "line", "fit"):
                r[f"{key}_{meth}_rel"] = (r[f"{key}_{meth}"] - tru) / tru
            lo, hi = r[f"{key}_lo"], r[f"{key}_hi"]
            r[f"{key}_cov"] = bool(lo is not None and lo <= tru <= hi)
        rows.append(r)
        log(f"{c.name} seed {s}: N nl {r['N_nl_rel']:+.3f} raw {r['N_raw_rel']:+.3f} line {r['N_line_rel']:+.3f} | "
            f"K nl {r['K_nl_rel']:+.3f} [{'in' if r['K_cov'] else 'OUT'}] raw {r['K_raw_rel']:+.3f} "
            f"line {r['K_line_rel']:+.3f} (tau {r['tau_K']:.3g}) fit {r['K_fit_rel']:+.3f} | "
            f"{', '.join(r['added'])} | diag {r['diag_wall_s']:.1f} s, allan {r['allan_s']:.3f} s")
    return rows


# ----------------------------------------------------------------------------- report

def pct(x: float) -> str:
    return f"{100 * x:+.1f} %"


def apct(x: float) -> str:
    return f"{100 * x:.1f} %"


def fmt(x) -> str:
    return "—" if x is None else f"{x:.3g}"


def summarize(rows: list[dict], key: str, meth: str) -> tuple[float, float]:
    e = np.array([r[f"{key}_{meth}_rel"] for r in rows])
    return float(np.median(np.abs(e))), float(np.median(e))


def render(cases, rows, meta) -> str:
    L = [BEGIN, ""]
    L.append(f"Run: {meta['date']} (local time). Wall clock {meta['wall']:.0f} s. Machine: nproc {os.cpu_count()}, "
             f"{platform.platform()}; Python {platform.python_version()}, numpy {np.__version__}, allantools "
             f"{allantools.__version__}. Load average at start {meta['load0']}, at end {meta['load1']}.")
    L.append("")
    L.append("Cases (N = 0.002 units sqrt(s) throughout, K = sqrt(3) N / tau_c; seeds 100 i + s, "
             f"s = {', '.join(map(str, meta['seeds']))}, for the i-th case); the expected raw readings are the exact Allan deviation of the "
             "truth model (`Predictor.allan`) at 1 s and 3 s, relative to N and K:")
    L.append("")
    L.append("| case | kind | Ts | record | samples | N | K | tau_c | extra | nominal | expected sigma_A(1 s)/N - 1 | expected sigma_A(3 s)/K - 1 |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for c in cases:
        r0 = [r for r in rows if r["case"] == c.name][0]
        mk = f"Markov std {c.markov[0]:g}, T {c.markov[1]:g} s" if c.markov else ""
        L.append(f"| {c.name} | {c.kind} | {1000 * c.Ts:g} ms | {c.minutes:g} min | {c.n:,} | {c.N:.3g} | {c.K:.3g} | "
                 f"{c.tau_c:g} s | {mk} | {c.nominal} | {pct(r0['th_adev1'] / c.N - 1)} | {pct(r0['th_adev3'] / c.K - 1)} |")
    L.append("")
    L.append("Summary per case over seeds: median |relative error| (median signed relative error); noiselab's "
             "95 % interval coverage k/n; median times.")
    L.append("")
    L.append("| case | N: noiselab | N cover | N: raw sigma_A(1 s) | N: -1/2 line @1 s | N: AVAR fit | "
             "K: noiselab | K cover | K: raw sigma_A(3 s) | K: +1/2 line @3 s | K: AVAR fit | diagnose s | Allan s |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|")

    def cell(rs, key, meth):
        a, b = summarize(rs, key, meth)
        return f"{apct(a)} ({pct(b)})"

    groups = [(c.name, [r for r in rows if r["case"] == c.name]) for c in cases]
    groups.append(("**all**", rows))
    plain = [r for r in rows if r["case"] in {c.name for c in cases if not c.markov}]
    if len(plain) != len(rows):
        groups.append(("all but M", plain))
    for name, rs in groups:
        cN = sum(r["N_cov"] for r in rs)
        cK = sum(r["K_cov"] for r in rs)
        L.append(f"| {name} | {cell(rs, 'N', 'nl')} | {cN}/{len(rs)} | {cell(rs, 'N', 'raw')} | {cell(rs, 'N', 'line')} | "
                 f"{cell(rs, 'N', 'fit')} | {cell(rs, 'K', 'nl')} | {cK}/{len(rs)} | {cell(rs, 'K', 'raw')} | "
                 f"{cell(rs, 'K', 'line')} | {cell(rs, 'K', 'fit')} | "
                 f"{np.median([r['diag_wall_s'] for r in rs]):.2f} | {np.median([r['allan_s'] for r in rs]):.3f} |")
    L.append("")
    tot_d = sum(r["diag_wall_s"] for r in rows)
    tot_a = sum(r["allan_s"] for r in rows)
    L.append(f"Total time over {len(rows)} recordings: diagnose {tot_d:.0f} s, Allan readings {tot_a:.1f} s "
             f"(ratio {tot_d / tot_a:.0f}x).")
    L.append("")
    L.append("<details><summary>Per recording</summary>")
    L.append("")
    L.append("| case | seed | N_hat noiselab [95 %] | rel | N raw | rel | N line (anchor tau) | rel | "
             "K_hat noiselab [95 %] | rel | K raw | rel | K line (anchor tau) | rel | K fit | rel | added by diagnose | "
             "error before → after | diagnose s |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        L.append(
            f"| {r['case']} | {r['seed']} | {r['N_nl']:.4g} [{fmt(r['N_lo'])}, {fmt(r['N_hi'])}] | {pct(r['N_nl_rel'])} | "
            f"{r['N_raw']:.4g} | {pct(r['N_raw_rel'])} | {r['N_line']:.4g} ({r['tau_N']:.3g} s) | {pct(r['N_line_rel'])} | "
            f"{r['K_nl']:.4g} [{fmt(r['K_lo'])}, {fmt(r['K_hi'])}]{'' if r['K_cov'] else ' ✗'} | {pct(r['K_nl_rel'])} | "
            f"{r['K_raw']:.4g} | {pct(r['K_raw_rel'])} | {r['K_line']:.4g} ({r['tau_K']:.3g} s) | {pct(r['K_line_rel'])} | "
            f"{r['K_fit']:.4g} | {pct(r['K_fit_rel'])} | {', '.join(r['added']) or 'nothing'} | "
            f"{r['error_before']:.3g} → {r['error_after']:.3g} | {r['diag_wall_s']:.2f} |")
    L.append("")
    L.append("</details>")
    L.append("")
    L.append("Reproduce (from the repository root):")
    L.append("")
    L.append("```")
    L.append(".venv/bin/python tests/bench/bench_noise_density.py --write")
    L.append("```")
    L.append(END)
    return "\n".join(L)


INTRO = """
Script: `tests/bench/bench_noise_density.py` (its docstring states the method exactly). On the same
recordings (a sensor on a quiet first-order plant with `sensor.white`, `sensor.bias_walk` and, in
rows M, a `sensor.bias_markov`), noiselab's diagnosis (`diagnose()` against a nominal model without
these effects: N_hat = fitted white std x sqrt(Ts), K_hat = fitted walk std, 95 % profile intervals)
is compared with reading the overlapping Allan deviation (allantools, 100 log-spaced taus as in
MathWorks' example, plus 1 s and 3 s): *raw* sigma_A(1 s) for N and sigma_A(3 s) for K; *line*: the
-1/2 line through the grid point whose local slope is closest to -1/2, read at 1 s, and the +1/2
line through the point whose slope is closest to +1/2, read at 3 s (IEEE 952 Annex C as usually
coded); and, as an extra that is not the slope practice, a weighted two-term fit
AVAR = N^2/tau + K^2 tau/3.
"""


def write_results(block: str) -> None:
    write_block(block, BEGIN, END, HEADING, INTRO)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", help="case names (default: all)")
    ap.add_argument("--seeds", nargs="*", type=int, default=list(SEEDS))
    ap.add_argument("--quick", action="store_true", help=f"cases {', '.join(QUICK)}, seeds 1 2; never writes")
    ap.add_argument("--write", action="store_true", help="replace the generated block in RESULTS.md")
    ap.add_argument("--json", help="write every row to this JSON file")
    args = ap.parse_args(argv)
    names = list(QUICK) if args.quick else (args.cases or [c.name for c in CASES])
    seeds = [1, 2] if args.quick else args.seeds
    cases = [c for c in CASES if c.name in names]
    meta = {"date": datetime.datetime.now().strftime("%Y-%m-%d %H:%M"), "seeds": seeds,
            "load0": " ".join(f"{x:.2f}" for x in os.getloadavg())}
    t0 = time.perf_counter()
    rows = []
    for c in cases:
        rows += run_case(c, seeds, lambda s: print(s, flush=True))
    meta["wall"] = time.perf_counter() - t0
    meta["load1"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    block = render(cases, rows, meta)
    print(block)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    if args.write and not args.quick:
        write_results(block)
        print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
