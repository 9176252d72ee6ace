"""Damaged inputs for the fuzz tests: files that independent writers produced, mutated by
Hypothesis (byte flips, truncations, insertions, duplicated chunks, corrupted length fields).

A `Seed` is one undamaged file and what is known of its layout: `fields`, the (offset, width)
of its length and offset fields (packet sizes, zip sizes and offsets), which "length"
mutations overwrite with boundary values; `hot`, byte ranges where most positions are drawn
(the structure of a file that is mostly payload). `damaged(seed)` draws 1-4 mutations.

The pass sizes: FUZZ_EXAMPLES (default 25) inputs per seed in the default suite; the slow
pass reads E3DPSM_FUZZ_EXAMPLES (default 1000). With E3DPSM_FUZZ_REPORT=FILE each test
appends its counts (one JSON line) to FILE; docs/testing.md has the table and the command.
"""
from __future__ import annotations

import json
import os
import struct
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

FUZZ_EXAMPLES = 25
SLOW_EXAMPLES = int(os.environ.get("E3DPSM_FUZZ_EXAMPLES", "1000"))
BOUND_S = 20.0  # per input, in-process reader calls (they take milliseconds)
CLI_BOUND_S = 90.0  # per command (the bound set for a damaged recording)
MUTATIONS = ("flip", "truncate", "insert", "duplicate", "length")


def fuzz_settings(examples: int, derandomize: bool = True) -> settings:
    """Hypothesis settings for a pass: no per-example deadline (the bounded worker enforces the
    time bound in a child process), no database, the module-scoped worker fixture allowed.
    The default pass is derandomised (the same inputs every run); the slow pass draws new ones
    each run (`pytest --hypothesis-seed=N` repeats one)."""
    return settings(max_examples=examples, deadline=None, database=None, derandomize=derandomize,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                           HealthCheck.data_too_large])


@dataclass(frozen=True)
class Seed:
    name: str  # the file name the damaged copy gets (its suffix picks the reader)
    data: bytes = field(repr=False)
    writer: str = ""  # who wrote the undamaged file
    fields: tuple[tuple[int, int], ...] = ()  # (offset, width in bytes) of length/offset fields
    hot: tuple[tuple[int, int], ...] = ()  # [start, end) ranges drawn from 3 times in 4


@st.composite
def positions(draw: st.DrawFn, seed: Seed, size: int) -> int:
    hot = [(a, min(b, size)) for a, b in seed.hot if a < min(b, size)]
    if hot and draw(st.integers(0, 3)):
        start, end = draw(st.sampled_from(hot))
        return draw(st.integers(start, end - 1))
    return draw(st.integers(0, size - 1))


