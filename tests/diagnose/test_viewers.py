"""Viewers: the .rrd written by noiselab.viewers.rerun_log is read back with rerun.chunk.RrdReader (rerun-sdk
0.41.0 API: ``RrdReader(path)``, ``.recordings()`` / ``.blueprints()`` -> [StoreEntry],
``.store(store=entry)`` -> LazyStore (needs the footer), ``.stream(store=entry)`` -> LazyChunkStream of
Chunk with ``.entity_path``, ``.num_rows``, ``.is_static``, ``.timeline_names``,
``.to_record_batch()`` -> pyarrow RecordBatch whose columns are ``rerun.controls.RowId``, one per
timeline (``t`` duration[ns], ``revision`` int64) and one per component (``Scalars:scalars``,
``LineStrips2D:strips``, AnyValues keys such as ``y``), each a list array (one list per row)).
The summary PNG is read back with matplotlib.image.imread. No mocks: real files, real rerun.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from helpers.rrd import column, read_chunks

from noiselab.diagnose.results import Comparison, Region, View
from noiselab.viewers.comparisons import ViewerInputError
from noiselab.viewers.report import report_markdown
from noiselab.viewers.rerun_log import log_comparisons
from noiselab.viewers.summary_png import figure_size_px, write_summary_png

N = 2000
TS = 0.01


# -- synthetic comparisons -------------------------------------------------------------------------------
def _regions(view: View) -> list:
    out, f, i = [], view.flagged, 0
    while i < f.size:
        if not f[i]:
            i += 1
            continue
        k = i
        while k + 1 < f.size and f[k + 1]:
            k += 1
        zz = view.z[i:k + 1]
        out.append(Region(view.name, view.output, float(view.x[i]), float(view.x[k]), k - i + 1,
                          float(np.max(np.abs(zz))), "above" if zz.mean() > 0 else "below"))
        i = k + 1
    return out


def _finish(v: View) -> View:
    v.flagged = np.abs(v.z) > 3.0
    v.error = float(np.mean(v.z ** 2))
    return v


def make_comparison(rng, revision: int, p: int, with_tone_effect: bool, truth: bool = True,
                    level: bool = False) -> Comparison:
    """A model with sensor.white + process.white; the data hold a tone at 5 Hz too. Revision with
    ``with_tone_effect`` has the tone in the model (error about 1), otherwise the PSD and ACF are
    flagged around it. The recording (t, y, truth) depends on p only, as for model revisions
    checked against one recording; ``rng`` draws the statistics' sampling noise."""
    t = np.arange(N) * TS
    x0 = 0.5 * np.sin(2 * np.pi * 0.7 * t)
    truth_x = np.column_stack([x0, np.gradient(x0, TS)])
    data_rng = np.random.default_rng(1000 + p)
    y = np.column_stack([x0 + 0.05 * (j + 1) * data_rng.standard_normal(N) + 0.02 * np.sin(2 * np.pi * 5 * t)
                         for j in range(p)])
    mean = np.column_stack([x0] * p)
    sd = np.full((N, p), 0.05) * (1 + np.arange(p))
    views = []
    for j in range(p):
        s2 = (0.05 * (j + 1)) ** 2
        # variance over 40 windows
        xc = (np.arange(40) + 0.5) * N / 40 * TS
        parts = {"sensor.white": np.full(40, s2), "process.white": np.full(40, 0.2 * s2)}
        if with_tone_effect:
            parts["sensor.tone"] = np.full(40, 0.02 ** 2 / 2)
        pred = sum(parts.values())
        emp = (s2 * 1.2 + 0.02 ** 2 / 2) * rng.chisquare(49, 40) / 49
        if not with_tone_effect:
            emp[12:14] *= 3.0           # a burst the model does not explain: flagged windows
        views.append(_finish(View("variance", j, xc, "time [s]", "variance [units^2]", emp, pred, 0.6 * pred,
                                  1.5 * pred, contributions=parts, z=(emp / pred - 1) / 0.2)))
        # acf, lags 0..0.5 s
        lag = np.arange(51) * TS
        parts = {"sensor.white": np.where(lag == 0, s2, 0.0), "process.white": 0.2 * s2 * np.exp(-lag / 0.1)}
        if with_tone_effect:
            parts["sensor.tone"] = 0.02 ** 2 / 2 * np.cos(2 * np.pi * 5 * lag)
        pred = sum(parts.values())
        emp = pred + 0.02 ** 2 / 2 * np.cos(2 * np.pi * 5 * lag) * (not with_tone_effect) \
            + 2e-5 * rng.standard_normal(lag.size)
        se = np.full(lag.size, 4e-5)
        views.append(_finish(View("acf", j, lag, "lag [s]", "autocovariance [units^2]", emp, pred,
                                  pred - 3 * se, pred + 3 * se, contributions=parts, z=(emp - pred) / se)))
        # psd, log-spaced bands 0.05..50 Hz
        f = np.logspace(np.log10(0.05), np.log10(50), 31)
        parts = {"sensor.white": np.full(f.size, 2 * s2 * TS), "process.white": 1e-4 * s2 / (f ** 2 + 0.5)}
        tone = np.where(np.abs(np.log10(f / 5.0)) < 0.06, 0.02 ** 2 / 2 / 0.7, 0.0)
        if with_tone_effect:
            parts["sensor.tone"] = tone
        pred = sum(parts.values())
        emp = (sum(v for k, v in parts.items() if k != "sensor.tone") + tone) * rng.chisquare(40, f.size) / 40
        views.append(_finish(View("psd", j, f, "frequency [Hz]", "PSD [units^2/Hz]", emp, pred, 0.6 * pred,
                                  1.6 * pred, contributions=parts, z=np.log(emp / pred) / 0.22,
                                  log_x=True, log_y=True, notes=["Welch, Hann, synthetic"])))
        # allan, octave taus
        tau = TS * 2.0 ** np.arange(9)
        parts = {"sensor.white": np.sqrt(s2) / np.sqrt(tau / TS), "process.white": 0.01 * np.sqrt(s2) * np.sqrt(tau)}
        pred = np.sqrt(sum(a ** 2 for a in parts.values()))
        emp = pred * (1 + 0.05 * rng.standard_normal(tau.size))
        if not with_tone_effect:
            emp[3:5] *= 2.0
        views.append(_finish(View("allan", j, tau, "tau [s]", "Allan deviation [units]", emp, pred, 0.8 * pred,
                                  1.25 * pred, contributions=parts, z=np.log(emp / pred) / 0.1,
                                  log_x=True, log_y=True)))
        if level:       # window means of y - E[y] against 0 (a record from rest)
            xc = (np.arange(20) + 0.5) * N / 20 * TS
            sd_w = np.full(20, 0.05 * (j + 1) / np.sqrt(N / 20))
            emp = sd_w * rng.standard_normal(20) + (0.0 if with_tone_effect else 3 * sd_w)
            views.append(_finish(View("level", j, xc, "time [s]", "mean of y - E[y] in the window [units]", emp,
                                      np.zeros(20), -3 * sd_w, 3 * sd_w, z=emp / sd_w)))
    names = ("variance", "acf", "psd", "allan") + (("level",) if level else ())
    per_view = {n: float(np.mean([v.error for v in views if v.name == n])) for n in names}
    regions = [rg for v in views for rg in _regions(v)]
    return Comparison(model_name="seed+tone" if with_tone_effect else "seed", model_source=f"model_r{revision}.toml",
                      revision=revision, Ts=TS, t=t, y=y, y_mean=mean, y_sd=sd,
                      truth=truth_x if truth else None, views=views, error=float(np.mean(list(per_view.values()))),
                      error_per_view=per_view, regions=regions, notes=["synthetic data for the viewer tests"])


