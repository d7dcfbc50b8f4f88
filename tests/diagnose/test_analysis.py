"""The offline analysis (issue 4 "What it must show"): the model error is about 1 for the right
model, clearly larger when an effect is left out, the regions localize the mismatch, the .rrd
holds exactly the numbers of compare(), bad input is one line and exit 2, and foreign
recordings (leading-slash topic, header stamps, gaps, irregular timing) are analysed honestly.

Real files only: recordings written by ``noiselab simulate``, by RecordingWriter or by the
raw ``mcap`` writer; the CLI runs as a subprocess; the .rrd is read back with
rerun.chunk.RrdReader (rerun-sdk 0.41: ``.stream()`` -> Chunk, ``.to_record_batch()``). Every
random draw has a fixed seed.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers.models import ALL_LINEAR, ENCODER_TOML, load
from helpers.recordings import raw_json_mcap
from helpers.rrd import column, read_chunks
from noiselab.diagnose.compare import compare, transient_samples
from noiselab.model import load_model, parse_model
from noiselab import wire
from noiselab.recordings.writer import RecordingWriter

ROOT = Path(__file__).resolve().parents[2]
VIEWS = ("variance", "acf", "psd", "allan")


def cli(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "noiselab.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=timeout)


# -- 1. the right model: error about 1 -------------------------------------------------------------------
N_LONG = 50_000
SEEDS = range(10)


@pytest.mark.slow
@pytest.mark.parametrize("which", ["seed", "all_linear"])
def test_error_of_the_right_model_is_about_one(which):
    """Mean over seeds of the model error within 3 standard errors (+ 0.1) of 1, overall and per view.

    Derivation: each record's error is a mean of z^2 with E = 1 under the (Gaussian) model; the
    records are independent, so the mean over K seeds has standard error sd/sqrt(K), sd observed
    across the seeds. Allowance 0.1, stated: (a) the error's distribution is right-skewed (the
    variance windows and long Allan taus have few dof, nu ~ 5), so with K = 10 the sample mean sits
    below 1 more often than not and the sample sd is itself uncertain (chi with 9 dof); (b) the
    all-linear model holds a tone and jitter, whose non-Gaussian errors make the Gaussian spread
    formulas conservative (error slightly below 1). Measured (20 seeds x 60,000 samples): seed 1.08 +- 0.10,
    all-linear 1.10 +- 0.10; 400 trials of the seed model's variance view alone 0.997 +- 0.021.
    """
    mdl = load_model("seed") if which == "seed" else load(ALL_LINEAR)
    overall, per_view = [], {v: [] for v in VIEWS}
    for seed in SEEDS:
        rec = mdl.simulate(N_LONG, seed=seed)
        c = compare(mdl, rec.t, rec.y, rec.u, burn=None)
        overall.append(c.error)
        for v in VIEWS:
            per_view[v].append(c.error_per_view[v])
    rows = [("overall", np.array(overall))] + [(v, np.array(a)) for v, a in per_view.items()]
    print(f"\n{which}: model error of the right model over {len(SEEDS)} seeds x {N_LONG} samples")
    bad = []
    for name, a in rows:
        mean, se = a.mean(), a.std(ddof=1) / np.sqrt(a.size)
        bound = 3 * se + 0.1
        print(f"  {name:<9} mean {mean:6.3f}  se {se:5.3f}  min {a.min():6.3f}  max {a.max():6.3f}  "
              f"|mean - 1| bound {bound:5.3f}")
        if not abs(mean - 1) < bound:
            bad.append((name, mean, se))
    assert not bad, bad


@pytest.mark.slow
def test_window_variance_spread_is_exact_for_long_memory():
    """The variance view's z divides by the exact std of a window's sample variance. The O(W)
    formula equals the definition (2/W^2) sum_ij C_ij^2 (the demeaned window's covariance built
    entry by entry) for white, Gauss-Markov, walk and periodic variograms, and a Monte Carlo of
    2000 windows of a Gauss-Markov process with tau = 2.4 W (plus white noise) reproduces it within
    4 standard errors. (The stationary approximation used before for W > 2048 understated this
    case 2.2x, which put a right model's variance view at about 1.5 instead of 1.)"""
    from scipy.signal import lfilter

    from noiselab.diagnose.compare import windowed_variance_var

    def brute(gam, W):
        S = np.cumsum(gam[:W])
        a = np.arange(W)
        g = (S[a] + S[W - 1 - a]) / W
        C = -gam[np.abs(a[:, None] - a[None, :])] + g[:, None] + g[None, :] - g.mean()
        return 2.0 * np.sum(C**2) / W**2

    for W in (64, 3000):
        d = np.arange(W)
        rho = np.exp(-1 / (2.4 * W))
        for gam in (1.0 * (d > 0), 0.3 * (d > 0) + 5 * (1 - rho**d), 1e-3 * (d > 0) + d,
                    np.sin(0.3 * d) ** 2 + 0.01 * (d > 0)):
            assert windowed_variance_var(gam, W) == pytest.approx(brute(gam, W), rel=1e-10)

    W, K, s2, sw2 = 3000, 2000, 5.0, 0.3
    rho = np.exp(-1 / (2.4 * W))
    rng = np.random.default_rng(11)
    e = rng.standard_normal((K, W)) * np.sqrt(s2 * (1 - rho**2))
    e[:, 0] = rng.standard_normal(K) * np.sqrt(s2)              # each window starts stationary
    x = lfilter([1.0], [1.0, -rho], e, axis=1) + np.sqrt(sw2) * rng.standard_normal((K, W))
    v = x.var(axis=1)
    d = np.arange(W)
    want = windowed_variance_var(sw2 * (d > 0) + s2 * (1 - rho**d), W)
    got = v.var(ddof=1)
    # se of a sample variance: sqrt((m4 - (K-3)/(K-1) m2^2) / K), m4 and m2 the sample moments
    m2, m4 = got, np.mean((v - v.mean()) ** 4)
    se = np.sqrt((m4 - (K - 3) / (K - 1) * m2**2) / K)
    assert abs(got - want) < 4 * se, (got, want, se)


@pytest.mark.slow
def test_level_view_is_calibrated_with_a_walk_and_a_gauss_markov_bias():
    """The level view (window means of y - E[y] on a record from rest) under a right model whose
    bias walk (b_0 random) and Gauss-Markov bias move every window's mean together: over 300
    records the view's error has mean 1 within 4 of its predicted standard errors and its spread
    within 40 % of the predicted one (the windows' correlations in it)."""
    m = parse_model('name = "lv"\n[sampling]\nTs = 0.01\n[plant]\nm = 1.0\nc = 0.8\nk = 4.0\n'
                    '[command]\nkind = "step"\namplitude = 1.0\n[process.white]\nstd = 0.5\n'
                    '[sensor.white]\nstd = 0.01\n[sensor.bias_walk]\nstd = 0.002\ninitial_std = 0.01\n'
                    '[sensor.bias_markov]\nstd = 0.005\ntau_s = 3.0\n', "lv")
    R = 300
    err, err_var = [], []
    for seed in range(R):
        rec = m.simulate(4000, seed=seed)
        v = compare(m, rec.t, rec.y, rec.u, burn=None, level=True).view("level", 0)
        err.append(v.error)
        err_var.append(v.error_var)
    err = np.array(err)
    sd_pred = math.sqrt(float(np.mean(err_var)))
    assert abs(err.mean() - 1.0) < 4 * sd_pred / math.sqrt(R), (err.mean(), sd_pred)
    assert 0.6 < err.std() / sd_pred < 1.4, (err.std(), sd_pred)
    # without a record from rest there is no level view
    with pytest.raises(KeyError):
        compare(m, rec.t, rec.y, rec.u, burn=None).view("level", 0)


@pytest.mark.slow
def test_window_variance_kurtosis_is_exact():
    """The variance view's Var(z^2) = 2 + 12 sum lambda^4 / (sum lambda^2)^2 over the eigenvalues of
    the demeaned window's covariance (a Gaussian quadratic form's fourth cumulant). The ratio equals
    the dense eigenvalue computation for white, Gauss-Markov, walk and periodic variograms (all
    eigenvalues up to KURT_DENSE samples; beyond, Lanczos for the largest and Hutchinson's estimator
    on the rest: within 2 %), and a Monte Carlo of 10,000 windows of a Gauss-Markov process with tau
    = 2.4 W (plus white noise) reproduces E z^4 (12.7) within 4 standard errors and rejects the
    chi-squared of matching variance (3 + 12 / nu = 5.0)."""
    from scipy.signal import lfilter

    from noiselab.diagnose.compare import KURT_DENSE, window_kurtosis, windowed_variance_var

    def dense(gam, W):
        a = np.arange(W)
        C = -gam[np.abs(a[:, None] - a[None, :])]
        C = C - C.mean(axis=0, keepdims=True)
        C = C - C.mean(axis=1, keepdims=True)
        lam = np.linalg.eigvalsh(C)
        return np.sum(lam**4) / np.sum(lam**2) ** 2

    for W in (64, 1500):
        d = np.arange(W)
        rho = np.exp(-1 / (2.4 * W))
        for gam in (1.0 * (d > 0), 0.3 * (d > 0) + 5 * (1 - rho**d), 1e-3 * (d > 0) + d,
                    np.sin(0.3 * d) ** 2 + 0.01 * (d > 0)):
            got, want = window_kurtosis(gam, W), dense(gam, W)
            assert got == pytest.approx(want, rel=1e-9 if W <= KURT_DENSE else 0.02), (W, got, want)

    W, K, s2, sw2 = 300, 10_000, 5.0, 0.3
    rho = np.exp(-1 / (2.4 * W))
    rng = np.random.default_rng(13)
    e = rng.standard_normal((K, W)) * np.sqrt(s2 * (1 - rho**2))
    e[:, 0] = rng.standard_normal(K) * np.sqrt(s2)
    x = lfilter([1.0], [1.0, -rho], e, axis=1) + np.sqrt(sw2) * rng.standard_normal((K, W))
    v = x.var(axis=1)
    d = np.arange(W)
    gam = sw2 * (d > 0) + s2 * (1 - rho**d)
    var = windowed_variance_var(gam, W)
    mean = sw2 * (W - 1) / W + s2 * (1 - (1 + 2 * np.sum((1 - d[1:] / W) * rho ** d[1:])) / W)
    z4 = ((v - mean) / np.sqrt(var)) ** 4
    se = z4.std(ddof=1) / np.sqrt(K)                # z^4 is heavy-tailed: se from its own spread
    want, old = 3 + 12 * window_kurtosis(gam, W), 3 + 12 / (2 * mean**2 / var)
    print(f"E z^4: Monte Carlo {z4.mean():.2f} +- {se:.2f}, exact {want:.2f}, chi-squared {old:.2f}")
    assert abs(z4.mean() - want) < 4 * se
    assert abs(z4.mean() - old) > 4 * se           # the data reject the chi-squared's value


@pytest.mark.slow
def test_acf_spread_at_lag_zero_is_exact_for_long_memory():
    """The ACF view's spread, Bartlett's formula scaled to the exact variance at lag 0 (the mean of
    the segments' variances, with the correlation between segments): a Monte Carlo of 1000 records
    of 8 contiguous segments of a Gauss-Markov process with tau = 2.4 M plus white noise reproduces
    Var(acf(0)) within 4 standard errors. (Bartlett alone, per segment and with the segments taken
    as independent, understates it about 1.9x here.)"""
    from scipy.signal import lfilter

    from noiselab.diagnose.compare import acf_view

    M, K, R, s2, sw2 = 512, 8, 1000, 5.0, 0.3
    rho = np.exp(-1 / (2.4 * M))
    d = np.arange(K * M + M)
    gam = {"x": (sw2 * (d > 0) + s2 * (1 - rho**d))[:, None]}
    rng = np.random.default_rng(12)
    e = rng.standard_normal((R, K * M)) * np.sqrt(s2 * (1 - rho**2))
    e[:, 0] = rng.standard_normal(R) * np.sqrt(s2)
    x = lfilter([1.0], [1.0, -rho], e, axis=1) + np.sqrt(sw2) * rng.standard_normal((R, K * M))
    views = [acf_view(x[i], 0.01, gam, 0, M, M // 8) for i in range(R)]
    a0 = np.array([v.empirical[0] for v in views])
    v = views[0]
    want = ((v.empirical[0] - v.predicted[0]) / v.z[0]) ** 2      # the view's variance at lag 0
    got = a0.var(ddof=1)
    se = np.sqrt((np.mean((a0 - a0.mean()) ** 4) - (R - 3) / (R - 1) * got**2) / R)
    assert abs(got - want) < 4 * se, (got, want, se)


# -- 2. an effect left out: clearly larger --------------------------------------------------------------
BASE = """
name = "one"
[sampling]
Ts = 0.01
[plant]
m = 1.0
c = 0.8
k = 3.0
[command]
kind = "sine"
amplitude = 0.5
frequency_hz = 0.3
"""
WHITE = "[sensor.white]\nstd = {}\n"
# Truth models: the mass-spring-damper above, a small white sensor noise, and the effect with a
# parameter large enough to matter physically. The command's response has amplitude ~0.17 m and
# peak rate ~0.32 m/s.
LEFT_OUT = {
    "process.white": WHITE.format(0.001) + "[process.white]\nstd = 0.3",
    "actuator.white": WHITE.format(0.001) + "[actuator.white]\nstd = 0.2",
    "actuator.ar1": WHITE.format(0.001) + "[actuator.ar1]\nstd = 0.2\ntau_s = 0.3",
    # the lag shapes the actuator noise and delays the sine's response by atan(2 pi 0.3 0.05) = 0.094 rad
    "actuator.lag": WHITE.format(0.001) + "[actuator.white]\nstd = 0.3\n[actuator.lag]\ntau_s = 0.05",
    # |command + noise| exceeds 0.6 on the sine's crests
    "actuator.saturation": WHITE.format(0.001) + "[actuator.white]\nstd = 0.2\n[actuator.saturation]\nlimit = 0.6",
    "actuator.deadzone": WHITE.format(0.001) + "[actuator.white]\nstd = 0.2\n[actuator.deadzone]\nwidth = 0.1",
    # 5 % of the 0.17 m response: an 8 mm sinusoid at the command frequency. (Under the 3x larger
    # process noise of test_model_spectra, std 0.3, it is marginal: error 9-29 over 4 seeds.)
    "sensor.scale_factor": WHITE.format(0.001) + "[process.white]\nstd = 0.1\n[sensor.scale_factor]\nerror = 0.05",
    "sensor.bias_walk": WHITE.format(0.001) + "[process.white]\nstd = 0.05\n[sensor.bias_walk]\nstd = 0.002",
    "sensor.bias_markov": WHITE.format(0.001) + "[sensor.bias_markov]\nstd = 0.01\ntau_s = 2.0",
    # the white noise itself is the effect here: a small process noise keeps the model without it non-degenerate
    "sensor.white": "[process.white]\nstd = 0.05\n" + WHITE.format(0.01),
    "sensor.tone": WHITE.format(0.002) + "[sensor.tone]\namplitude = 0.01\nfrequency_hz = 7.0",
    # ydot dt: ~0.32 m/s x 2 ms ~ 0.45 mm rms against 0.5 mm of white noise
    "sensor.jitter": WHITE.format(0.0005) + "[sensor.jitter]\nstd_s = 0.002",
    # step^2/12 = (2.9 mm)^2 on top of 5 mm of white noise (+33 % white floor); sigma/step >= 0.5, so the
    # uniform model holds (Widrow bound < 1 %), the truth model explains its own data
    "sensor.quantization": WHITE.format(0.005) + "[process.white]\nstd = 0.05\n[sensor.quantization]\nstep = 0.01",
}
N_LEFT_OUT = 40_000


def test_error_is_clearly_larger_when_an_effect_is_left_out():
    rows = []
    for eid, extra in LEFT_OUT.items():
        truth = load(BASE + extra, f"truth with {eid}")
        assert eid in truth.effects
        without = truth.without_effect(eid)
        assert eid not in without.effects
        rec = truth.simulate(N_LEFT_OUT, seed=20240611)
        e_truth = compare(truth, rec.t, rec.y, rec.u, burn=None).error
        e_without = compare(without, rec.t, rec.y, rec.u, burn=None).error
        rows.append((eid, e_truth, e_without))
    print(f"\n{'effect left out':<22} {'error_truth':>12} {'error_without':>14}   ({N_LEFT_OUT} samples, seed 20240611)")
    for eid, a, b in rows:
        print(f"{eid:<22} {a:12.3f} {b:14.4g}")
    assert {r[0] for r in rows} == set(LEFT_OUT)
    # the truth model's own error is about 1 (single record: sd ~0.5, see test 1), the other clearly larger
    bad = [r for r in rows if not (r[1] < 3 and r[2] > 5 and r[2] > 3 * r[1])]
    assert not bad, bad


# -- 3. the regions localize ------------------------------------------------------------------------------
def test_regions_localize_the_missing_colored_actuator_noise():
    """Seed data (AR(1) actuator noise, bias walk) against seed-nominal (white actuator noise of the
    same std, no walk): the colored noise puts more power near the resonance, so a psd region with
    data above the model covers it; the walk shows at long taus (an allan region)."""
    seed, nominal = load_model("seed"), load_model("seed-nominal")
    rec = seed.simulate(N_LONG, seed=5)
    c = compare(nominal, rec.t, rec.y, rec.u, burn=None)
    eig = np.linalg.eigvals(seed.plant.A)
    f_res = float(np.max(np.abs(eig.imag))) / (2 * np.pi)          # damped resonance, ~0.29 Hz
    assert 0.28 < f_res < 0.30
    psd = [r for r in c.regions if r.view == "psd" and r.x_lo <= f_res <= r.x_hi]
    assert psd, [r for r in c.regions if r.view == "psd"]
    assert psd[0].direction == "above", psd[0]
    assert any(r.view == "allan" for r in c.regions), c.regions
    # and the view itself: data above the model at the band holding the resonance
    v = c.view("psd")
    j = int(np.argmin(np.abs(np.log(v.x / f_res))))
    assert v.empirical[j] > v.hi[j]


# -- shared recording ------------------------------------------------------------------------------------
REC_SEED = 7
REC_N = 6000


@pytest.fixture(scope="module")
def seed_recording(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rec") / "seed60.mcap"
    r = cli("simulate", "seed", "--duration", "60", "--seed", REC_SEED, "--out", out)
    assert r.returncode == 0, r.stderr
    return out


# -- 4. the .rrd read back ------------------------------------------------------------------------------
def test_rrd_holds_the_numbers_of_compare(seed_recording, tmp_path):
    rrd = tmp_path / "out" / "analysis.rrd"
    rrd.parent.mkdir()
    r = cli("analyze", seed_recording, "--model", "seed-nominal", "--rrd", rrd, "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    # the same data, computed here: the simulate file holds model.simulate(n, seed) exactly
    rec = load_model("seed").simulate(REC_N, seed=REC_SEED)
    # a record from rest (seq 0): its absolute level is predicted, so the level view is in
    c = compare(load_model("seed-nominal"), rec.t, rec.y, rec.u, burn=None, level=True)
    assert rep["error"] == c.error and rep["error_per_view"] == c.error_per_view
    ch = read_chunks(rrd)
    assert np.array_equal(column(ch["/rev0/position/level"], "z")[0], c.view("level").z)
    v = c.view("psd")
    emp = ch["/rev0/position/psd/plot/empirical"]
    assert np.array_equal(column(emp, "x")[0], v.x)
    assert np.array_equal(column(emp, "y")[0], v.empirical)
    assert np.array_equal(column(ch["/rev0/position/psd/plot/predicted"], "y")[0], v.predicted)
    assert np.array_equal(column(ch["/rev0/position/psd"], "z")[0], v.z)
    # the model error per revision (one revision) is the --json error
    ov = ch["/error/overall"]
    assert column(ov, "revision") == [0]
    assert np.concatenate(column(ov, "Scalars:scalars")).tolist() == [rep["error"]]
    for name in VIEWS + ("level",):
        assert np.concatenate(column(ch[f"/error/{name}"], "Scalars:scalars")).tolist() == [rep["error_per_view"][name]]
    png = rrd.with_suffix(".png")
    assert rep["rrd"] == str(rrd) and rep["png"] == str(png)
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# -- 7. bad input: one line, exit 2 --------------------------------------------------------------------
def _imu_message(stamp_ns: int, x: float) -> bytes:
    # json.dumps writes NaN as the bare literal NaN (invalid JSON that Python's json accepts)
    return json.dumps({"header": {"stamp_ns": stamp_ns},
                       "linear_acceleration": {"x": x, "y": 0.01, "z": 9.81}}).encode()


@pytest.fixture(scope="module")
def bad_inputs(tmp_path_factory, seed_recording) -> dict:
    d = tmp_path_factory.mktemp("bad")
    seed = load_model("seed")
    rec = seed.simulate(2000, seed=1)
    # a recording with only a truth-like topic
    truth_only = d / "truth_only.mcap"
    with RecordingWriter(truth_only) as w:
        t, pub = wire.sample_times(0, 2000, seed.Ts)
        w.write_batch("noiselab/seed/truth", "truth", 0, pub, pub,
                      wire.encode_batch("truth", 0, t, rec.x, topic="noiselab/seed/truth"))
    # a foreign recording with a NaN sample
    nan = d / "nan.mcap"
    raw_json_mcap(nan, "/imu", [(k * 10_000_000, _imu_message(k * 10_000_000, float("nan") if k == 700 else
                                                                float(rec.y[k, 0]))) for k in range(2000)])
    assert b"NaN" in _imu_message(0, float("nan"))
    short = d / "short.mcap"
    r = cli("simulate", "seed", "--duration", "0.5", "--out", short)
    assert r.returncode == 0, r.stderr
    wrong_ts = d / "seed_ts002.toml"
    text = (ROOT / "service" / "scenarios" / "seed.toml").read_text()
    wrong_ts.write_text(text.replace("Ts = 0.01 ", "Ts = 0.02 ", 1))
    assert "Ts = 0.02 " in wrong_ts.read_text()
    not_mcap = d / "notes.mcap"
    not_mcap.write_text("these are notes, not a recording\n")
    (d / "a_dir.mcap").mkdir()
    # a plant with a mode at +4.4 /s: its mean response overflows within the record; refused in
    # one line, without the overflow's RuntimeWarnings before it
    unstable = d / "unstable.toml"
    plant = text[text.index("[plant]"):text.index("[command]")]
    unstable.write_text(text.replace(plant, "[plant]\nA = [[0.0, 1.0], [30.0, 5.0]]\nB = [[0.0], [1.0]]\n"
                                     "C = [[1.0, 0.0]]\n\n", 1))
    assert "A = " in unstable.read_text() and "k = " not in unstable.read_text()
    # foreign messages are untrusted: one nested 200,000 deep (Python's parser recursed out of its
    # stack), a number beyond float64, a time stamp beyond int64 ns (OverflowError tracebacks)
    deep = d / "deep.mcap"
    raw_json_mcap(deep, "/imu", [(k * 10_000_000, b'{"linear_acceleration": {"x": ' + b"[" * 200_000 + b"]" * 200_000
                                   + b"}}" if k == 300 else _imu_message(k * 10_000_000, float(rec.y[k, 0])))
                                  for k in range(2000)])
    huge = d / "huge.mcap"
    raw_json_mcap(huge, "/imu", [(k * 10_000_000, _imu_message(k * 10_000_000, float(rec.y[k, 0])) if k != 5 else
                                   b'{"header": {"stamp_ns": 50000000}, "linear_acceleration": {"x": 1' + b"0" * 400
                                   + b"}}") for k in range(2000)])
    late = d / "late.mcap"
    raw_json_mcap(late, "/imu", [(k * 10_000_000, _imu_message(10**30 if k == 9 else k * 10_000_000,
                                                                float(rec.y[k, 0]))) for k in range(2000)])
    late_publish = d / "late_publish.mcap"          # MCAP's u64 publish_time beyond int64
    raw_json_mcap(late_publish, "/imu", [(2**64 - 1 if k == 9 else k * 10_000_000, _imu_message(0, float(rec.y[k, 0])))
                                          for k in range(2000)])
    # a topic with a control character (a newline) and a value beyond the analysis' bound: the
    # one-line message escapes it
    odd = d / "odd_topic.mcap"
    topic = "noiselab/a\nb/measurement"
    y = rec.y.copy()
    y[7, 0] = 1e60
    with RecordingWriter(odd) as w:
        t, pub = wire.sample_times(0, 2000, seed.Ts)
        w.write_batch(topic, "measurement", 0, pub, pub, wire.encode_batch("measurement", 0, t, y, topic=topic))
    imu = ["--measurement", "/imu:linear_acceleration.x", "--time", "header.stamp_ns"]
    return {
        "nested 200,000 deep": ([deep, "--model", "seed", *imu], ["deep.mcap: /imu: sample 300", "deeper than 32"]),
        "number beyond float64": ([huge, "--model", "seed", *imu],
                                  ["/imu: sample 5: linear_acceleration.x = 1000", "is not a number within float64"]),
        "stamp beyond int64": ([late, "--model", "seed", *imu],
                               ["/imu: sample 9: header.stamp_ns = 1000", "is not a number of ns within int64"]),
        "publish time beyond int64": ([late_publish, "--model", "seed", "--measurement", "/imu:linear_acceleration.x"],
                                      ["/imu: sample 9: publish_time = 18446744073709551615", "of ns within int64"]),
        "control character in a topic": ([odd, "--model", "seed"], ["noiselab/a\\nb/measurement: y[0] = 1e+60 at seq 7"]),
        "no measurement topic": ([truth_only, "--model", "seed"], ["no measurement topic"]),
        "missing field": ([seed_recording, "--model", "seed", "--measurement", "noiselab/seed/measurement:y_mm"],
                          ["y_mm", "not found"]),
        "NaN samples": ([nan, "--model", "seed", "--measurement", "/imu:linear_acceleration.x", "--time",
                         "header.stamp_ns"], ["/imu", "NaN", "sample 700"]),
        "too short": ([short, "--model", "seed"], ["too short"]),
        "Ts mismatch": ([seed_recording, "--model", wrong_ts], ["0.01", "Ts is 0.02"]),
        "missing file": ([d / "absent.mcap", "--model", "seed"], ["absent.mcap", "no such file"]),
        "not MCAP": ([not_mcap, "--model", "seed"], ["notes.mcap", "not an MCAP file"]),
        "directory": ([d / "a_dir.mcap", "--model", "seed"], ["a_dir.mcap", "is a directory"]),
        "unstable plant": ([seed_recording, "--model", unstable], ["unstable mode", "process.white"]),
        # an .rrd with no file name: its PNG's name cannot be made (was a ValueError traceback)
        "rrd without a name": ([seed_recording, "--model", "seed", "--rrd", "/"], ["/: is a directory"]),
        # the model's error before the outputs' and the recording's (the recording is read early)
        "model first": ([not_mcap, "--model", "nope-model", "--rrd", "/"], ["nope-model", "no such model"]),
    }


@pytest.mark.parametrize("case", ["no measurement topic", "missing field", "NaN samples", "too short",
                                  "Ts mismatch", "missing file", "not MCAP", "directory", "unstable plant",
                                  "rrd without a name", "model first", "nested 200,000 deep", "number beyond float64",
                                  "stamp beyond int64", "publish time beyond int64", "control character in a topic"])
def test_bad_input_is_one_line_and_exit_2(bad_inputs, case):
    args, words = bad_inputs[case]
    r = cli("analyze", *args, "--json")
    lines = r.stderr.splitlines()
    assert r.returncode == 2, (r.returncode, r.stderr[-2000:])
    assert len(lines) == 1 and lines[0].startswith("noiselab: "), r.stderr
    assert "Traceback" not in r.stderr and r.stdout == ""
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_live_outputs_are_checked_before_the_run(tmp_path):
    """`analyze --live --rrd`: the .rrd and the PNG beside it (or --png) are checked before any
    session opens, as offline: no file name, an existing file without --force, a directory."""
    existing = tmp_path / "old.png"
    existing.write_text("kept")
    for args, words in ((["--rrd", "/"], ["/: is a directory"]),
                        (["--rrd", tmp_path / "new.rrd", "--png", existing], ["old.png", "exists"]),
                        (["--rrd", tmp_path / "old.rrd"], ["old.png", "exists"]),
                        (["--rrd", tmp_path], ["is a directory"])):
        r = cli("analyze", "--live", "--model", "seed-nominal", "--connect-timeout", "1", *args, "--json")
        lines = r.stderr.splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "Traceback" not in r.stderr, (args, r.stderr[-2000:])
        for w in words:
            assert w in lines[0], (w, lines[0])
    assert existing.read_text() == "kept" and not (tmp_path / "new.rrd").exists()


def test_a_model_ts_slightly_off_the_records_is_noted(seed_recording, tmp_path):
    """Within the 1 % the loader accepts, a model Ts 0.5 % off the record's step (0.01 s) is said in
    a note with the offset's sign and size; 0.05 % off (under the 0.1 % timing tolerance) is not."""
    text = (ROOT / "service" / "scenarios" / "seed.toml").read_text()
    for ts, noted in (("0.01005", True), ("0.010005", False)):
        model = tmp_path / f"seed_{ts}.toml"
        model.write_text(text.replace("Ts = 0.01 ", f"Ts = {ts} ", 1))
        r = cli("analyze", seed_recording, "--model", model, "--json")
        assert r.returncode == 0, r.stderr
        notes = [n for n in json.loads(r.stdout)["notes"] if "sample step" in n]
        if noted:
            assert len(notes) == 1 and "-0.5 % from the model's Ts = 0.01005 s" in notes[0], notes
        else:
            assert notes == [], notes


def _record_of(w: RecordingWriter, model, n: int, seed: int, kinds=("truth", "command", "measurement"),
               start_ns: int = 0) -> None:
    """``n`` samples of ``model`` from rest (seq 0) on the topics ``kinds``, written by ``w`` as
    ``simulate`` writes them; publish times from ``start_ns`` (a stream started later)."""
    b = model.simulate(n, seed=seed)
    t, pub = wire.sample_times(0, n, model.Ts)
    arrays = {"truth": b.x, "command": b.u, "measurement": b.y}
    w.write_interleaved([(wire.key(model.name, kind), kind, 0, pub + start_ns, pub + start_ns,
                          wire.encode_batch(kind, 0, t, arrays[kind], topic=wire.key(model.name, kind)))
                         for kind in kinds])


@pytest.mark.slow
def test_the_command_analysed_is_named_in_the_json_and_an_assumed_one_on_stderr(seed_recording, tmp_path):
    """A recording without a command topic (a sensor log) is analysed with the model's own
    [command]: analyze and diagnose say so on stderr once (with --json too, stdout staying JSON)
    and their JSON's ``command`` names it (source "model", its kind and parameters); a recording
    with a command topic gives source "recording" and its topic, and nothing on stderr."""
    seed = load_model("seed")
    bare = tmp_path / "no_command.mcap"
    with RecordingWriter(bare) as w:
        _record_of(w, seed, 3000, 11, kinds=("truth", "measurement"))
    said = "no command topic in the recording: the analysis assumes the model's own command ([command] kind = 'sine'"
    for command, extra in (("analyze", []), ("diagnose", ["--max-effects", "1"])):
        r = cli(command, bare, "--model", "seed", "--json", *extra)
        assert r.returncode == 0, r.stderr[-2000:]
        lines = [ln for ln in r.stderr.splitlines() if said in ln]
        assert len(lines) == 1 and lines[0].startswith(f"noiselab {command}: "), r.stderr
        rep = json.loads(r.stdout)
        assert rep["command"] == {"source": "model", "kind": "sine", "amplitude": 0.8, "frequency_hz": 0.7,
                                  "offset": 0.0, "phase_rad": 0.0}, rep["command"]
        assert sum(said in n for n in rep["notes"]) == 1
        r = cli(command, seed_recording, "--model", "seed", "--json", *extra)
        assert r.returncode == 0 and r.stderr == "", r.stderr[-2000:]
        assert json.loads(r.stdout)["command"] == {"source": "recording", "topic": "noiselab/seed/command"}


@pytest.mark.slow
def test_a_restarted_source_is_analysed_one_segment_at_a_time_chosen_with_segment(tmp_path):
    """A recording in which the source restarted (a stream of 1500 samples, then one of 3000 from
    seq 0 again, 60 s later) is analysed one stream segment at a time: by default the longest,
    with ``--segment N`` the N-th, each exactly as compare() gives it on that stream alone; the
    note names the restart and the flag. A segment beyond the recording's, or --segment with a
    foreign recording, is one line and exit 2 (analyze and diagnose)."""
    seed = load_model("seed")
    path = tmp_path / "restarted.mcap"
    with RecordingWriter(path) as w:
        _record_of(w, seed, 1500, 3)
        _record_of(w, seed, 3000, 4, start_ns=60 * 10**9)
    for segment, n, s in ((None, 3000, 4), (1, 1500, 3), (2, 3000, 4)):
        r = cli("analyze", path, "--model", "seed", "--json", *([] if segment is None else ["--segment", segment]))
        assert r.returncode == 0, r.stderr[-2000:]
        rep = json.loads(r.stdout)
        rec = seed.simulate(n, seed=s)
        c = compare(seed, rec.t, rec.y, rec.u, burn=None, level=True)      # that stream, from rest
        assert rep["error"] == c.error and rep["samples"] == c.t.size, (segment, rep["samples"])
        note, = [x for x in rep["notes"] if "restarted" in x]
        assert "2 stream segments of 1500, 3000 samples" in note, note
        assert note.endswith("analysed segment 2 (the one with the longest gap-free run; --segment N takes segment N)"
                             if segment is None else f"analysed segment {segment} (--segment {segment})"), note
    for command in ("analyze", "diagnose"):
        r = cli(command, path, "--model", "seed", "--segment", 3)
        lines = r.stderr.splitlines()
        assert r.returncode == 2 and len(lines) == 1 and r.stdout == "", r.stderr[-2000:]
        assert lines[0] == (f"noiselab: {path}: --segment 3 asked for, but noiselab/seed/measurement has 2 stream "
                            "segments (1..2)")
        r = cli(command, path, "--model", "seed", "--segment", 1, "--measurement", "noiselab/seed/measurement:y[0]")
        lines = r.stderr.splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "--segment" in lines[0] and "foreign" in lines[0], r.stderr


# -- 8. a foreign recording ---------------------------------------------------------------------------
IMU = """
name = "imu"
[sampling]
Ts = 0.005
[plant]
m = 1.0
c = 0.8
k = 3.0
[command]
kind = "none"
[process.white]
psd = 0.002
[sensor.white]
std = 0.002
[sensor.bias_markov]
std = 0.01
tau_s = 1.0
"""


def test_foreign_recording_with_gap_and_irregular_timing(tmp_path):
    """/imu (leading slash), JSON {header.stamp_ns, linear_acceleration.x}, epoch stamps in ns, a
    3-sample gap in the middle, three stamps late by 0.5 % of Ts. The data are the stationary part
    of a simulated 1-output model (the first 5 transients dropped: real data do not start at rest).

    Bound on the error: a correct model's error on one record of 10,000 samples has mean 1.00 and
    sd 0.55 (measured: 40 seeds of this model; min 0.36, max 2.5), so 0.2 < error < 1 + 5 sd."""
    path = tmp_path / "imu.mcap"
    model_file = tmp_path / "imu.toml"
    model_file.write_text(IMU)
    m = load(IMU, "imu")
    n, burn = 20_000, 5 * transient_samples(m)
    y = m.simulate(n + burn, seed=3).y[burn:, 0]
    Ts_ns = 5_000_000
    stamps = 1_700_000_000_123_456_789 + np.arange(n, dtype=np.int64) * Ts_ns
    late = [3000, 7000, 15000]
    stamps[late] += Ts_ns // 200                                      # 0.5 % of Ts
    keep = np.ones(n, bool)
    keep[10_000:10_003] = False                                      # the gap
    raw_json_mcap(path, "/imu", [(int(stamps[k]), _imu_message(int(stamps[k]), float(y[k])))
                                  for k in np.flatnonzero(keep)])
    r = cli("analyze", path, "--model", model_file, "--measurement", "/imu:linear_acceleration.x",
            "--time", "header.stamp_ns", "--json")
    assert r.returncode == 0, r.stderr
    rep = json.loads(r.stdout)
    notes = " | ".join(rep["notes"])
    print("\nforeign notes:", notes, f"\nerror {rep['error']:.3f}", rep["error_per_view"])
    assert "3 samples missing" in notes, notes
    assert "irregular timing: 6 steps" in notes, notes                # two steps around each late stamp
    # the longest gap-free run is samples 0..9999, analysed as they are (no burn: not from rest)
    assert rep["samples"] == 10_000
    ref = compare(m, (stamps[:10_000] - stamps[0]) * 1e-9, y[:10_000], None, burn=0)
    assert rep["error"] == ref.error and rep["error_per_view"] == ref.error_per_view
    assert 0.2 < rep["error"] < 1 + 5 * 0.55
    # and the analysis discriminates: without the bias instability the same data are far off
    assert compare(m.without_effect("sensor.bias_markov"), ref.t, y[:10_000], None, burn=0).error > 10


# -- 6. what the live analyzer relies on: exact predictions, cached and bounded ----------------------------
@pytest.mark.slow
@pytest.mark.parametrize("text, name", [(None, "seed (rho = 0.97)"), ("tau", "seed, tau_s = 30 s (rho = 0.99967)"),
                                        ("everything", "every effect: AR(1) + white actuator noise")])
def test_drive_noise_var_equals_the_closed_form(text, name):
    """Var of the AR(1) actuator noise from rest (noise updated before use, seed section 5):
    n_k = sum_{i<k} rho^i c e, so Var(n_{k+1}) = rho^2 c^2 (1 - rho^{2k}) / (1 - rho^2) + c^2 (+ the
    white actuator noise's std^2), evaluated in exact rational arithmetic from the model's own
    double-precision rho and c; the doubling recursion agrees to 1e-13 relative at every k, also
    where rho^{2k} is below the double epsilon (the converged tail)."""
    from fractions import Fraction

    from helpers.models import EVERYTHING
    from noiselab.model import parse_model
    from noiselab.model.model import scenario_text

    if text == "everything":
        mdl = parse_model(EVERYTHING, "everything")
    elif text == "tau":
        mdl = parse_model(scenario_text("seed").replace("rho = 0.97", "tau_s = 30.0"), "tau")
    else:
        mdl = load_model("seed")
    ar1 = mdl.effects["actuator.ar1"]
    white = mdl.effects.get("actuator.white")
    rho, c = Fraction(float(ar1.rho[0])), Fraction(float(ar1.c[0]))
    w2 = Fraction(float(white.params["std"][0])) ** 2 if white else Fraction(0)
    n = 250_000
    got = mdl.predictor().drive_noise_var(n)[:, 0]
    ks = [0, 1, 2, 3, 10, 100, 1000, 10_000, 100_000, n - 1]
    exact = [float(rho**2 * c**2 * (1 - rho ** (2 * k)) / (1 - rho**2) + c**2 + w2) for k in ks]
    assert np.allclose(got[ks], exact, rtol=1e-13, atol=0), (name, np.max(np.abs(got[ks] / exact - 1)))


def test_cached_predictions_give_the_uncached_numbers_and_stay_bounded():
    """compare() on records of growing length (what a live analyzer does while its window fills:
    the variogram is computed once for a generous length and sliced) gives exactly the floats of a
    cold compare() of each record; the cache holds at most its byte bound, keeps one variogram
    per model, and a model whose text differs is a different entry."""
    from noiselab.diagnose import compare as cm

    mdl = load_model("seed")
    rec = mdl.simulate(12_000, seed=5)
    lengths = [3000, 3500, 5000, 7001, 12_000]
    cm.cache_clear()
    warm = [compare(mdl, rec.t[:n], rec.y[:n], rec.u[:n], burn=None) for n in lengths]
    gammas = [v for k, v in cm.CACHE.items() if k[1] == "gamma"]
    assert len(gammas) == 1 and gammas[0][0] >= 12_000 - transient_samples(mdl)
    assert 0 < cm.CACHE.bytes <= cm.CACHE.nbytes
    for n, w in zip(lengths, warm):
        cm.cache_clear()
        cold = compare(mdl, rec.t[:n], rec.y[:n], rec.u[:n], burn=None)
        assert w.error == cold.error and w.error_per_view == cold.error_per_view
        for a, b in zip(w.views, cold.views):
            assert np.array_equal(a.predicted, b.predicted) and np.array_equal(a.z, b.z), (n, a.name)
    # a byte bound smaller than one variogram: computed, used, not kept; the bound holds
    other = load_model("seed-nominal")
    old = cm.CACHE.nbytes
    try:
        cm.CACHE.nbytes = 64 * 1024
        c_small = compare(other, rec.t, rec.y, rec.u, burn=None)
        assert cm.CACHE.bytes <= cm.CACHE.nbytes
    finally:
        cm.CACHE.nbytes = old
    cm.cache_clear()
    assert compare(other, rec.t, rec.y, rec.u, burn=None).error == c_small.error


_COARSE_QUANT_DOC = """name = "q"
[sampling]
Ts = 0.005
[plant]
m = 1.0
c = 1.0
k = 10.0
[command]
kind = "sine"
amplitude = 1.0
frequency_hz = 0.4
[process.white]
std = 0.5
[sensor.white]
std = 0.002
[sensor.quantization]
step = 0.02
"""


def test_cached_predictions_follow_the_record_when_a_coarse_quantizer_makes_them_depend_on_it():
    """A coarse quantizer's error is correlated over the record's own mean response, so every view's
    prediction depends on the record, not only on the model: comparing one record and then another
    (a live window sliding from a moving to a still command) gives the second's cold numbers. The
    views' cache was keyed by the model alone, and the PSD view read 120 where its cold value is 2."""
    from noiselab.diagnose import compare as cm

    text = _COARSE_QUANT_DOC
    moving = parse_model(text, "moving")
    still = parse_model(text.replace("amplitude = 1.0", "amplitude = 0.0"), "still")
    a = moving.simulate(24_000, seed=1)
    b = still.simulate(24_000, seed=2)
    cm.cache_clear()
    cold = compare(moving, b.t, b.y, b.u, burn=None)
    cm.cache_clear()
    first = compare(moving, a.t, a.y, a.u, burn=None)
    warm = compare(moving, b.t, b.y, b.u, burn=None)
    # the first record's predictions differ from the second's (what a shared entry would hand over)
    assert any(not np.array_equal(x.predicted, y.predicted) for x, y in zip(first.views, cold.views))
    assert warm.error == cold.error and warm.error_per_view == cold.error_per_view
    for x, y in zip(warm.views, cold.views):
        assert np.array_equal(x.predicted, y.predicted), x.name


@pytest.mark.slow
def test_psd_view_spread_holds_at_a_resonance_narrower_than_a_welch_bin():
    """A lightly damped plant (zeta 0.01 at 1 Hz: half-power width 0.02 Hz, a Welch bin 0.024 Hz)
    has a correlation time longer than a segment, so the bands at its resonance know less than the
    flat-spectrum dof say. Over 100 right-model records the PSD view's z^2 at the resonance band
    must average 1 (within 4 standard errors of the records' own spread): with the flat dof it
    averaged 5.8, and right models of lightly damped plants read model errors above 1.5."""
    from noiselab.diagnose.compare import (default_settings, predictor_of, psd_band_dof_factor, psd_fine_length,
                                          psd_view)
    from noiselab.stats import welch
    from noiselab.stats.psd import log_bin_groups

    wn = 2 * np.pi
    mdl = parse_model(f"""name = "ld"
[sampling]
Ts = 0.01
[plant]
m = 1.0
c = {2 * 0.01 * wn}
k = {wn**2}
[command]
kind = "none"
[process.white]
std = 1.0
[sensor.white]
std = 0.001
""", "light damping")
    n, burn = 32_768, 3000
    L = default_settings(n)["nperseg"]
    gam = predictor_of(mdl).variogram(n + 1, quantization=False)
    short = {k: g[:L] for k, g in gam.items()}
    z_model, z_flat = [], []
    for seed in range(100):
        r = mdl.simulate(n + burn, seed=1000 + seed).y[burn:, 0]
        z_model.append(psd_view(r, mdl.Ts, short, 0, L, 10, gam_fine=gam).z)
        z_flat.append(psd_view(r, mdl.Ts, short, 0, L, 10).z)
    z_model, z_flat = np.array(z_model) ** 2, np.array(z_flat) ** 2
    view = psd_view(r, mdl.Ts, short, 0, L, 10, gam_fine=gam)
    est = welch(r, 1.0 / mdl.Ts, nperseg=L)
    fac = psd_band_dof_factor(sum(g[:, 0] for g in gam.values()), None, L, log_bin_groups(est.f, 10),
                              psd_fine_length(L, n))
    band, next_ = np.argsort(fac)[:2]
    assert 0.9 < view.x[band] < 1.3 and fac[band] < 0.3 and abs(band - next_) == 1, (view.x[band], fac)
    assert any("dof under the model's spectrum" in note for note in view.notes)
    for b in (band, next_):
        z2 = z_model[:, b]
        se = z2.std(ddof=1) / np.sqrt(z2.size)
        assert abs(z2.mean() - 1) < 4 * se, (view.x[b], z2.mean(), se)
    z2 = z_flat[:, band]
    assert z2.mean() > 1 + 4 * z2.std(ddof=1) / np.sqrt(z2.size)     # the flat dof: what it mends
    # where the spectrum is flat across the bands (below 0.3 Hz the plant's static gain, above
    # 10 Hz the sensor's white floor) the dof are the flat ones, to under 1 %; between, the
    # 1/f^4 roll-off is not flat across a band either, and the dof fall by up to ~7 % there
    far = (view.x < 0.3) | (view.x > 10.0)
    assert np.allclose(fac[far], 1.0, atol=0.01), fac


@pytest.mark.slow
def test_psd_view_a_tones_band_varies_only_through_the_noise_under_it():
    """A tone's power in a band is the same in every Welch segment (a fixed amplitude, a random
    phase): its band's estimate varies through the noise under the tone and the tone x noise
    product only. Over 100 right-model records the band's z^2 must average 1 within 4 standard
    errors (the flat dof, which treated the tone as Gaussian noise, gave 0.004: a model amplitude
    10 % off read z = -3 there); and a model amplitude 10 % too high must stand out (|z| > 10)."""
    from noiselab.diagnose.compare import default_settings, predictor_of, psd_view

    def model(amplitude):
        return parse_model(f"""name = "tone"
[sampling]
Ts = 0.01
[plant]
m = 1.0
c = 4.0
k = 10.0
[command]
kind = "none"
[process.white]
std = 1.0
[sensor.white]
std = 0.01
[sensor.tone]
amplitude = {amplitude}
frequency_hz = 3.3
""", "tone")
    n, burn = 32_768, 500
    L = default_settings(n)["nperseg"]
    right, high = model(0.05), model(0.055)
    views = {}
    for name, mdl in (("right", right), ("high", high)):
        gam = predictor_of(mdl).variogram(n + 1, quantization=False)
        views[name] = (gam, {k: g[:L] for k, g in gam.items()})
    z_right, z_high = [], []
    for seed in range(100):
        r = right.simulate(n + burn, seed=2000 + seed).y[burn:, 0]
        v = psd_view(r, right.Ts, views["right"][1], 0, L, 10, gam_fine=views["right"][0], line_ids={"sensor.tone"})
        band = int(np.argmin(np.abs(v.x - 3.3)))
        z_right.append(v.z[band])
        if seed < 5:
            vh = psd_view(r, right.Ts, views["high"][1], 0, L, 10, gam_fine=views["high"][0], line_ids={"sensor.tone"})
            z_high.append(vh.z[band])
    z2 = np.array(z_right) ** 2
    assert abs(z2.mean() - 1) < 4 * z2.std(ddof=1) / np.sqrt(z2.size), z2.mean()
    assert np.all(np.array(z_high) < -10), z_high


def test_psd_band_dof_factor_is_one_for_a_flat_spectrum_bounded_for_a_bare_tone_and_on_the_grid():
    """The factor on the bands' dof: 1 for white noise (to 1e-3), whatever the segment
    length (1000 samples: G = L 2^k puts every bin on the grid); finite and at most PSD_DOF_MAX for
    a tone over no noise at all (a band known exactly); lowest at a resonance's band for segments of
    1000 and of 1024 samples alike (G was a power of two: 8192 for L = 1000, and 2G // L = 16 grid
    points per bin where there are 16.4 put the bins up to 12 bins off by Nyquist)."""
    from noiselab.diagnose.compare import PSD_DOF_MAX, psd_band_dof_factor, psd_fine_length
    from noiselab.stats.psd import log_bin_groups

    n = 10_001                                                      # G = 8000 for L = 1000 (2G // L exact)
    d = np.arange(n + 1, dtype=float)
    white = np.where(d > 0, 1.0, 0.0)                               # gamma of unit white noise
    for L in (1000, 1024):
        G = psd_fine_length(L, n)
        assert G % L == 0 and 4 * L <= G <= n
        groups = log_bin_groups(np.fft.rfftfreq(L), 10)
        # to 1e-3: the R(0) V(f) term the variogram form leaves out touches the first bins (2e-5 here)
        assert np.allclose(psd_band_dof_factor(white, None, L, groups, G), 1.0, rtol=1e-3, atol=0)
        f0, zeta = 0.2, 0.002                                          # cycles/sample
        rho, w0 = np.exp(-zeta * 2 * np.pi * f0), 2 * np.pi * f0
        R = rho**d * np.cos(w0 * d)                                    # a narrow resonance's ACF
        fac = psd_band_dof_factor(R[0] - R + 1e-3 * white, None, L, groups, G)
        b = int(np.argmin(fac))
        f_band = np.fft.rfftfreq(L)[groups[b]]
        assert fac[b] < 0.5 and f_band.min() - 1.0 / L <= f0 <= f_band.max() + 1.0 / L, (L, f_band, fac[b])
    L = 1024
    G = psd_fine_length(L, n)
    groups = log_bin_groups(np.fft.rfftfreq(L), 10)
    tone = 0.5 * (1 - np.cos(2 * np.pi * 0.1234 * d))                # unit amplitude, no noise
    fac = psd_band_dof_factor(tone, tone, L, groups, G)
    assert np.all(np.isfinite(fac)) and fac.max() <= PSD_DOF_MAX and fac.max() == PSD_DOF_MAX


def test_acf_spread_does_not_depend_on_the_other_views_settings():
    """The ACF view's spread covers every pair of its segments from the variogram to the record's
    length, so it is the same whatever the other views' sizes (a live analyzer sets its own
    variance window): once read from a variogram cut to the longest of them, it depended on the
    window (live and offline differed by 0.02 in the model error). A Gauss-Markov bias as long as
    a segment makes the segments' variances correlate, which is where it shows."""
    from noiselab.diagnose import compare as cm

    mdl = parse_model((ROOT / "service" / "scenarios" / "seed.toml").read_text()
                      + "\n[sensor.bias_markov]\nstd = 0.01\ntau_s = 5.0\n")
    rec = mdl.simulate(3000, seed=2)
    acf = []
    for window in (16, 700):
        cm.cache_clear()
        c = compare(mdl, rec.t, rec.y, rec.u, burn=None, settings={"window": window})
        acf.append(next(v for v in c.views if v.name == "acf"))
    assert np.array_equal(acf[0].z, acf[1].z) and np.array_equal(acf[0].hi, acf[1].hi)


def test_live_history_is_thinned_not_unbounded():
    """The live analyzer's error history (the .rrd's error over time) stops at HISTORY_MAX entries:
    it keeps every other one when full, and the first entry of every revision."""
    import io

    from noiselab.nodes import analyzer

    an = analyzer.LiveAnalyzer("seed", device=None, window_s=5.0, log=io.StringIO())
    for i in range(3 * analyzer.HISTORY_MAX):
        an.add_history({"t": i * 0.5, "revision": 0 if i < 1000 else 1, "error": 1.0, "error_per_view": {}})
        assert len(an.history) < analyzer.HISTORY_MAX
    ts = [h["t"] for h in an.history]
    assert ts == sorted(ts) and ts[0] == 0.0 and ts[-1] == (3 * analyzer.HISTORY_MAX - 1) * 0.5
    assert 500.0 in ts                                     # revision 1 starts at i = 1000


def test_live_update_ends_at_the_newest_complete_sample():
    """Measurement and command arrive on separate subscriber threads, so at an update the newest
    measurements may still miss their command: the update analyses up to the newest sample that
    has both (exactly compare() on that prefix), instead of finding no complete run at all."""
    import io

    from noiselab.nodes import analyzer

    mdl = load_model("seed")
    rec = mdl.simulate(1000, seed=2)
    an = analyzer.LiveAnalyzer("seed", device=None, window_s=60.0, log=io.StringIO())
    for k in range(1000):
        an.meas.put(k, float(rec.t[k]), rec.y[k])
        if k < 997:
            an.cmd.put(k, float(rec.t[k]), rec.u[k])
    got = an.analyse()
    ref = compare(mdl, rec.t[:997], rec.y[:997], rec.u[:997], burn=None, level=True)   # seq 0: from rest
    assert got is not None and got.t.size == 997
    assert got.error == ref.error and got.error_per_view == ref.error_per_view


@pytest.mark.slow
def test_a_coarse_quantizer_over_little_noise_right_model_reads_about_one():
    """An encoder-like sensor: a step of 0.5 over a sensor noise of 0.04 (0.08 step), a sine moving
    the mean across ~11 steps. The quantizer's error is then mostly a function of the mean: its
    conditional mean E[Q(x)] - mu (up to half a step) belongs in the mean response, and the
    measurement's variance follows the mean's place between the levels (~0 on a level, Delta^2 / 4
    on a threshold half-way between two). Over 12 right-model records: the record-averaged residual's power matches the
    predicted Var(y_k) / 12 (within 4 standard errors of its terms), the variance view's z^2
    averages 1 (within 4 standard errors of the records' own spread), and no model error is above
    1.5 (they average 0.95). Before, the conditional mean was left in the residual: power ratio 17, model
    errors 6-12."""
    mdl = parse_model(ENCODER_TOML, "encoder")
    n, burn = 24_000, 4000
    pr = mdl.predictor()
    mo = pr.quantizer_moments(pr.mean_response(n).y)
    assert mo is not None and mo.active[0]
    res, errs, z2 = [], [], []
    for seed in range(12):
        rec = mdl.simulate(n, seed=seed)
        c = compare(mdl, rec.t, rec.y, rec.u, burn=None, level=True)
        res.append(rec.y[:, 0] - c.y_mean[:, 0])
        errs.append(c.error)
        z2.append(np.mean(next(v for v in c.views if v.name == "variance").z ** 2))
    avg = np.mean(res, axis=0)[burn:]
    expect = mo.var_y[burn:, 0] / 12
    ratio = np.sum(avg**2) / np.sum(expect)
    se = np.sqrt(np.sum((avg**2 - expect) ** 2)) / np.sum(expect)
    assert abs(ratio - 1) < 4 * se, (ratio, se)
    z2 = np.array(z2)
    assert abs(np.mean(z2) - 1) < 4 * np.std(z2, ddof=1) / np.sqrt(z2.size), z2
    # the model error's spreads are approximate (the PSD and Allan views' under the modulation):
    # the product's own criterion, a right model explained (ERROR_OK)
    assert max(errs) < 1.5, errs


@pytest.mark.slow
def test_a_motor_measured_by_angle_and_speed_holds_the_speed_to_its_levels():
    """Two outputs, one of which (the angle) the plant's walk reaches: the level view, which needs
    a stationary variance, runs for the speed alone (it was off for both: one flag per model), and
    on the right model its error averages 1 within three standard errors of the view's own
    error variance over 8 records."""
    text = (Path(__file__).resolve().parents[2] / "service" / "scenarios" / "motor.toml").read_text()
    m = parse_model(text.replace("C = [[1.0, 0.0]]", "C = [[1.0, 0.0], [0.0, 1.0]]"), "motor2")
    assert m.p == 2
    errs, evars = [], []
    for seed in range(8):
        rec = m.simulate(12000, seed=100 + seed)
        c = compare(m, rec.t, rec.y, rec.u, level=True)
        lv = [v for v in c.views if v.name == "level"]
        assert [v.output for v in lv] == [1]
        errs.append(lv[0].error)
        evars.append(lv[0].error_var)
    assert np.all(np.isfinite(evars))
    assert abs(np.mean(errs) - 1.0) <= 3.0 * math.sqrt(np.mean(evars) / len(errs)), (errs, evars)


def test_a_region_is_one_side_of_the_model():
    """A run of flagged points whose z changes sign is two regions, each with its own direction and
    largest |z| (an ACF above the model at short lags and below it after was one region "below",
    with its largest |z| on the side above)."""
    from noiselab.diagnose.compare import regions_of
    from noiselab.diagnose.results import View
    z = np.array([0.0, 5.0, 6.0, -7.0, -4.0, 0.5, 3.0])
    x = np.arange(z.size, dtype=float)
    v = View("acf", 0, x, "lag [s]", "acf", z, z, z, z, z=z, flagged=np.abs(z) > 2)
    got = [(r.x_lo, r.x_hi, r.points, r.max_abs_z, r.direction) for r in regions_of(v)]
    assert got == [(1.0, 2.0, 2, 6.0, "above"), (3.0, 4.0, 2, 7.0, "below"), (6.0, 6.0, 1, 3.0, "above")]


def test_a_psd_region_spans_its_bands_edges():
    """A 50 Hz tone missing from the model flags the PSD band that holds it; the region spans that
    band's edges, so it contains 50 Hz (it gave the band's mean frequency, 44.98..44.98 Hz)."""
    truth, nominal = load_model("hidden/sensor.tone"), load_model("hidden/sensor.tone-nominal")
    rec = truth.simulate(30_000, seed=1)
    c = compare(nominal, rec.t, rec.y, rec.u)
    psd = [r for r in c.regions if r.view == "psd"]
    assert psd and any(r.x_lo <= 50.0 <= r.x_hi and r.direction == "above" for r in psd), psd
    v = c.view("psd")
    assert np.all(v.x_lo <= v.x) and np.all(v.x <= v.x_hi) and np.all(v.x_hi[:-1] <= v.x_lo[1:] + 1e-9)
