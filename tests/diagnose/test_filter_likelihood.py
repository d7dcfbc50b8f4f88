"""What a diagnosis of the sensor's own filter has to work with: on the hidden pair's record (a
4-tap moving average on white noise, 3 minutes at 100 Hz) the spectral likelihood of the nominal
model with a filter added, its white noise's variance fitted (the inner fit), peaks at the planted
filter by a wide margin, the fitted std recovers the planted one, and the likelihood over the
taps is not unimodal (a moving average of N taps has spectral nulls at multiples of fs / N: a
search over taps has to scan the integers, a golden section would stop at a wrong one)."""

from __future__ import annotations

from noiselab.diagnose.data import Data
from noiselab.diagnose.edits import _set
from noiselab.diagnose.hypotheses import Hypotheses
from noiselab.model import load_model


def test_the_likelihood_over_filters_peaks_at_the_planted_one():
    truth, nom = load_model("hidden/sensor.filter"), load_model("hidden/sensor.filter-nominal")
    rec = truth.simulate(round(180.0 / truth.Ts), seed=11)
    H = Hypotheses(Data(rec.y, rec.u, nom.Ts, True, 0), nom)
    free = {"sensor.white": ["std"]}
    base = H.inner_fit(nom, free).loglik

    def gain(**params):
        f = H.inner_fit(_set(nom, "sensor.filter", params), free)
        return f.loglik - base, float(f.model.effects["sensor.white"].params["std"][0])

    by_taps = {n: gain(kind="average", taps=n)[0] for n in range(2, 9)}
    best, std = gain(kind="average", taps=4)
    assert max(by_taps, key=by_taps.get) == 4, by_taps
    assert best > 1000.0                          # far above any Delta BIC threshold
    assert abs(std / 0.01 - 1) < 0.05, std
    assert by_taps[3] < 0 < by_taps[2]           # not unimodal in taps: 2 above the nominal, 3 below
    for kind in ("lowpass1", "lowpass2"):
        for fc in (3.0, 6.0, 10.0, 15.0, 25.0, 40.0):
            assert gain(kind=kind, cutoff_hz=fc)[0] < best - 1000.0, (kind, fc)


def test_the_diagnosis_finds_a_low_pass_and_its_cutoff():
    """A sensor whose white noise leaves through a second-order low-pass (12 Hz at 100 Hz) and a
    quantizer after it; its model has the white noise only. The diagnosis adds the quantizer and
    the filter, names the kind, its cutoff inside the 95 % interval and within 5 %, and the model
    error falls to about one; the taps and kinds it tried stand behind one candidate."""
    from noiselab.diagnose.diagnose import diagnose
    from noiselab.model import parse_model

    base = 'name = "g"\n[sampling]\nTs = 0.01\n[outputs]\nnames = ["gx"]\nunits = ["rad/s"]\n[sensor.white]\nstd = 0.01\n'
    truth = parse_model(base + '[sensor.filter]\nkind = "lowpass2"\ncutoff_hz = 12.0\n[sensor.quantization]\nstep = 0.002\n')
    rec = truth.simulate(18_000, seed=2)
    rep = diagnose(parse_model(base), rec.t, rec.y, rec.u)
    got = {m["effect"]: m for m in rep["missing"]}
    assert set(got) == {"sensor.quantization", "sensor.filter"}, list(got)
    f = got["sensor.filter"]
    assert f["params"]["kind"] == "lowpass2" and f["mode"] == "add"
    lo, hi = f["interval"]["cutoff_hz"]
    assert lo <= 12.0 <= hi and abs(f["params"]["cutoff_hz"] / 12.0 - 1) < 0.05, (f["params"], lo, hi)
    assert "low-pass" in f["evidence"] or "lowpass2" in f["evidence"]
    assert sum(c["effect"] == "sensor.filter" for c in rep["candidates"]) == 1
    assert rep["error_before"] > 20 and rep["error_after"] <= 1.5


def test_a_tone_before_the_filter_is_fitted_at_its_amplitude_before_it():
    """A line enters before the sensor's own filter (chain order), so the measurement holds it at
    |H(f)| times the model's amplitude: a 3-tap average passes 17.21 Hz at 100 Hz with gain
    sin(3 pi f Ts) / (3 sin(pi f Ts)) = 0.647. The diagnosis finds both and reports the amplitude
    before the filter (the model file's), its interval holding the planted one; a residual cached
    for the same tone without the filter would have kept the measured 0.647 A (model error 71)."""
    from noiselab.diagnose.diagnose import diagnose
    from noiselab.model import parse_model

    base = 'name = "g"\n[sampling]\nTs = 0.01\n[outputs]\nnames = ["gx"]\nunits = ["rad/s"]\n[sensor.white]\nstd = 0.01\n'
    truth = parse_model(base + '[sensor.tone]\namplitude = 0.0073\nfrequency_hz = 17.21\n'
                        '[sensor.filter]\nkind = "average"\ntaps = 3\n')
    rec = truth.simulate(18_000, seed=6)
    rep = diagnose(parse_model(base), rec.t, rec.y, rec.u)
    got = {m["effect"]: m for m in rep["missing"]}
    assert set(got) == {"sensor.tone", "sensor.filter"}, list(got)
    assert got["sensor.filter"]["params"] == {"kind": "average", "taps": 3}
    a = got["sensor.tone"]["params"]["amplitude"]
    lo, hi = got["sensor.tone"]["interval"]["amplitude"]
    assert lo <= 0.0073 <= hi and abs(a / 0.0073 - 1) < 0.05, (a, lo, hi)
    assert rep["error_after"] <= 1.5
