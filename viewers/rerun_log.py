"""Comparisons (``noiselab.diagnose.results``) -> one Rerun ``.rrd`` file whose blueprint tells the
story on one screen: the data against the model, where they part, and the model error falling
across revisions.

Every Rerun call of the viewers (here, :mod:`noiselab.viewers.plot2d`, :mod:`noiselab.viewers.layout`) was checked
against the installed rerun-sdk **0.41.0** (package source in ``site-packages/rerun``):
``rr.RecordingStream(app_id, recording_id=...)``, ``.binary_stream()`` (the .rrd encoded in
memory; ``BinaryStream.read(flush=True)`` gives it, footer included),
``.send_blueprint(bp, make_active=False, make_default=True)`` (what ``.save(path,
default_blueprint=bp)`` sends), ``.send_columns(path, indexes=[rr.TimeColumn(name, duration=timedelta64[ns]
| sequence=ints)], columns=rr.Scalars.columns(scalars=...))`` (a (N, 2) array gives two scalars per
row; float seconds are *truncated* to ns by TimeColumn, so times are rounded here first),
``rr.Scalars`` / ``rr.SeriesLines`` / ``rr.SeriesPoints`` (the plural archetypes; ``rr.Scalar`` and
``rr.SeriesLine`` are gone),
``rr.LineStrips2D``, ``rr.Points2D``, ``rr.AnyValues``, ``rr.TextDocument(..., media_type=
rr.MediaType.MARKDOWN)``, ``rerun.blueprint`` (``Blueprint``, ``Horizontal``, ``Vertical``, ``Tabs``,
``TimeSeriesView``, ``Spatial2DView``, ``TextDocumentView``, ``TimeAxis``, ``VisualBounds2D``,
``TimePanel``), and ``.flush()`` + ``.disconnect()``. The bytes are written to the file by
Python, not by Rerun's file sink: a sink whose file fails (a full disk) hangs ``save``, raises a
RuntimeError without the OS's reason from ``flush``, logs its errors on stderr and warns at exit
of the data it dropped; an OSError from Python names the reason and leaves nothing behind.
``rerun.chunk.RrdReader(path).store()`` opens the file (it needs the footer, the manifest).

Entity layout (r = ``Comparison.revision``, o = output name, v = view name, e = effect id)
-----------------------------------------------------------------------------------------
Output names are the model's ``[outputs]`` names (identifiers, so valid path parts as they
stand; :func:`output_names`), units its units: axis labels read ``name [unit]`` and the views'
``units`` placeholder becomes the output's unit (:func:`with_unit`).

recording property ``source``       AnyValues ``recording`` (path, topic and field the data came
                                    from), ``model``, ``output_names``, ``output_units``
                                    (``/__properties/source`` when read back); the recording's name
                                    says "<recording> against <model>".
``/report``                         TextDocument (markdown): the recording, the outputs, model error
                                    per revision, what each revision changed (effects added with
                                    their fitted values, removed, refitted), the regions'
                                    ``describe()`` lines, notes. Static.
``/error/overall``, ``/error/<v>``  Scalars on the sequence timeline ``revision``: one row per
                                    revision (the model error and the per-view errors).
``/error/chart/...``                the same numbers as a 2D chart (log10 error vs revision, see below).
``/data/<o>/{measurement,truth}``   the data, once (the revisions compare models with the same
                                    recording; a comparison whose t, y or truth differ from the
                                    first one's gets its own ``/rev<r>/<o>/data``): Scalars on the
                                    duration timeline ``t`` (sample time, integer ns), sent with
                                    ``send_columns`` (one chunk per series, N rows). ``truth`` beside
                                    output i is state x[i] (the shorthand plant measures y = x[0]),
                                    logged when truth is present and i < n.
``/rev<r>``                         AnyValues: model name and source, error, the recording, the
                                    output names and units, ``changes`` from the previous revision.
``/rev<r>/<o>/series/{mean,band}``
                                    the model's predicted mean and the band mean -+ 2 sd (two
                                    scalars per row), on ``t`` likewise.
``/rev<r>/<o>/variance/{empirical,predicted,band,flagged,contrib/<e>}``
                                    Scalars on ``t`` (x = window centre time), ``flagged`` only at
                                    the flagged windows (red markers). Parent: raw View (AnyValues).
``/rev<r>/<o>/{acf,psd,allan}``  AnyValues: the View's raw arrays (x, z, flagged, error, ...) and
                                    the plot's axis mapping.
``/rev<r>/<o>/{acf,psd,allan}/plot/...``
                                    the 2D plot: ``empirical`` (+ ``empirical_points``),
                                    ``predicted``, ``band``, ``contrib/<e>``, ``previous`` (the
                                    previous revision's prediction, grey), ``flagged`` (red points),
                                    ``regions`` (red bars along the bottom, one per Region),
                                    ``axes/{frame,grid,ticks,titles}``, ``legend/...``. Each data
                                    entity also carries its raw values as AnyValues ``x``, ``y``
                                    (float64, exactly the Comparison's numbers), so a hover or the
                                    selection panel shows them and scripts can read them back.


The 2D plots (:mod:`noiselab.viewers.plot2d`) and the blueprint (:mod:`noiselab.viewers.layout`) say how they are
drawn and laid out.
"""

