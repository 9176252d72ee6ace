"""What the two device traces share (tflite_trace.py: an INT8 `.tflite`'s codes; pte_trace.py:
a `.pte`'s instruction outputs): a recorded trace read back and checked before it is compared,
and the `record | compare` command line each runs on the host and on the device."""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence


@dataclass(frozen=True)
class TraceKind:
    """How one kind of trace names what it digests: `items` is the record's list of digested
    values (each a dict holding `key`), `what` its phrase in messages ("code tensors")."""
    name: str           # the module, as messages and the command line say it
    items: str          # the record's field listing the digested values
    key: str            # a field every item holds
    what: str           # the items, in plural, in messages
    described: str      # "a list of <described>"

    @property
    def fields(self) -> tuple[str, ...]:
        return ("model", "steps", self.items, "digests", "isa")


def digest(data: bytes) -> str:
    """The 8-byte digest a record keeps of one value at one step (the host's file stays small,
    the device needs no host arrays)."""
    return hashlib.blake2b(data, digest_size=8).hexdigest()


def read_record(path: str | os.PathLike, kind: TraceKind) -> dict[str, Any]:
    """A record written by `kind`'s `record`, checked for what `compare` reads: a DataError
    naming the file and what is wrong, not a KeyError or an IndexError from inside the
    comparison."""
    from e3dpsm.errors import DataError

    try:
        trace = json.loads(Path(path).read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DataError(f"{path}: not a JSON trace ({exc})") from exc
    if not isinstance(trace, dict) or any(field not in trace for field in kind.fields):
        raise DataError(f"{path}: not a {kind.name} record (it needs {', '.join(kind.fields)})")
    steps, items, digests = trace["steps"], trace[kind.items], trace["digests"]
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise DataError(f"{path}: a trace of {steps!r} steps compares nothing")
    if not isinstance(items, list) or not all(isinstance(item, dict) and kind.key in item for item in items):
        raise DataError(f"{path}: its {kind.items} are not a list of {kind.described}")
    if (not isinstance(digests, list) or len(digests) != steps
            or not all(isinstance(row, list) and len(row) == len(items) for row in digests)):
        raise DataError(f"{path}: its digests are not {steps} steps of {len(items)} {kind.what} each")
    return trace


def trace_main(argv: Sequence[str] | None, kind: TraceKind, doc: str | None, *, record: Callable[..., dict],
               compare: Callable[[dict, dict], dict], summary: Callable[[dict], str], record_help: str,
               compare_help: str, exit_codes: Mapping[type, int] | None = None) -> int:
    """`python -m e3dpsm.golden.<kind> record MODEL GOLDEN OUT | compare HOST DEVICE`: one
    error line and exit 2 on bad input (or the code `exit_codes` gives an error type)."""
    from e3dpsm.errors import E3DPSMError
    from e3dpsm.utils.io import write_json_atomic

    parser = argparse.ArgumentParser(prog=f"python -m e3dpsm.golden.{kind.name}", description=doc,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    rec = sub.add_parser("record", help=record_help)
    rec.add_argument("model")
    rec.add_argument("golden")
    rec.add_argument("out")
    rec.add_argument("--steps", type=int)
    rec.add_argument("--threads", type=int, default=1)
    cmp_ = sub.add_parser("compare", help=compare_help)
    cmp_.add_argument("host")
    cmp_.add_argument("device")
    cmp_.add_argument("--out", help="write the comparison as JSON")
    args = parser.parse_args(argv)
    codes = dict(exit_codes or {})
    try:
        if args.command == "record":
            write_json_atomic(args.out, record(args.model, args.golden, args.steps, args.threads))
            return 0
        report = compare(read_record(args.host, kind), read_record(args.device, kind))
    except (E3DPSMError, OSError, ValueError, KeyError, *codes) as exc:
        print(f"{kind.name}: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return next((code for error, code in codes.items() if isinstance(exc, error)), 2)
    if args.out:
        write_json_atomic(args.out, report)
    print(summary(report))
    return 0


def first_steps_apart(host: dict[str, Any], device: dict[str, Any], kind: TraceKind,
                      position: bool = False) -> dict[str, Any]:
    """Each item's first step apart between the two records (None: the same at every step both
    ran) and the items that part first; `position` adds each item's place in the record."""
    steps = min(host["steps"], device["steps"])
    per_item = []
    for k, item in enumerate(host[kind.items]):
        first = next((s for s in range(steps) if host["digests"][s][k] != device["digests"][s][k]), None)
        per_item.append({**item, **({"position": k} if position else {}), "first_step": first})
    apart = [item for item in per_item if item["first_step"] is not None]
    first_step = min((item["first_step"] for item in apart), default=None)
    return {"steps": steps, "items": per_item, "apart_by_end": len(apart), "first_step": first_step,
            "first_departures": [item for item in apart if item["first_step"] == first_step]}


def departure_line(report: Mapping[str, Any], count: int, items: str, order: str, describe: Callable[[dict], str],
                   more: str) -> str:
    """The one line each trace prints: `<items> part first at step S, first <order> <the first
    departure>[, then N more <more>]; A of <count> <items> apart by step E`, or that none part."""
    if report["first_step"] is None:
        return f"all {count} {items} the same at every one of {report['steps']} steps"
    first = report["first_departures"]
    return (f"{items} part first at step {report['first_step']}, first {order} {describe(first[0])}"
            + (f", then {len(first) - 1} more {more}" if len(first) > 1 else "")
            + f"; {report['apart_by_end']} of {count} {items} apart by step {report['steps'] - 1}")