@pytest.fixture(scope="module")
def two_revisions():
    rng = np.random.default_rng(20240611)
    return [make_comparison(rng, 0, 1, False), make_comparison(rng, 1, 1, True)]


@pytest.fixture(scope="module")
def two_outputs():
    rng = np.random.default_rng(7)
    return [make_comparison(rng, 2, 2, False, truth=False)]


@pytest.fixture(scope="module")
def with_level():
    rng = np.random.default_rng(11)
    return [make_comparison(rng, 0, 2, False, level=True), make_comparison(rng, 1, 2, True, level=True)]


# -- reading an .rrd back ----------------------------------------------------------------------------------
def blueprint_values(bp: dict, name: str) -> list:
    """One component of every view entity of a blueprint store (one value per view)."""
    return [x for k, b in bp.items() if k.startswith("/view/") for row in column(b, name) for x in row]


def column_type(batches: list, name: str) -> pa.DataType:
    return next(b.schema.field(name).type for b in batches if name in b.schema.names)


# -- the .rrd ------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def rrd(tmp_path_factory, two_revisions):
    path = tmp_path_factory.mktemp("rrd") / "check.rrd"
    log_comparisons(two_revisions, str(path))
    return path


def test_rrd_is_complete_with_one_recording_and_a_blueprint(rrd):
    from rerun.chunk import RrdReader

    r = RrdReader(rrd)
    recs, bps = r.recordings(), r.blueprints()
    assert len(recs) == 1 and recs[0].application_id == "noiselab"
    assert len(bps) == 1 and bps[0].application_id == "noiselab"
    # LazyStore needs the footer (manifest): a file without it would not open here
    assert len(r.store()) > 0
    bp = read_chunks(rrd, store=bps[0])
    assert "/viewport" in bp and "/time_panel" in bp
    origins = set(blueprint_values(bp, "ViewBlueprint:space_origin"))
    classes = blueprint_values(bp, "ViewBlueprint:class_identifier")
    for rev in (0, 1):
        for o in ("series", "variance", "psd", "acf", "allan"):
            assert f"/rev{rev}/out0/{o}" in origins
    assert {"/error/chart", "/report"} <= origins
    assert classes.count("TimeSeries") == 4 and classes.count("2D") == 7 and classes.count("TextDocument") == 1
    assert column(bp["/time_panel"], "TimePanelBlueprint:timeline") == [["t"]]


