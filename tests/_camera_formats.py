"""Prophesee RAW / DAT encoders for the reader tests, written from Prophesee's public format
specification (docs.prophesee.ai: data/encoding_formats/evt2.html, evt3.html;
data/file_formats/dat.html, raw.html), as explicit per-event loops, independently of the
vectorised decoders in e3dpsm/data/formats/prophesee.py."""
from __future__ import annotations

import struct

import numpy as np

from e3dpsm.data.sequence import EventStream


def camera_stream(n: int = 3000, seed: int = 0, span_us: int = 40_000_000, t0_us: int = 1_000) -> EventStream:
    """Unique events sorted by (t, y, p, x), spanning more than EVT 3.0's 2^24 us wrap, with
    runs of neighbouring x on one row at one time (what EVT 3.0 encodes as vectors)."""
    rng = np.random.default_rng(seed)
    t = rng.integers(0, span_us, n) + t0_us
    x, y, p = rng.integers(0, 640, n), rng.integers(0, 480, n), rng.integers(0, 2, n)
    runs = []  # 40 bursts: up to 30 pixels of one row, same time and polarity, with holes
    for k in range(40):
        width = int(rng.integers(5, 30))
        xs = int(rng.integers(0, 600)) + np.flatnonzero(rng.random(width) < 0.7)
        runs.append(np.stack([np.full(xs.size, t[k]), xs, np.full(xs.size, y[k]), np.full(xs.size, p[k])], 1))
    table = np.unique(np.concatenate([np.stack([t, x, y, p], 1), *runs]), axis=0)
    table = table[np.lexsort((table[:, 1], table[:, 3], table[:, 2], table[:, 0]))]  # by t, y, p, x
    return EventStream(x=table[:, 1].astype(np.int32), y=table[:, 2].astype(np.int32),
                       t_us=table[:, 0].astype(np.int64), p=table[:, 3].astype(np.uint8))


def _header(lines: list[str]) -> bytes:
    return "".join(f"% {line}\n" for line in lines).encode("ascii")


def encode_evt2(stream: EventStream, header: list[str]) -> bytes:
    """EVT 2.0: 32-bit LE words, type in bits 31..28. CD_OFF 0x0 / CD_ON 0x1: t low 6 bits in
    27..22, x in 21..11, y in 10..0. EVT_TIME_HIGH 0x8: t bits 33..6 in 27..0. A CD word
    before the first time-high (undefined time, to be dropped), a trigger (0xA) and an
    OTHERS (0xE) word are mixed in."""
    words = [(0x1 << 28) | (5 << 11) | 7]  # before any time high: no defined time
    high = None
    for i, (x, y, t, p) in enumerate(zip(stream.x.tolist(), stream.y.tolist(), stream.t_us.tolist(), stream.p.tolist())):
        if t >> 6 != high:
            high = t >> 6
            words.append((0x8 << 28) | high)
        if i == 10:
            words += [(0xA << 28) | 123, (0xE << 28) | 456]
        words.append((p << 28) | ((t & 0x3F) << 22) | (x << 11) | y)
    return _header(header) + struct.pack(f"<{len(words)}I", *words)


def encode_evt3(stream: EventStream, header: list[str]) -> bytes:
    """EVT 3.0: 16-bit LE words, type in bits 15..12. ADDR_Y 0x0 (y in 10..0), ADDR_X 0x2
    (p in 11, x in 10..0), VECT_BASE_X 0x3 (p, base x), VECT_12 0x4 / VECT_8 0x5 (valid
    mask, bit i = base + i; base += 12 / 8), TIME_LOW 0x6 and TIME_HIGH 0x8 (the low and
    high 12 bits of a 24-bit time that wraps every 2^24 us). Events of one (t, y, p) with
    neighbouring x go out as vectors, the rest as single events. The stream must be sorted
    by (t, y, p, x) without repeats (what `camera_stream` makes), the order vectors keep."""
    words: list[int] = []
    high = low = row = None
    events = list(zip(stream.t_us.tolist(), stream.y.tolist(), stream.p.tolist(), stream.x.tolist()))
    i = 0
    while i < len(events):
        t, y, p, _ = events[i]
        group = []
        while i < len(events) and events[i][:3] == (t, y, p):
            group.append(events[i][3])
            i += 1
        if (t >> 12) & 0xFFF != high:
            high = (t >> 12) & 0xFFF
            words.append((0x8 << 12) | high)
            low = None  # as cameras do: a time-low follows each time-high
        if t & 0xFFF != low:
            low = t & 0xFFF
            words.append((0x6 << 12) | low)
        if y != row:
            row = y
            words.append((0x0 << 12) | y)
        j = 0
        while j < len(group):
            if j + 1 < len(group) and group[j + 1] - group[j] < 12:  # a vector from group[j]
                base = group[j]
                words.append((0x3 << 12) | (p << 11) | base)
                while j < len(group) and group[j] < base + 12:
                    span = 8 if not any(base + 8 <= x < base + 12 for x in group[j:]) else 12
                    mask = 0
                    while j < len(group) and group[j] < base + span:
                        mask |= 1 << (group[j] - base)
                        j += 1
                    words.append(((0x4 if span == 12 else 0x5) << 12) | mask)
                    base += span
            else:
                words.append((0x2 << 12) | (p << 11) | group[j])
                j += 1
    return _header(header) + struct.pack(f"<{len(words)}H", *words)


def encode_dat(stream: EventStream, header: list[str]) -> bytes:
    """DAT version 2: header, then the bytes 0x0C (CD event) and 8 (size), then per event a
    32-bit timestamp and a 32-bit word with x in bits 13..0, y in 27..14, p in 31..28."""
    body = b"".join(
        struct.pack("<II", t, (p << 28) | (y << 14) | x)
        for x, y, t, p in zip(stream.x.tolist(), stream.y.tolist(), stream.t_us.tolist(), stream.p.tolist())
    )
    return _header(header) + bytes([0x0C, 8]) + body
