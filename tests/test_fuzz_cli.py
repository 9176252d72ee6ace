"""The command line on damaged inputs: `e3dpsm run`, `golden check` and `import --released` exit 0
or 2 (`golden check` also 1, a verdict), with exactly one `e3dpsm CMD: error:` line on 2, no
traceback, and nothing written.

A handful run as real processes (`python -m e3dpsm ...`, under CLI_BOUND_S): the files that
hung dv-processing and crashed h5py, a damaged checkpoint, a damaged golden. Many more run
`main()` in the bounded child process (tests/_bounded.py), on damaged copies of every seed of
the reader fuzz tests (tests/_fuzz_seeds.py).
"""
from __future__ import annotations

import itertools
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hypothesis import given

from _bounded import BoundedWorker
from _fuzz import CLI_BOUND_S, SLOW_EXAMPLES, Counts, Seed, damaged, fuzz_settings, write_input
from _fuzz_seeds import SEEDS, make_seed, seed_stream, small_golden
from _runtime_helpers import exported_tiny
from e3dpsm.cli import error_line
from e3dpsm.errors import DataError

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = Path(__file__).parent / "fixtures"
RUN_EXAMPLES = 2  # per seed in the default pass: each loads the graph


def test_an_error_is_one_line_whatever_its_message_holds():
    assert error_line("run", DataError("a.h5: cannot read HDF5 file: Unable to open\n  (bad superblock)\n")) == \
        "e3dpsm run: error: a.h5: cannot read HDF5 file: Unable to open (bad superblock)"
    assert error_line("golden", DataError("x")) == "e3dpsm golden: error: x"


def e3dpsm_process(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    """`python -m e3dpsm ARGS`, as a user runs it, under the issue's bound for a damaged input."""
    return subprocess.run([sys.executable, "-m", "e3dpsm", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=CLI_BOUND_S)


def assert_refused(done: subprocess.CompletedProcess | tuple, command: str, out: Path) -> str:
    code, err = (done.returncode, done.stderr) if isinstance(done, subprocess.CompletedProcess) else (done[0], done[2])
    assert code == 2 and "Traceback" not in err, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"e3dpsm {command}: error: "), err
    left = [p.name for p in out.parent.iterdir() if p.name == out.name or p.name.startswith(".")]
    assert left == [], f"written on exit 2: {left}"  # neither the output nor a temporary
    return lines[0]


@pytest.fixture(scope="module")
def graph(tmp_path_factory) -> Path:
    return exported_tiny(str(tmp_path_factory.getbasetemp()))[1]


@pytest.mark.parametrize("fixture, message", [
    ("aedat4/dv_hang_one_flip.aedat4", "corrupted packet at byte 830: the lz4 data does not decompress"),
    ("hdf5/lzf_chunk_flip.h5", "lzf_chunk_flip.h5: "),
])
def test_run_on_the_files_that_hung_or_crashed_a_library(graph, tmp_path, fixture, message):
    out = tmp_path / "out" / "poses.csv"
    out.parent.mkdir()
    done = e3dpsm_process(["run", "--model", str(graph), "--events", str(FIXTURES / fixture), "--out", str(out)],
                          tmp_path)
    assert message in assert_refused(done, "run", out)


def test_import_of_a_truncated_checkpoint(tmp_path):
    torch.save({"state_dict": {"model.event_3d_posenet.conv1.0.weight": torch.ones(8, 2, 3, 3)}}, tmp_path / "a.ckpt")
    data = (tmp_path / "a.ckpt").read_bytes()
    (tmp_path / "a.ckpt").write_bytes(data[: len(data) // 2])
    out = tmp_path / "imported"
    done = e3dpsm_process(["import", "--released", str(tmp_path / "a.ckpt"), "--out", str(out)], tmp_path)
    assert "is not a readable PyTorch checkpoint" in assert_refused(done, "import", out)


def test_golden_check_of_a_golden_with_a_nameless_state(graph, tmp_path):
    record = small_golden(tmp_path / "golden")
    manifest = json.loads((record / "golden.json").read_text())
    manifest["states"][0]["name"] = None
    (record / "golden.json").write_text(json.dumps(manifest))
    out = tmp_path / "check"
    done = e3dpsm_process(["golden", "check", "--model", str(graph), "--golden", str(record), "--out", str(out)],
                          tmp_path)
    assert "'states' is" in assert_refused(done, "golden", out)


# `run` on damaged recordings, in the bounded child ------------------------------------------------
@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli_seeds")
    stream = seed_stream()
    return {name: make_seed(name, stream, folder) for name in SEEDS}


@pytest.fixture(scope="module")
def worker():
    with BoundedWorker(preload=("_fuzz_targets", "e3dpsm.cli.run", "e3dpsm.runtime", "h5py")) as bounded:
        yield bounded


def run_pass(seed: Seed, graph: Path, worker: BoundedWorker, folder: Path, examples: int,
             derandomize: bool = True) -> None:
    counts = Counts(f"e3dpsm run {seed.name} ({seed.writer})", CLI_BOUND_S)
    runs = itertools.count()

    @fuzz_settings(examples, derandomize)
    @given(damaged(seed))
    def run_damaged(case):
        run = folder / f"run_{next(runs)}"
        run.mkdir()
        events, out = write_input(run, seed, case.data), run / "out" / "poses.csv"
        out.parent.mkdir()
        outcome = worker.call("_fuzz_targets:run_cli", ["run", "--model", str(graph), "--events", str(events),
                                                         "--out", str(out), "--threads", "1", "--no-progress"],
                              bound_s=CLI_BOUND_S)
        where = f"{seed.name} after {list(case.steps)}"
        assert outcome.kind == "returned", f"{where}: {outcome.kind}: {outcome.detail}"
        code = outcome.value[0]
        counts.add(f"exit_{code}", outcome.seconds, "; ".join(case.steps))
        if code == 0:
            assert out.is_file() and out.with_name("poses.report.json").is_file(), where
        else:
            assert_refused(outcome.value, "run", out)
        shutil.rmtree(run)

    try:
        run_damaged()
    finally:
        counts.report()


@pytest.mark.parametrize("name", SEEDS)
def test_run_on_damaged_recordings_exits_0_or_2_with_one_line(seeds, graph, worker, tmp_path, name):
    run_pass(seeds[name], graph, worker, tmp_path, RUN_EXAMPLES)


@pytest.mark.slow
@pytest.mark.parametrize("name", SEEDS)
def test_run_on_damaged_recordings_long_pass(seeds, graph, worker, tmp_path, name):
    run_pass(seeds[name], graph, worker, tmp_path, max(SLOW_EXAMPLES // 10, RUN_EXAMPLES), False)