def test_rrd_entity_layout(rrd, two_revisions):
    ents = set(read_chunks(rrd))
    expected = {"/report", "/error/overall", "/error/psd", "/error/chart", "/error/chart/overall",
                "/data/out0/measurement", "/data/out0/truth"}
    for rev in (0, 1):
        b = f"/rev{rev}/out0"
        expected |= {f"/rev{rev}", f"{b}/series/mean",
                     f"{b}/series/band", f"{b}/variance/empirical", f"{b}/variance/predicted", f"{b}/variance/band"}
        for v in ("psd", "acf", "allan"):
            expected |= {f"{b}/{v}", f"{b}/{v}/plot/empirical", f"{b}/{v}/plot/predicted", f"{b}/{v}/plot/band",
                         f"{b}/{v}/plot/contrib/sensor.white", f"{b}/{v}/plot/axes/ticks", f"{b}/{v}/plot/flagged"}
    expected |= {"/rev1/out0/psd/plot/contrib/sensor.tone", "/rev1/out0/psd/plot/previous",
                 "/rev0/out0/psd/plot/regions", "/rev0/out0/variance/flagged"}
    assert expected <= ents, sorted(expected - ents)
    assert "/rev0/out0/psd/plot/previous" not in ents      # nothing before the first revision
    assert not any(e.startswith("/rev1/data") for e in ents)  # same recording: the data are logged once


