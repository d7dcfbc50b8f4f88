"""Salvage an unfinished or damaged MCAP file: every intact message into a new, finished file."""

from __future__ import annotations

import itertools
import os
from collections import defaultdict
from dataclasses import dataclass

from mcap.records import Channel, Schema
from mcap.writer import Writer

from .errors import McapIoError
from .mcapformat import AVAILABLE, COMPRESSION_TYPES, COMPRESSIONS, DEFAULT_COMPRESSION
from .output import Output, os_error
from .scan import ScanReport, check_magic, scan


@dataclass(frozen=True)
class RecoverStats:
    """Outcome of :func:`recover`: messages salvaged per topic (as spelled in the file),
    whether the input was already a finished, undamaged file (then nothing was lost), and
    the reader's note (empty in that case)."""

    messages: dict[str, int]
    already_complete: bool
    note: str

    @property
    def total(self) -> int:
        return sum(self.messages.values())


def recover(broken_path: str | os.PathLike, out_path: str | os.PathLike, force: bool = False,
            *, compression: str = DEFAULT_COMPRESSION, chunk_size: int = 1024 * 1024
            ) -> RecoverStats:
    """Rewrite every intact message of ``broken_path`` into a new, finished MCAP file.

    The input is read sequentially (non-seeking stream reader) up to its end or its first
    truncated or damaged record, whether or not it has a footer. The repaired file is the same
    kind of file as the source: its header (profile, library: a rosbag2 file stays ``ros2``,
    which ROS tools check before anything else), schemas (name, encoding, data), channels
    (topic, message encoding, metadata such as rosbag2's QoS profiles; a channel read without
    any message too), metadata records, and per message sequence, log_time and publish_time
    (ns) and data, unchanged, in file order. ``out_path`` must differ from the input and must
    not exist unless ``force`` (an existing one is replaced only once the new file is finished,
    as :class:`RecordingWriter` does). On failure the partial output is removed.

    What is not copied: what the file's end cut off (a rosbag2 writer puts its ``rosbag2``
    metadata record, with the message counts, at the very end), and attachments. A rosbag2
    bag directory's ``metadata.yaml`` describes the whole bag (its file names and message
    counts), not the repaired file, so it is not the repaired file's: ROS 2 readers open a
    single ``.mcap`` file of profile ``ros2`` by itself (``rosbags``' ``Reader`` and
    ``AnyReader``, ``ros2 bag info FILE.mcap``).
    """
    src = os.fspath(broken_path)
    dst = os.fspath(out_path)
    check_magic(src)
    if compression not in COMPRESSION_TYPES or not AVAILABLE[compression]:
        raise McapIoError(f"compression {compression!r} is not available; use one of "
                          f"{', '.join(COMPRESSIONS)}")
    if os.path.exists(dst) and os.path.samefile(src, dst):
        raise McapIoError(f"{dst}: output is the input file; write the recovery elsewhere")
    report = ScanReport()
    counts: dict[str, int] = defaultdict(int)
    target = Output(dst, force, ".recovering")    # not .partial: that may be the input
    try:
        writer = Writer(target.file, chunk_size=chunk_size, compression=COMPRESSION_TYPES[compression])
        messages = scan(src, None, report, stream=True)
        first = next(messages, None)                # the header is read before the first message
        writer.start(profile=report.profile, library=report.library)
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}

        def channel_id(schema: Schema | None, channel: Channel) -> int:
            cid = channel_ids.get(channel.id)
            if cid is None:
                sid = 0
                if schema is not None:
                    sid = schema_ids.get(schema.id, 0)
                    if sid == 0:
                        sid = schema_ids[schema.id] = writer.register_schema(
                            schema.name, schema.encoding, schema.data)
                cid = channel_ids[channel.id] = writer.register_channel(
                    channel.topic, channel.message_encoding, sid, dict(channel.metadata))
            return cid

        if first is not None:
            for schema, channel, msg in itertools.chain([first], messages):
                writer.add_message(channel_id=channel_id(schema, channel), log_time=msg.log_time,
                                   data=msg.data, publish_time=msg.publish_time, sequence=msg.sequence)
                counts[channel.topic] += 1
        for schema, channel in report.channels.values():      # topics without an intact message
            channel_id(schema, channel)
        for name, data in report.metadata.items():
            writer.add_metadata(name, data)
        writer.finish()
        target.commit()
    except OSError as e:            # the output's disk or directory; the input is only read
        target.abandon(keep=False)
        raise os_error(target.writing, e, "cannot write it") from None
    except BaseException:
        target.abandon(keep=False)
        raise
    return RecoverStats(messages=dict(counts),
                        already_complete=bool(report.complete and report.intact),
                        note=report.note)
