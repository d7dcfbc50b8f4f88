"""An ``.rrd`` file read back: its chunks as pyarrow record batches per entity path."""

from __future__ import annotations


def read_chunks(path, store=None) -> dict:
    """{entity path: [pyarrow.RecordBatch, ...]} of one store (default: the first recording)."""
    from rerun.chunk import RrdReader

    out: dict = {}
    for chunk in RrdReader(path).stream(store=store):
        out.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    return out


def column(batches: list, name: str) -> list:
    """Rows of one column across an entity's chunks (batches that lack it are skipped)."""
    rows = []
    for b in batches:
        if name in b.schema.names:
            rows.extend(b.column(name).to_pylist())
    return rows