def test_rrd_time_series_has_n_rows_on_the_t_timeline(rrd, two_revisions):
    ch = read_chunks(rrd)
    c = two_revisions[1]
    meas = ch["/data/out0/measurement"]
    assert sum(b.num_rows for b in meas if "t" in b.schema.names) == N
    assert column_type(meas, "t") == pa.duration("ns")
    t_ns = np.concatenate([b.column("t").cast(pa.int64()).to_numpy() for b in meas if "t" in b.schema.names])
    # integer ns rounded from t (rerun's own float-seconds path truncates: 2.05 s -> 2049999999 ns)
    assert np.array_equal(t_ns, np.rint(c.t * 1e9).astype(np.int64))
    # Scalars are float64: exact
    assert column_type(meas, "Scalars:scalars").value_type == pa.float64()
    assert np.array_equal(np.concatenate(column(meas, "Scalars:scalars")), c.y[:, 0])
    band = np.array(column(ch["/rev1/out0/series/band"], "Scalars:scalars"))
    assert band.shape == (N, 2)
    assert np.allclose(band[:, 0], c.y_mean[:, 0] - 2 * c.y_sd[:, 0], rtol=0, atol=1e-15)
    assert np.allclose(band[:, 1], c.y_mean[:, 0] + 2 * c.y_sd[:, 0], rtol=0, atol=1e-15)
    assert sum(b.num_rows for b in ch["/rev1/out0/series/mean"] if "t" in b.schema.names) == N
    assert np.array_equal(np.concatenate(column(ch["/rev1/out0/series/mean"], "Scalars:scalars")), c.y_mean[:, 0])
    truth = np.concatenate(column(ch["/data/out0/truth"], "Scalars:scalars"))
    assert np.array_equal(truth, c.truth[:, 0])


def test_rrd_psd_values_equal_the_comparison(rrd, two_revisions):
    ch = read_chunks(rrd)
    for c in two_revisions:
        v = c.view("psd", 0)
        emp = ch[f"/rev{c.revision}/out0/psd/plot/empirical"]
        # raw values (AnyValues, float64): exactly the Comparison's
        assert np.array_equal(column(emp, "y")[0], v.empirical)
        assert np.array_equal(column(emp, "x")[0], v.x)
        for eid, arr in v.contributions.items():
            assert np.array_equal(column(ch[f"/rev{c.revision}/out0/psd/plot/contrib/{eid}"], "y")[0], arr)
        # the plotted geometry is float32 (Position2D): invert the logged axis mapping
        # row -> list of strips -> list of points -> fixed_size_list<float32>[2]
        pt = column_type(emp, "LineStrips2D:strips").value_type.value_type
        assert pa.types.is_fixed_size_list(pt) and pt.list_size == 2 and pt.value_type == pa.float32()
        m = {k: column(ch[f"/rev{c.revision}/out0/psd"], k)[0][0]
             for k in ("x_log", "x_lo", "x_hi", "y_log", "y_lo", "y_hi", "box_w", "box_h")}
        assert m["x_log"] and m["y_log"]
        pts = np.concatenate([np.asarray(s, float) for s in column(emp, "LineStrips2D:strips")[0]])
        f = 10 ** (m["x_lo"] + pts[:, 0] / m["box_w"] * (m["x_hi"] - m["x_lo"]))
        p = 10 ** (m["y_lo"] + (1 - pts[:, 1] / m["box_h"]) * (m["y_hi"] - m["y_lo"]))
        assert pts.shape[0] == v.x.size           # every PSD point is drawn (all positive, in range)
        np.testing.assert_allclose(f, v.x, rtol=2e-5)
        np.testing.assert_allclose(p, v.empirical, rtol=2e-5)


def test_rrd_flags_and_regions(rrd, two_revisions):
    ch = read_chunks(rrd)
    v0 = two_revisions[0].view("psd", 0)
    assert v0.flagged.any()
    fl = ch["/rev0/out0/psd/plot/flagged"]
    assert len(column(fl, "Points2D:positions")[0]) == int(v0.flagged.sum())
    assert np.array_equal(column(fl, "x")[0], v0.x[v0.flagged])
    regs = [rg for rg in two_revisions[0].regions if rg.view == "psd"]
    assert len(column(ch["/rev0/out0/psd/plot/regions"], "LineStrips2D:strips")[0]) == len(regs)
    vv = two_revisions[0].view("variance", 0)
    assert vv.flagged.any()
    assert sum(len(r) for r in column(ch["/rev0/out0/variance/flagged"], "Scalars:scalars")) == vv.flagged.sum()