from __future__ import annotations

import contextlib
import uuid
from pathlib import Path

import numpy as np

from noiselab.diagnose.results import VIEW_NAMES, Comparison, View

from .comparisons import (
    effect_ids,
    flag_mask,
    has_truth,
    model_changes,
    model_title,
    output_label,
    output_names,
    output_units,
    recording_of,
    truth_label,
    validate_comparisons,
    view_y_label,
)
from .layout import build_blueprint, data_paths, output_path, rev_path
from .plot2d import log_error_chart, log_view_2d
from .report import report_markdown
from .style import COLORS, CONTRIB_COLORS, VIEW_COLORS, effect_color

RERUN_VERSION_CHECKED = "0.41.0"


# -- time series (TimeSeriesView on the duration timeline "t") -------------------------------------------
def seconds_to_ns(t) -> np.ndarray:
    """Sample times in s -> integer ns, rounded. (``rr.TimeColumn(duration=float seconds)`` multiplies
    by 1e9 and truncates in 0.41, so 2.05 s would become 2049999999 ns; give it timedelta64[ns].)"""
    return np.rint(np.asarray(t, float) * 1e9).astype(np.int64).astype("timedelta64[ns]")


def _send_series(rec, rr, path: str, t: np.ndarray, values: np.ndarray) -> None:
    rec.send_columns(path, indexes=[rr.TimeColumn("t", duration=seconds_to_ns(t))],
                     columns=rr.Scalars.columns(scalars=np.asarray(values, float)))


def _style(rec, rr, path: str, names: list, rgb: tuple, width: float = 1.5) -> None:
    rec.log(path, rr.SeriesLines(names=names, colors=[rgb] * len(names), widths=[width] * len(names)), static=True)


def _log_data(rec, rr, p: str, c: Comparison, i: int) -> None:
    t = np.asarray(c.t, float)
    _send_series(rec, rr, f"{p}/measurement", t, np.asarray(c.y, float)[:, i])
    _style(rec, rr, f"{p}/measurement", [f"{output_label(c, i)} measured"], COLORS["measurement"], 1.0)
    if has_truth(c, i):
        _send_series(rec, rr, f"{p}/truth", t, np.asarray(c.truth, float)[:, i])
        _style(rec, rr, f"{p}/truth", [truth_label(i)], COLORS["truth"], 1.5)


def _log_time_series(rec, rr, base: str, c: Comparison, i: int) -> None:
    t = np.asarray(c.t, float)
    mean = np.asarray(c.y_mean, float)[:, i]
    sd = np.asarray(c.y_sd, float)[:, i]
    p = f"{base}/series"
    _send_series(rec, rr, f"{p}/mean", t, mean)
    _style(rec, rr, f"{p}/mean", ["predicted mean"], COLORS["mean"], 2.0)
    _send_series(rec, rr, f"{p}/band", t, np.column_stack([mean - 2 * sd, mean + 2 * sd]))
    _style(rec, rr, f"{p}/band", ["mean - 2 sd", "mean + 2 sd"], COLORS["band"], 1.0)


