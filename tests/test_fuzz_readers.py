"""Fuzzing the event readers: damaged copies of files that independent writers produced
(tests/_fuzz_seeds.py: expelliarmus, dv-processing, h5py, numpy, the spec encoder of EVT 3.0).
Each input is read by `read_events` in a child process (tests/_bounded.py) under a time
bound; it must end with events or one DataError line. A hang, a crash or any other exception fails the test with the
mutations that caused it (Hypothesis shrinks them).

The default pass reads FUZZ_EXAMPLES inputs per file; the slow pass E3DPSM_FUZZ_EXAMPLES
(docs/testing.md has its counts and the command).
"""
from __future__ import annotations

import pytest
from hypothesis import given

from _bounded import BoundedWorker
from _fuzz import (BOUND_S, FUZZ_EXAMPLES, SLOW_EXAMPLES, Counts, Seed, damaged, fuzz_settings, outcome_label,
                   write_input)
from _fuzz_seeds import SEEDS, make_seed, seed_stream


@pytest.fixture(scope="module")
def stream():
    return seed_stream()


@pytest.fixture(scope="module")
def seeds(stream, tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz_seeds")
    return {name: make_seed(name, stream, folder) for name in SEEDS}


@pytest.fixture(scope="module")
def worker():
    with BoundedWorker(preload=("e3dpsm.data.readers", "_fuzz_targets", "h5py", "lz4.frame", "zstandard")) as bounded:
        yield bounded


def fuzz_pass(seed: Seed, worker: BoundedWorker, folder, examples: int, derandomize: bool = True) -> None:
    counts = Counts(f"read_events {seed.name} ({seed.writer})", BOUND_S)

    @fuzz_settings(examples, derandomize)
    @given(damaged(seed))
    def read_damaged(case):
        outcome = worker.call("_fuzz_targets:read_events", write_input(folder, seed, case.data), bound_s=BOUND_S)
        counts.add(outcome_label(outcome), outcome.seconds, "; ".join(case.steps))
        where = f"{seed.name} ({seed.writer}) after {list(case.steps)}"
        assert outcome.kind in ("returned", "refused"), f"{where}: {outcome.kind}: {outcome.detail}"
        if outcome.kind == "refused":
            assert outcome.detail.startswith("DataError: ") and "\n" not in outcome.detail, f"{where}: {outcome.detail}"

    try:
        read_damaged()
    finally:
        counts.report()


@pytest.mark.parametrize("name", SEEDS)
def test_every_seed_reads_back_its_events(seeds, worker, stream, tmp_path, name):
    """The undamaged files are what the fuzzing starts from: each reads back every event."""
    outcome = worker.call("_fuzz_targets:read_events", write_input(tmp_path, seeds[name], seeds[name].data),
                          bound_s=BOUND_S)
    assert outcome.kind == "returned" and outcome.value == len(stream), outcome


@pytest.mark.parametrize("name", SEEDS)
def test_damaged_files_end_with_events_or_one_error_line(seeds, worker, tmp_path, name):
    fuzz_pass(seeds[name], worker, tmp_path, FUZZ_EXAMPLES)


@pytest.mark.slow
@pytest.mark.parametrize("name", SEEDS)
def test_damaged_files_long_pass(seeds, worker, tmp_path, name):
    fuzz_pass(seeds[name], worker, tmp_path, SLOW_EXAMPLES, derandomize=False)
