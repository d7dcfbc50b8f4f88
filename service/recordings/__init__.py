"""Recordings in and out: noiselab MCAP, foreign JSON MCAP, ROS bags, and the series they become.

Below the analysis, the diagnosis and the nodes: it imports the wire contract
(:mod:`noiselab.wire`), the bounds and the errors, never the analysis, a node or the CLI. The
analysis and the diagnosis take a :class:`~.series.Series`, never a file.

Modules, one concept each:

- :mod:`.mcapformat`: magic, sequence width, compressions, what a damaged record raises;
- :mod:`.errors`: one-line errors of the files (:class:`~.errors.McapIoError` and kinds) and of
  the series (:class:`~.errors.SeriesError`);
- :mod:`.output`: the file a writer fills (``.partial`` beside a file it replaces);
- :mod:`.blockwriter`: an MCAP writer that takes a block of messages per call;
- :mod:`.writer`: :class:`~.writer.RecordingWriter`, noiselab streams into a new recording;
- :mod:`.scan`: messages one by one in file order, of finished and unfinished files;
- :mod:`.merge`: messages merged across channels by publish time (the replay's order);
- :mod:`.chunks`: a finished file's chunks at the struct level (the fast read);
- :mod:`.recording`: what a recording holds once read (devices, streams, stream segments);
- :mod:`.reader`: :func:`~.reader.read_recording`, every device of a recording into arrays;
- :mod:`.salvage`: :func:`~.salvage.recover`, an unfinished file's intact messages into a
  finished one;
- :mod:`.rosbag_in`, :mod:`.rosbag_out`: ROS bags read with rosbags, a simulated run written as
  a rosbag2 bag;
- :mod:`.simulated`: ``noiselab simulate``'s output, MCAP or ROS 2;
- :mod:`.fieldpaths`: ``TOPIC:FIELD`` specs and field paths (``a.b[2].c``, a final ``.*``);
- :mod:`.series`: :class:`~.series.Series` and the checks every series passes (magnitude,
  period, regular timing, the longest gap-free run);
- :mod:`.foreign`: a foreign JSON MCAP's or a ROS bag's fields as a series;
- :mod:`.load`: :func:`~.load.load_recording`, any recording as a series.

MCAP conventions (DESIGN.md, "Wire contract (Zenoh and MCAP)"):

- one channel per stream, topic = the Zenoh key without a leading ``/``
  (``noiselab/<name>/<kind>``), message encoding ``json``, one registered JSON Schema per kind
  (schema encoding ``jsonschema``, names :data:`noiselab.wire.SCHEMA_NAMES`);
- MCAP ``sequence`` = payload ``seq``. MCAP's sequence is a uint32, so past 2**32 - 1 it wraps
  modulo 2**32; the payload ``seq`` stays exact and is the one the reader returns;
- ``publish_time`` = the stream's wall-clock start + the sample's time from it, in integer ns
  (:mod:`noiselab.wire`, "Time"; the start is ``start_time_ns`` in the ``noiselab`` metadata
  record); ``log_time`` = receive time in integer ns. Readers order and pace by publish_time and
  take a sample's time from the payload ``t``; they must not assume that either time is
  wall-clock (a foreign file's need not be). All times stay Python ints / int64, never float64.

Readers accept topics with or without a leading ``/``, find devices by the ``/measurement``
suffix, and treat an absent ``truth`` topic as normal (real data has none).

A writer that is killed (SIGKILL, power loss) leaves a file with no footer and no summary.
:func:`~.reader.read_recording` still reads every message of every chunk that was fully written,
with the non-seeking stream reader, and says so in ``Recording.complete`` / ``Recording.note``;
:func:`~.salvage.recover` rewrites those messages into a finished file.

Where a writer's bytes go (:class:`~.writer.RecordingWriter`): straight to the named file when
nothing is there, so a killed writer's unfinished file has the name the user gave; when ``force``
replaces an existing file, to ``<name>.partial`` beside it, renamed over the old file only once
finished (``RecordingWriter.writing_path`` says which). A failed or interrupted write never spoils
the old file, and what it wrote stays where a ``noiselab recover`` finds it.
"""
