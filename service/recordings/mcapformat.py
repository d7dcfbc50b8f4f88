"""The MCAP format as noiselab writes and reads it (https://mcap.dev/spec): the magic, the width
of a message's sequence, the chunk compressions the installed packages give, the bound on a
chunk's size, what a damaged record raises from inside the mcap reader, and a topic's spelling."""

from __future__ import annotations

import struct

from mcap.exceptions import McapError
from mcap.writer import CompressionType

try:  # mcap depends on both; tolerate a stripped-down install all the same
    import zstandard as zstd
except ImportError:  # pragma: no cover
    zstd = None
try:
    import lz4.frame as lz4frame
except ImportError:  # pragma: no cover
    lz4frame = None

MAGIC = b"\x89MCAP0\r\n"
"""The 8 bytes that open and close every MCAP file."""

SEQUENCE_MODULUS = 2**32
"""MCAP message ``sequence`` is a uint32: the writer stores ``seq % SEQUENCE_MODULUS``."""

AVAILABLE = {"zstd": zstd is not None, "lz4": lz4frame is not None, "none": True}
COMPRESSIONS: tuple[str, ...] = tuple(c for c, ok in AVAILABLE.items() if ok)
"""Chunk compressions usable with the installed packages."""

DEFAULT_COMPRESSION: str = COMPRESSIONS[0]
"""``"zstd"`` when zstandard is installed, else ``"lz4"``, else ``"none"``."""

COMPRESSION_TYPES = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
                      "none": CompressionType.NONE}

# What a truncated or damaged record can raise from inside the mcap reader: short reads
# (EndOfFile is an McapError), struct unpacking of short buffers, CRC mismatch (ValueError),
# bad UTF-8, zstd/lz4 decompression failures, absurd lengths, ids or offsets that point
# nowhere (found by flipping single bits of real files).
CORRUPTION_ERRORS: tuple[type[BaseException], ...] = (
    McapError, struct.error, ValueError, EOFError, RuntimeError, MemoryError, OverflowError,
    KeyError, IndexError,
) + ((zstd.ZstdError,) if zstd is not None else ())


CHUNK_MAX = 1 << 30
"""Bytes a chunk may decompress to (its header's uncompressed size is trusted up to this): chunks
are kilobytes to megabytes; a damaged size must not make the reader allocate it."""


def norm_topic(topic: str) -> str:
    """A topic as noiselab compares it: without a leading ``/``."""
    return topic.lstrip("/")
