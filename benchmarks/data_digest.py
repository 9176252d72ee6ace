"""A digest per prepared sequence (its ground-truth poses and every 50th LNES frame: cheap, and
still any change), to check that another machine synthesised and prepared the same data.

    python3 benchmarks/data_digest.py OUT.json PREP [PREP ...]

Writes {"<prep folder name>/<sequence>": first 16 hex digits of the sha256} to OUT.json.
"""
from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np


def sequence_digest(seq: Path) -> str:
    pose = np.load(seq / "pose.npz")
    digest = hashlib.sha256(np.ascontiguousarray(pose["j3d_mm"]).tobytes())
    digest.update(np.ascontiguousarray(np.load(seq / "lnes.npy", mmap_mode="r")[::50]).tobytes())
    return digest.hexdigest()[:16]


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print("usage: data_digest.py OUT.json PREP [PREP ...]", file=sys.stderr)
        return 2
    out, preps = Path(argv[0]), [Path(p) for p in argv[1:]]
    digests = {f"{prep.name}/{seq.name}": sequence_digest(seq)
               for prep in preps for seq in sorted(p for p in prep.iterdir() if p.is_dir())}
    out.write_text(json.dumps(digests, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
