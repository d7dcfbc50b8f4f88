"""``noiselab recover BROKEN -o FIXED``: every intact message of an unfinished MCAP file, salvaged."""

from __future__ import annotations

from ._common import emit


def register(sub) -> None:
    sv = sub.add_parser("recover", help="salvage every intact message of an unfinished MCAP file")
    sv.add_argument("broken", help="the unfinished (or damaged) .mcap")
    sv.add_argument("--out", "-o", required=True, help="the repaired .mcap to write")
    sv.add_argument("--force", action="store_true", help="overwrite an existing output file")
    sv.add_argument("--json", action="store_true", help="machine-readable summary")
    sv.set_defaults(func=cmd_recover)


def cmd_recover(args) -> int:
    from ..recordings.salvage import recover

    st = recover(args.broken, args.out, force=args.force)
    rep = {"node": "recover", "input": args.broken, "output": args.out, "messages": st.messages,
           "total": st.total, "already_complete": st.already_complete, "note": st.note}
    lines = [f"recovered {st.total} messages from {args.broken} into {args.out}"
             + (" (the input was complete)" if st.already_complete else "")]
    lines += [f"  {topic}: {count}" for topic, count in sorted(st.messages.items())]
    if st.note:
        lines.append(f"  {st.note}")
    emit(args, rep, lines)
    return 0