def _log_variance(rec, rr, base: str, v: View, effects: list, y_label: str) -> None:
    p = f"{base}/variance"
    x = np.asarray(v.x, float)
    flagged = flag_mask(v)
    rec.log(p, rr.AnyValues(x_label=v.x_label, y_label=y_label, error=float(v.error), conf=float(v.conf),
                            x=x, z=np.asarray(v.z if v.z is not None else np.full(x.size, np.nan), float),
                            flagged=flagged), static=True)
    _send_series(rec, rr, f"{p}/empirical", x, v.empirical)
    _style(rec, rr, f"{p}/empirical", ["data (window variance)"], COLORS["empirical"], 1.5)
    _send_series(rec, rr, f"{p}/predicted", x, v.predicted)
    _style(rec, rr, f"{p}/predicted", ["model"], COLORS["predicted"], 2.0)
    _send_series(rec, rr, f"{p}/band", x, np.column_stack([np.asarray(v.lo, float), np.asarray(v.hi, float)]))
    _style(rec, rr, f"{p}/band", ["band low", "band high"], COLORS["band"], 1.0)
    for eid, arr in v.contributions.items():
        q = f"{p}/contrib/{rr.escape_entity_path_part(eid)}"
        _send_series(rec, rr, q, x, arr)
        _style(rec, rr, q, [eid], effect_color(effects.index(eid)) if eid in effects else CONTRIB_COLORS[0], 1.0)
    if flagged.any():
        _send_series(rec, rr, f"{p}/flagged", x[flagged], np.asarray(v.empirical, float)[flagged])
        rec.log(f"{p}/flagged", rr.SeriesPoints(names=["outside the band"], colors=[COLORS["flagged"]],
                                                markers=["cross"], marker_sizes=[5.0]), static=True)


# -- entry point ------------------------------------------------------------------------------------------
def log_comparisons(comparisons: list, path: str, *, app_id: str = "noiselab", history: list | None = None) -> None:
    """Write ``comparisons`` (one per model revision) to the Rerun file ``path`` with the blueprint.

    ``history`` (live analysis): [{"t": s, "revision": int, "error": float, "error_per_view": {...}}]
    is logged as the model error over time on the ``t`` timeline under ``/error/history``.

    The file is complete (footer included) when this returns. Parent directories are created.
    Rerun is put in strict mode for these calls (thread-local), so a bad argument raises instead
    of becoming a warning and a silently empty entity. A file that cannot be written (disk full,
    ...) raises the OSError, and a regular file cut short by it is removed.
    """
    import rerun as rr
    from rerun.error_utils import catch_and_log_exceptions   # thread-local strict mode (0.41 source)

    comps = validate_comparisons(comparisons)
    effects = effect_ids(comps)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    rec = rr.RecordingStream(app_id, recording_id=uuid.uuid4())
    stream = rec.binary_stream()        # in memory; written to the file below (module docstring)
    try:
        with catch_and_log_exceptions("noiselab.viewers.log_comparisons", strict=True):
            rec.send_blueprint(build_blueprint(comps, history=bool(history)), make_active=False, make_default=True)
            if history:
                _log_history(rec, rr, history)
            _log_header(rec, rr, comps)
            _log_errors(rec, rr, comps)
            _log_revisions(rec, rr, comps, effects)
            rec.flush()
        data = stream.read(flush=True)
    finally:
        rec.disconnect()
        stream.read(flush=True)          # whatever an error left in the stream: nothing is dropped with a warning
    _write_file(out, data)


def _log_history(rec, rr, history: list) -> None:
    """The live analysis's model error over time (``/error/history/...`` on the ``t`` timeline)."""
    th = seconds_to_ns(np.array([h["t"] for h in history], float))
    rec.send_columns("/error/history/overall", indexes=[rr.TimeColumn("t", duration=th)],
                     columns=rr.Scalars.columns(scalars=np.array([h["error"] for h in history], float)))
    rec.send_columns("/error/history/revision", indexes=[rr.TimeColumn("t", duration=th)],
                     columns=rr.Scalars.columns(scalars=np.array([h["revision"] for h in history], float)))
    for n in VIEW_NAMES:
        vals = np.array([h["error_per_view"].get(n, np.nan) for h in history], float)
        rec.send_columns(f"/error/history/{n}", indexes=[rr.TimeColumn("t", duration=th)],
                         columns=rr.Scalars.columns(scalars=vals))