def test_rrd_model_error_per_revision(rrd, two_revisions):
    ch = read_chunks(rrd)
    ov = ch["/error/overall"]
    assert column(ov, "revision") == [0, 1]
    assert np.array_equal(np.concatenate(column(ov, "Scalars:scalars")), [c.error for c in two_revisions])
    for n in ("variance", "acf", "psd", "allan"):
        vals = np.concatenate(column(ch[f"/error/{n}"], "Scalars:scalars"))
        assert np.array_equal(vals, [c.error_per_view[n] for c in two_revisions])
    assert two_revisions[0].error > two_revisions[1].error
    text = column(ch["/report"], "TextDocument:text")[0][0]
    assert "model error" in text.lower()
    for rg in two_revisions[0].regions:
        assert rg.describe("Hz" if rg.view == "psd" else "s") in text
    assert column(ch["/report"], "TextDocument:media_type")[0][0] == "text/markdown"


def test_rrd_two_outputs(tmp_path, two_outputs):
    path = tmp_path / "sub" / "p2.rrd"
    log_comparisons(two_outputs, str(path), app_id="noiselab-test")
    from rerun.chunk import RrdReader

    assert RrdReader(path).recordings()[0].application_id == "noiselab-test"
    ch = read_chunks(path)
    c = two_outputs[0]
    for i in (0, 1):
        assert sum(b.num_rows for b in ch[f"/data/out{i}/measurement"] if "t" in b.schema.names) == N
        assert np.array_equal(column(ch[f"/rev2/out{i}/psd/plot/empirical"], "y")[0], c.view("psd", i).empirical)
    assert not any(k.endswith("/truth") for k in ch)      # no truth: real data
    bp = read_chunks(path, store=RrdReader(path).blueprints()[0])
    origins = set(blueprint_values(bp, "ViewBlueprint:space_origin"))
    assert {"/rev2/out1/psd", "/rev2/out1/allan", "/rev2/out1/series"} <= origins


def test_rrd_revision_on_other_data_gets_its_own_data(tmp_path, two_revisions):
    import dataclasses

    other = dataclasses.replace(two_revisions[1], y=two_revisions[1].y + 1.0)
    path = tmp_path / "other.rrd"
    log_comparisons([two_revisions[0], other], str(path))
    ch = read_chunks(path)
    assert np.array_equal(np.concatenate(column(ch["/data/out0/measurement"], "Scalars:scalars")),
                          two_revisions[0].y[:, 0])
    assert np.array_equal(np.concatenate(column(ch["/rev1/out0/data/measurement"], "Scalars:scalars")), other.y[:, 0])
    from rerun.chunk import RrdReader

    bp = read_chunks(path, store=RrdReader(path).blueprints()[0])
    queries = [q for k, b in bp.items() if k.endswith("/ViewContents") for row in column(b, "ViewContents:query")
               for q in row]
    assert "+ /rev1/out0/data/**" in queries and "+ /data/out0/**" in queries


def test_bad_input_is_named(tmp_path, two_revisions):
    with pytest.raises(ViewerInputError, match="empty"):
        log_comparisons([], str(tmp_path / "x.rrd"))
    c = two_revisions[0]
    bad = Comparison(**{**c.__dict__, "y_sd": c.y_sd[:-1]})
    with pytest.raises(ViewerInputError, match="y_sd"):
        log_comparisons([bad], str(tmp_path / "x.rrd"))
    with pytest.raises(ViewerInputError, match="distinct"):
        write_summary_png([c, c], str(tmp_path / "x.png"))
    assert not (tmp_path / "x.rrd").exists() and not (tmp_path / "x.png").exists()


def test_report_lists_errors_and_regions(two_revisions):
    text = report_markdown(two_revisions)
    assert "| 0 | seed |" in text and "| 1 | seed+tone |" in text
    assert "nowhere" in text or not two_revisions[1].regions


# -- the PNG ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["two_revisions", "two_outputs", "with_level"])
def test_summary_png(tmp_path, request, which):
    import matplotlib.image as mpimg

    comps = request.getfixturevalue(which)
    path = tmp_path / "summary.png"
    write_summary_png(comps, str(path))
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(str(path))
    w, h = figure_size_px(np.asarray(comps[0].y).shape[1])
    assert img.shape[:2] == (h, w)
    assert img.shape[2] in (3, 4)
    assert float(np.std(img[..., :3])) > 0.05         # not a blank canvas


