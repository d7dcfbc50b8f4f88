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