def _log_header(rec, rr, comps: list) -> None:
    """The recording's name and ``source`` property, and the ``/report`` text."""
    src = recording_of(comps[-1])
    rec.send_recording_name((f"{src} against " if src else "") + f"{model_title(comps[0])}: "
                            f"{len(comps)} revision(s)")
    # where the data came from and what they are, for scripts and the viewer's recording panel
    rec.send_property("source", rr.AnyValues(
        recording=src or "", model=model_title(comps[0]), output_names=list(output_names(comps[-1])),
        output_units=list(output_units(comps[-1]))))
    rec.log("/report", rr.TextDocument(report_markdown(comps), media_type=rr.MediaType.MARKDOWN),
            static=True)


def _log_errors(rec, rr, comps: list) -> None:
    """The model error per revision, overall and per view (``/error/...`` on the ``revision``
    timeline), and as the 2D chart."""
    revs = np.array([c.revision for c in comps], np.int64)
    rec.send_columns("/error/overall", indexes=[rr.TimeColumn("revision", sequence=revs)],
                     columns=rr.Scalars.columns(scalars=np.array([c.error for c in comps], float)))
    _style(rec, rr, "/error/overall", ["model error"], COLORS["overall"], 2.5)
    for n in VIEW_NAMES:
        vals = np.array([c.error_per_view.get(n, np.nan) for c in comps], float)
        rec.send_columns(f"/error/{n}", indexes=[rr.TimeColumn("revision", sequence=revs)],
                         columns=rr.Scalars.columns(scalars=vals))
        _style(rec, rr, f"/error/{n}", [f"{n} error"], VIEW_COLORS[n], 1.5)
    log_error_chart(rec, rr, comps)


def _log_revisions(rec, rr, comps: list, effects: list) -> None:
    """Each revision's entity (``/rev<r>``) and, per output, its data (once for all revisions that
    share them), time series and views; a 2D view also shows the previous revision's prediction."""
    prev = None
    dpaths = data_paths(comps)
    logged_data = set()
    for c in comps:
        rec.log(rev_path(c), rr.AnyValues(revision=int(c.revision), model_name=c.model_name,
                                          model_source=str(c.model_source), Ts=float(c.Ts), error=float(c.error),
                                          n_regions=len(c.regions), recording=recording_of(c) or "",
                                          output_names=list(output_names(c)), output_units=list(output_units(c)),
                                          changes=model_changes(prev, c) if prev is not None else []),
                static=True)
        for i in range(np.asarray(c.y).shape[1]):
            if dpaths[c.revision, i] not in logged_data:
                _log_data(rec, rr, dpaths[c.revision, i], c, i)
                logged_data.add(dpaths[c.revision, i])
            base = output_path(c, i)
            _log_time_series(rec, rr, base, c, i)
            for v in (v for v in c.views if v.output == i):
                if v.name == "variance":
                    _log_variance(rec, rr, base, v, effects, view_y_label(c, v))
                    continue
                pv = None
                if prev is not None:
                    try:
                        pv = prev.view(v.name, i)
                    except KeyError:
                        pv = None
                regs = [rg for rg in c.regions if rg.view == v.name and rg.output == i]
                log_view_2d(rec, rr, f"{base}/{v.name}", v, regs, effects, pv, view_y_label(c, v))
        prev = c


def _write_file(out: Path, data: bytes) -> None:
    """``data`` to ``out``; on an OSError after the file was opened (disk full), a regular file cut
    short is removed (a device such as /dev/full is left alone) and the error raised."""
    f = open(out, "wb")
    try:
        f.write(data)
        f.close()
    except OSError:
        with contextlib.suppress(OSError):
            f.close()                    # closed even when its last flush fails
        if out.is_file():
            out.unlink()
        raise