def test_summary_png_has_a_level_panel_per_output_when_the_record_is_from_rest(with_level, two_outputs):
    """A record from rest has the level view: one panel per output, between the measurement and
    the variance, with the previous revision's model line; without it the layout is unchanged."""
    from noiselab.viewers.summary_png import summary_figure

    axes = summary_figure(with_level).axes
    titles = [ax.get_title() for ax in axes]
    assert sum(t.startswith("level") for t in titles) == 2
    for j in range(2):      # measurement | level | variance, left to right, in one row
        x0 = {name: ax.get_position().x0 for ax in axes for name in ("level", "variance")
              if ax.get_title().startswith(f"{name}") and f"out{j}:" in ax.get_title()}
        meas = [ax for ax in axes if ax.get_title(loc="left") == f"out{j} [units]"]
        assert len(meas) == 1 and meas[0].get_position().x1 < x0["level"] < x0["variance"]
        level = next(ax for ax in axes if ax.get_title().startswith(f"level (window mean of y - E[y]) out{j}"))
        assert len(level.get_lines()) >= 3      # data, model, previous revision's model
    titles = [ax.get_title() for ax in summary_figure(two_outputs).axes]
    assert not any(t.startswith("level") for t in titles)
    assert sum(t.startswith("variance") for t in titles) == 2


# -- output names and units, the recording, what each revision changed --------------------------------------
IMU_NAMES, IMU_UNITS = ("gyro_x", "accel_z"), ("rad/s", "m/s^2")
RECORDING = "imu_bag.mcap [/imu:angular_velocity.x,linear_acceleration.z]"


def described(c: Comparison, effects: dict, names=IMU_NAMES, units=IMU_UNITS, recording=RECORDING,
              model_name="imu", model_source="scenario imu-nominal") -> Comparison:
    """``c`` as the analysis gives it for a model with an [outputs] table, on a named recording:
    the attributes the viewers read beside the Comparison's fields."""
    import dataclasses

    c = dataclasses.replace(c, model_name=model_name, model_source=model_source)
    c.output_names, c.output_units, c.recording, c.model_effects = names, units, recording, effects
    return c


NOMINAL = {"actuator.white": {"std": 0.05}, "sensor.white": {"std": 0.002}}
STEP1 = {"actuator.ar1": {"std": 0.08649, "tau_s": 0.2615}, "sensor.white": {"std": 0.002}}
FITTED = {"actuator.ar1": {"std": 0.0862, "tau_s": 0.2615}, "sensor.white": {"std": 0.002},
          "sensor.bias_walk": {"std": 0.001559}}


@pytest.fixture(scope="module")
def diagnosis():
    """A diagnosis of a 2-output recording without truth: the nominal model, one step, the fitted
    model (named as diagnose names them: by the device's name, "+ <effect>", "fitted (2 added)")."""
    rng = np.random.default_rng(5)
    out = []
    for rev, (effects, name) in enumerate([(NOMINAL, "imu"), (STEP1, "+ actuator.ar1"),
                                           (FITTED, "fitted (2 added)")]):
        c = make_comparison(rng, rev, 2, rev > 0, truth=False)
        out.append(described(c, effects, model_name=name))
    return out


def figure_texts(fig) -> list:
    """Every text the figure shows: titles, axis labels, legend entries, free text."""
    out = [fig._suptitle.get_text()] if fig._suptitle is not None else []
    for ax in fig.axes:
        out += [ax.get_title(loc=loc) for loc in ("left", "center", "right")]
        out += [ax.get_xlabel(), ax.get_ylabel()] + [t.get_text() for t in ax.texts]
        if ax.get_legend() is not None:
            out += [t.get_text() for t in ax.get_legend().get_texts()]
    return [t.replace("\u00a0", " ") for t in out if t]


