"""``sensor.white``: white measurement noise v_k ~ N(0, std^2) (seed: sigma_v).

Two spellings, exactly one in a file: ``std``, the per-sample standard deviation in the output's
units, or ``density``, the noise density in units/sqrt(Hz) that IMU data sheets and calibration
tools (Kalibr, allan_variance_ros, imu_utils) give: std = density / sqrt(Ts). The density is
IEEE Std 952's N (angle random walk of a gyro, velocity random walk of an accelerometer): the
mean of m samples over tau = m Ts has variance std^2 / m = N^2 / tau, so the Allan deviation is

    sigma_A(tau) = N / sqrt(tau),      N = std sqrt(Ts)          (IEEE Std 952-1997, Annex C;
                                                                  El-Sheimy et al. 2008, table 1)

and N^2 is the two-sided PSD level (units^2/Hz; one-sided 2 N^2) below the Nyquist frequency.
The noise is held as ``std`` (what the simulation, predictions and diagnosis use) and written back
in the file's spelling, a refit too (:meth:`SensorWhite.respell`).
"""

from __future__ import annotations

import numpy as np

from ...bounds import MAGNITUDE_MAX
from ..schema import nonnegative
from .base import Coefficient, Effect, FitSpec, _g, _map, _plain_value


class SensorWhite(Effect):
    id = "sensor.white"
    stage = "sensor"
    chain_order = 9
    draw_order = 5
    summary = "white sensor noise"
    fit = FitSpec("noise", scale="std")
    # -- diagnosis hooks (base module docstring)
    channels = "output"

    def output_white_std(self):
        return self.params["std"]

    @classmethod
    def explain(cls, params, Ts, ctx=None):
        band = (ctx or {}).get("band")
        where = f"above {_g(band[0])} Hz" if band else "at high frequency"
        std = params["std"] if "std" in params else _map(lambda d: d / np.sqrt(Ts), params["density"])
        dens = params["density"] if "density" in params else _map(lambda s: s * np.sqrt(Ts), params["std"])
        return (f"a flat floor {where} that the plant does not shape, the same in every time window: "
                f"white sensor noise of std {_g(std)} (density {_g(dens)} per sqrt(Hz))")

    @classmethod
    def equivalents(cls, params, Ts):
        """std = density / sqrt(Ts) and back."""
        if "std" in params and "density" not in params:
            return {"density": _map(lambda s: s * float(np.sqrt(Ts)), params["std"])}
        if "density" in params and "std" not in params:
            return {"std": _map(lambda d: d / float(np.sqrt(Ts)), params["density"])}
        return {}

    def parse(self, t):
        if t.has("std") and t.has("density"):
            raise t.error("std", "give exactly one of std (per-sample std, output units) or density "
                                 "(output units/sqrt(Hz); std = density/sqrt(Ts))")
        Ts = self.dims.Ts
        if not t.has("density"):            # neither: std's "missing required key", with a misspelling hint
            self.density = None
            self.params["std"] = t.vector("std", self.dims.p, check=nonnegative, expect="std >= 0")
            return
        self.density = t.vector("density", self.dims.p, check=nonnegative, expect="densities >= 0 in units/sqrt(Hz)")
        std = self.density / np.sqrt(Ts)
        if np.any(std > MAGNITUDE_MAX):
            raise t.error("density", f"expected densities whose std = density/sqrt(Ts) (Ts = {Ts:g} s) is at most "
                                     f"{MAGNITUDE_MAX:g}, got {_g(self.density)}")
        self.params["std"] = std

    def param_dict(self):
        if self.density is None:
            return super().param_dict()
        return {"density": _plain_value(self.density)}

    def respell(self, values):
        if self.density is None or "std" not in values:
            return values
        out = dict(values)
        out["density"] = _map(lambda s: s * float(np.sqrt(self.dims.Ts)), out.pop("std"))
        return out

    def coefficients(self):
        rt = float(np.sqrt(self.dims.Ts))
        n = self.params["std"] * rt if self.density is None else self.density     # as given, when given
        return [Coefficient("N", n, "{u}/sqrt(Hz)", "std", lambda s: np.asarray(s, float) * rt, white=True)]

    def n_normals(self):
        return self.dims.p

    def sensor_terms(self, e, state):
        return self.params["std"] * e

    def spectral(self):
        return [("white", self.params["std"] ** 2)]