def _boundary_values(old: int, size: int, width: int) -> list[int]:
    top = (1 << (8 * width - 1)) - 1
    return [0, 1, -1, top, -top - 1, size, size + 1, size - 1, old + 1, old - 1, old * 2, old // 2, 1 << 16]


class Damaged:
    """A damaged copy of a seed; its repr (what Hypothesis prints for a failing input) is the
    list of mutations, not the bytes (Hypothesis prints a dataclass's every field)."""

    def __init__(self, data: bytes, steps: tuple[str, ...]) -> None:
        self.data, self.steps = data, steps

    def __repr__(self) -> str:
        return f"Damaged(steps={list(self.steps)})"


@st.composite
def damaged(draw: st.DrawFn, seed: Seed) -> Damaged:
    """1-4 mutations of the seed."""
    data = bytearray(seed.data)
    done: list[str] = []
    for _ in range(draw(st.integers(1, 4))):
        if not data:
            break
        kind = draw(st.sampled_from(MUTATIONS))
        at = draw(positions(seed, len(data)))
        if kind == "flip":
            mask = draw(st.integers(1, 255))
            data[at] ^= mask
            done.append(f"flip {at} ^{mask:#x}")
        elif kind == "truncate":
            del data[at:]
            done.append(f"truncate at {at}")
        elif kind == "insert":
            blob = draw(st.binary(min_size=1, max_size=16))
            data[at:at] = blob
            done.append(f"insert {blob.hex()} at {at}")
        elif kind == "duplicate":
            length = draw(st.integers(1, min(4096, len(data) - at)))
            to = draw(st.integers(0, len(data)))
            data[to:to] = data[at:at + length]
            done.append(f"duplicate {at}+{length} to {to}")
        else:
            done.append(_corrupt_field(draw, seed, data))
    return Damaged(bytes(data), tuple(done))


def _corrupt_field(draw: st.DrawFn, seed: Seed, data: bytearray) -> str:
    fields = [(at, w) for at, w in seed.fields if at + w <= len(data)]
    if fields:
        at, width = draw(st.sampled_from(fields))
    else:  # no known field: a 4-byte word anywhere
        at, width = draw(st.integers(0, max(0, len(data) - 4))) // 4 * 4, 4
        if at + 4 > len(data):
            return "length: file too short"
    fmt = {2: "<h", 4: "<i", 8: "<q"}[width]
    old = struct.unpack_from(fmt, data, at)[0]
    top = (1 << (8 * width - 1)) - 1
    value = draw(st.sampled_from(_boundary_values(old, len(data), width)) | st.integers(-top - 1, top))
    struct.pack_into(fmt, data, at, max(-top - 1, min(top, value)))
    return f"length field at {at} ({width} bytes): {old} -> {value}"


def zip_fields(data: bytes) -> tuple[tuple[tuple[int, int], ...], tuple[tuple[int, int], ...]]:
    """(fields, hot) of a zip file (npz, torch.save): the size, name-length and offset fields of
    each local header and central directory entry and of the end record; hot: the headers,
    the directory, and members whose names end in .pkl (a checkpoint's structure)."""
    import io

    fields, hot = [], []
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        for info in archive.infolist():
            local = info.header_offset
            fields += [(local + 18, 4), (local + 22, 4), (local + 26, 2), (local + 28, 2)]
            name_length, extra_length = struct.unpack_from("<HH", data, local + 26)
            start = local + 30 + name_length + extra_length
            hot.append((local, start))
            if info.filename.endswith(".pkl"):
                hot.append((start, start + info.compress_size))
    end = data.rindex(b"PK\x05\x06")
    directory = struct.unpack_from("<I", data, end + 16)[0]
    fields += [(end + 8, 2), (end + 10, 2), (end + 12, 4), (end + 16, 4)]
    at = directory
    while data[at:at + 4] == b"PK\x01\x02":
        fields += [(at + 20, 4), (at + 24, 4), (at + 28, 2), (at + 42, 4)]
        at += 46 + sum(struct.unpack_from("<HHH", data, at + 28))
    hot.append((directory, len(data)))
    return tuple(fields), tuple(hot)


def aedat4_fields(data: bytes) -> tuple[tuple[int, int], ...]:
    """The IO header's size, compression and data table position, and each packet's stream id
    and size (packets walked up to the data table)."""
    from e3dpsm.data.formats.flatbuffer import root_table

    size = struct.unpack_from("<i", data, 14)[0]
    table = root_table(data[18:18 + size], b"IOHE")
    fields = [(14, 4)] + [(18 + table.pos + offset, width)
                          for offset, width in zip(table.field_offsets, (4, 8)) if offset]
    end = struct.unpack_from("<q", data, fields[-1][0])[0] if len(fields) == 3 else len(data)
    at = 18 + size
    while at + 8 <= end:
        fields += [(at, 4), (at + 4, 4)]
        at += 8 + struct.unpack_from("<i", data, at + 4)[0]
    return tuple(fields)


@dataclass
class Counts:
    """What one pass saw: inputs, how they ended, the slowest one."""

    target: str
    bound_s: float
    inputs: int = 0
    outcomes: dict[str, int] = field(default_factory=dict)
    slowest_s: float = 0.0
    slowest: str = ""
    started: float = field(default_factory=time.monotonic)

    def add(self, outcome: str, seconds: float, what: str) -> None:
        self.inputs += 1
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1
        if seconds > self.slowest_s:
            self.slowest_s, self.slowest = seconds, what

    def report(self) -> None:
        path = os.environ.get("E3DPSM_FUZZ_REPORT")
        if not path or not self.inputs:
            return
        row = {"target": self.target, "inputs": self.inputs, **self.outcomes, "slowest_s": round(self.slowest_s, 3),
               "slowest": self.slowest, "bound_s": self.bound_s, "wall_s": round(time.monotonic() - self.started, 1)}
        with open(path, "a", encoding="utf-8") as fh:
            fh.write(json.dumps(row) + "\n")


def outcome_label(outcome: Any) -> str:
    """How the counts name an Outcome: read, refused, refused_crash (a crash the isolation
    turned into one error line: the HDF5 library), or the failure kinds."""
    if outcome.kind == "returned":
        return "read"
    if outcome.kind == "refused" and "the reader crashed" in outcome.detail:
        return "refused_crash"
    return outcome.kind


def write_input(folder: Path, seed: Seed, data: bytes) -> Path:
    path = folder / seed.name
    path.write_bytes(data)
    return path


JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**70), 2**70) | st.floats() | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
    max_leaves=6)
DELETE = object()


def json_paths(node: Any, prefix: tuple = ()) -> list[tuple]:
    """The key path of every value in a JSON document (the root is ())."""
    paths = [prefix]
    children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, child in children:
        paths += json_paths(child, (*prefix, key))
    return paths


@st.composite
def json_damaged(draw: st.DrawFn, seed: Seed) -> Damaged:
    """1-3 values of a JSON seed replaced by other JSON values (any type, NaN, huge numbers)
    or deleted: the damage a hand edit or a bug in another writer makes, which byte-level
    mutations of JSON text rarely reach (they mostly break the syntax)."""
    document = json.loads(seed.data)
    done = []
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(json_paths(document)))
        value = draw(JSON_VALUES | st.just(DELETE))
        if not path:
            document = {} if value is DELETE else value
        else:
            parent = document
            for key in path[:-1]:
                parent = parent[key]
            if value is DELETE:
                del parent[path[-1]]
            else:
                parent[path[-1]] = value
        done.append(f"{'/'.join(map(str, path)) or '(root)'} -> {'deleted' if value is DELETE else repr(value)[:40]}")
    return Damaged(json.dumps(document).encode(), tuple(done))