def test_with_unit_replaces_the_units_placeholder():
    from noiselab.viewers.comparisons import with_unit

    assert with_unit("PSD [units^2/Hz]", "rad/s") == "PSD [(rad/s)^2/Hz]"
    assert with_unit("PSD [units^2/Hz]", "m") == "PSD [m^2/Hz]"
    assert with_unit("Allan deviation [units]", "m/s^2") == "Allan deviation [m/s^2]"
    assert with_unit("mean of y - E[y] in the window [units]", "rad/s") == "mean of y - E[y] in the window [rad/s]"
    assert with_unit("frequency [Hz]", "rad/s") == "frequency [Hz]"


def test_rrd_entity_paths_and_views_use_the_output_names(tmp_path, diagnosis):
    from rerun.chunk import RrdReader

    path = tmp_path / "named.rrd"
    log_comparisons(diagnosis, str(path))
    ch = read_chunks(path)
    ents = set(ch)
    assert not any("/out0" in e or "/out1" in e for e in ents), sorted(e for e in ents if "/out" in e)[:5]
    for name in IMU_NAMES:
        assert f"/data/{name}/measurement" in ents
        for rev in (0, 1, 2):
            assert {f"/rev{rev}/{name}/series/mean", f"/rev{rev}/{name}/variance/empirical",
                    f"/rev{rev}/{name}/psd/plot/empirical", f"/rev{rev}/{name}/allan"} <= ents
    # the numbers under a name are that output's
    c = diagnosis[-1]
    assert np.array_equal(np.concatenate(column(ch["/data/accel_z/measurement"], "Scalars:scalars")), c.y[:, 1])
    assert np.array_equal(column(ch["/rev2/accel_z/psd/plot/empirical"], "y")[0], c.view("psd", 1).empirical)
    # axes in the output's unit: the PSD of a rate in (rad/s)^2/Hz
    assert column(ch["/rev2/gyro_x/psd"], "y_label")[0] == ["PSD [(rad/s)^2/Hz]"]
    titles = column(ch["/rev2/accel_z/allan/plot/axes/titles"], "Points2D:labels")[0]
    assert "Allan deviation [m/s^2] (log)" in titles
    assert not any("units" in lab for lab in titles)
    # the source: a recording property, and the report
    src = ch["/__properties/source"]
    assert column(src, "recording")[0] == [RECORDING]
    assert column(src, "output_names")[0] == list(IMU_NAMES) and column(src, "output_units")[0] == list(IMU_UNITS)
    assert column(src, "model")[0] == ["scenario imu-nominal"]
    report = column(ch["/report"], "TextDocument:text")[0][0]
    assert RECORDING in report and "gyro_x [rad/s], accel_z [m/s^2]" in report
    assert "+ sensor.bias_walk (std = 0.001559)" in report and "- actuator.white" in report
    # the blueprint's views are named by the output, name [unit]
    bp = read_chunks(path, store=RrdReader(path).blueprints()[0])
    names = blueprint_values(bp, "ViewBlueprint:display_name")
    assert any(n.startswith("gyro_x [rad/s]: measured, predicted mean") for n in names), names
    assert any(n.startswith("PSD accel_z [m/s^2]") for n in names), names
    assert not any("truth" in n for n in names)         # the recording has none
    assert not any("y[" in n for n in names)


def test_rrd_without_names_keeps_a_valid_layout(rrd):
    ents = set(read_chunks(rrd))
    assert "/data/out0/measurement" in ents and "/rev1/out0/psd/plot/empirical" in ents


def test_output_names_are_checked(tmp_path, diagnosis):
    bad = described(diagnosis[0], NOMINAL, names=("gyro_x",))
    with pytest.raises(ViewerInputError, match="output_names"):
        log_comparisons([bad], str(tmp_path / "x.rrd"))
    bad = described(diagnosis[0], NOMINAL, names=("gyro_x", "gyro_x"))
    with pytest.raises(ViewerInputError, match="distinct"):
        write_summary_png([bad], str(tmp_path / "x.png"))
    bad = described(diagnosis[0], NOMINAL, units=("rad/s",))
    with pytest.raises(ViewerInputError, match="output_units"):
        write_summary_png([bad], str(tmp_path / "x.png"))
    assert not (tmp_path / "x.rrd").exists() and not (tmp_path / "x.png").exists()


