"""Coverage-guided fuzzing of e3dpsm's own decoders with atheris (libFuzzer for Python).

    pip install atheris
    python tests/fuzz/atheris_readers.py FORMAT [libFuzzer flags]
    python tests/fuzz/atheris_readers.py aedat4 -max_total_time=300 -max_len=65536

FORMAT: aedat4, evt2, evt3, dat or npz. The decoders' Python is instrumented (every branch it
takes guides the mutations); each input is written to /dev/shm with the format's suffix and
read by `read_events`. A DataError is the expected way to refuse; any other exception is a
finding: libFuzzer stops and writes the input to runs/atheris/FORMAT-findings/crash-<sha1>.
A hang shows as a timeout (`-timeout=N`, default 20 s here). The corpus starts from files
the tests' independent writers make (tests/_fuzz_seeds.py) and grows in runs/atheris/FORMAT/.

HDF5 is not here: it is read in a child process (e3dpsm/utils/isolate.py), where atheris'
coverage cannot follow; tests/test_fuzz_readers.py covers it. docs/testing.md has what this
found.
"""
from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

import atheris

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

with atheris.instrument_imports(include=["e3dpsm"]):  # the readers import their decoders lazily: all here
    import e3dpsm.data.formats.flatbuffer  # noqa: F401
    import e3dpsm.data.formats.inivation  # noqa: F401
    import e3dpsm.data.formats.npz  # noqa: F401
    import e3dpsm.data.formats.prophesee  # noqa: F401
    import e3dpsm.events  # noqa: F401
    from e3dpsm.data.readers import read_events
    from e3dpsm.errors import DataError

SEED_NAMES = {"aedat4": "lz4.aedat4", "evt2": "evt2.raw", "evt3": "evt3.raw", "dat": "events.dat",
              "npz": "deflated.npz"}


def corpus(fmt: str) -> Path:
    """runs/atheris/FMT/, holding the seed file (and its other compressions for AEDAT4)."""
    from _fuzz_seeds import make_seed, seed_stream

    folder = ROOT / "runs" / "atheris" / fmt
    folder.mkdir(parents=True, exist_ok=True)
    names = ["lz4.aedat4", "zstd.aedat4", "plain.aedat4"] if fmt == "aedat4" else [SEED_NAMES[fmt]]
    if not any(folder.iterdir()):
        with tempfile.TemporaryDirectory() as tmp:
            for name in names:
                (folder / f"seed_{name}").write_bytes(make_seed(name, seed_stream(), Path(tmp)).data)
    return folder


def main() -> None:
    if len(sys.argv) < 2 or sys.argv[1] not in SEED_NAMES:
        sys.exit(f"usage: {sys.argv[0]} {{{','.join(SEED_NAMES)}}} [libFuzzer flags]")
    fmt = sys.argv[1]
    path = Path(tempfile.mkdtemp(dir="/dev/shm" if os.path.isdir("/dev/shm") else None)) / SEED_NAMES[fmt]

    def one_input(data: bytes) -> None:
        path.write_bytes(data)
        try:
            read_events(path)
        except DataError as exc:
            if "\n" in str(exc):
                raise AssertionError(f"a DataError of more than one line: {exc!r}") from exc

    flags = [a for a in sys.argv[2:] if a.startswith("-")]
    if not any(f.startswith("-timeout=") for f in flags):
        flags.append("-timeout=20")
    if not any(f.startswith("-artifact_prefix=") for f in flags):  # not the working folder
        findings = ROOT / "runs" / "atheris" / f"{fmt}-findings"
        findings.mkdir(parents=True, exist_ok=True)
        flags.append(f"-artifact_prefix={findings}/")
    atheris.Setup([sys.argv[0], *flags, str(corpus(fmt))], one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