def test_png_names_the_outputs_units_recording_compared_model_and_every_added_effect(diagnosis):
    from noiselab.viewers.summary_png import summary_figure

    fig = summary_figure(diagnosis)
    texts = figure_texts(fig)
    joined = "\n".join(texts)
    title = texts[0]
    # what was compared with what: the recording and the model the user gave, not the device's name
    assert RECORDING in title and "scenario imu-nominal" in title
    # every effect the diagnosis added, with its fitted values, and the one it replaced
    for phrase in ("+ actuator.ar1 (std = 0.0862, tau_s = 0.2615)", "+ sensor.bias_walk (std = 0.001559)",
                   "- actuator.white"):
        assert phrase in " ".join(title.split()), title
    # the report panel: each step with its values
    report = next(t for ax in fig.axes for t in (x.get_text() for x in ax.texts) if "revision" in t)
    assert "1: + actuator.ar1 (std = 0.08649, tau_s = 0.2615); - actuator.white" in report
    assert "2: actuator.ar1: std 0.08649 -> 0.0862; + sensor.bias_walk (std = 0.001559)" in report
    # outputs by name and unit, axes in the output's unit; no index labels, no placeholder unit
    ylabels = [" ".join(ax.get_ylabel().split()) for ax in fig.axes]
    assert "gyro_x [rad/s]" in ylabels and "accel_z [m/s^2]" in ylabels
    assert "PSD [(rad/s)^2/Hz]" in ylabels and "Allan deviation [m/s^2]" in ylabels
    assert "y[" not in joined.replace("E[y]", "") and "units" not in joined
    assert "x[" not in joined                         # no truth drawn: none recorded


def test_png_says_truth_only_when_the_recording_has_it(two_revisions, two_outputs):
    from noiselab.viewers.summary_png import summary_figure

    without = figure_texts(summary_figure(two_outputs))
    assert not any("truth" in t for t in without), [t for t in without if "truth" in t]
    with_truth = figure_texts(summary_figure(two_revisions))
    assert "truth: state x[0]" in with_truth


def test_png_notes_are_wrapped_not_cut(diagnosis):
    import dataclasses

    from noiselab.viewers.summary_png import summary_figure

    note = ("the record does not start at rest: analysis starts at t = 2.31 s, the command's mean response from "
            "the mean state fitted there (2 states, least squares), and the command is assumed to be the model's own")
    c = dataclasses.replace(diagnosis[0], notes=[note])
    c.output_names, c.output_units = IMU_NAMES, IMU_UNITS
    report = next(t for ax in summary_figure([c]).axes for t in (x.get_text() for x in ax.texts) if "notes:" in t)
    assert " ".join(note.split()) in " ".join(report.split("notes:")[1].split())
    assert "..." not in report


@pytest.mark.parametrize("which", ["with_level", "diagnosis"])
def test_png_panels_do_not_overlap(request, which):
    """Each panel with its title, tick and axis labels (its tight box) stays clear of every other
    panel's: a long axis label does not run into the neighbouring panel."""
    from noiselab.viewers.summary_png import summary_figure

    comps = request.getfixturevalue(which)
    fig = summary_figure(comps)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    boxes = [(ax, ax.get_tightbbox(r)) for ax in fig.axes if ax.axison]
    for k, (a, ba) in enumerate(boxes):
        for b, bb in boxes[k + 1:]:
            dx = min(ba.x1, bb.x1) - max(ba.x0, bb.x0)
            dy = min(ba.y1, bb.y1) - max(ba.y0, bb.y0)
            assert dx <= 1 or dy <= 1, (a.get_title(), a.get_ylabel(), b.get_title(), b.get_ylabel(), dx, dy)
    # and everything is on the canvas
    w, h = fig.canvas.get_width_height()
    for ax, bb in boxes:
        assert bb.x0 >= -1 and bb.y0 >= -1 and bb.x1 <= w + 1 and bb.y1 <= h + 1, (ax.get_title(), bb)
