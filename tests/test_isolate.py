"""e3dpsm/utils/isolate.py: a reader in a forked child of a helper process ends the call with its
value, or one DataError line on a crash or past its deadline; the caller survives both."""
from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.errors import DataError
from e3dpsm.utils.isolate import IsolatedError, deadline_for, run_isolated

FIXTURES = Path(__file__).parent / "fixtures"


def call(target: str, *args: str, deadline_s: float = 30.0):
    return run_isolated(f"_fuzz_targets:{target}", *args, deadline_s=deadline_s, what="file.h5")


def test_arrays_of_every_shape_and_dtype_come_back_exactly():
    got = call("typed_arrays", "1000")
    assert got["hw"] == [480, 640] and got["name"] == "x"
    np.testing.assert_array_equal(got["i32"], np.arange(1000, dtype=np.int32) - 7)
    assert got["i32"].dtype == np.int32 and got["u8"].dtype == np.uint8 and got["u8"][-1] == 999 % 251
    np.testing.assert_array_equal(got["f64_2d"], np.arange(2000.0).reshape(1000, 2) / 3)
    assert got["empty"].shape == (0,) and got["empty"].dtype == np.int64


def test_a_crash_is_one_error_line_and_the_next_call_works():
    with pytest.raises(DataError, match=r"^file\.h5: the reader crashed \(SIGSEGV\) on this file; it is damaged$"):
        call("segfault")
    assert call("typed_arrays", "3")["i32"].tolist() == [-7, -6, -5]


def test_a_call_past_its_deadline_is_killed_and_the_helper_kept():
    helper = call("pid")["parent"]
    start = time.monotonic()
    with pytest.raises(DataError, match=r"^file\.h5: reading did not end within 1 s \(the file is damaged"):
        call("spin", deadline_s=1.0)
    assert time.monotonic() - start < 10
    again = call("pid")
    assert again["parent"] == helper and again["pid"] != helper  # each call in a fresh child of one helper


def test_errors_keep_their_message_and_bugs_their_type():
    with pytest.raises(DataError, match=r"^bad file: byte 7$"):
        call("refuse", "bad file: byte 7")
    with pytest.raises(IsolatedError, match=r"^KeyError: 'a bug'$"):
        call("buggy")


def test_the_caller_is_not_the_process_that_reads():
    got = call("pid")
    assert got["pid"] != os.getpid() and got["parent"] != os.getpid()


def test_a_forked_worker_starts_its_own_helper():
    """A process pool forked after this process started its helper must not talk to that
    helper over the inherited pipes (the two would read each other's replies)."""
    import concurrent.futures as cf
    import multiprocessing as mp

    from _fuzz_targets import helper_of_this_process

    mine = helper_of_this_process()
    with cf.ProcessPoolExecutor(1, mp_context=mp.get_context("fork")) as pool:
        theirs = pool.submit(helper_of_this_process).result(timeout=120)
    assert theirs != mine and helper_of_this_process() == mine


def test_deadline_grows_with_the_file():
    assert deadline_for(0) == 30 and deadline_for(200_000_000) == 40


def test_an_hdf5_file_that_segfaulted_h5py_is_one_error_line():
    """tests/fixtures/hdf5/lzf_chunk_flip.h5: one byte of its LZF chunk changed (README there);
    reading it in the reading process killed that process with SIGSEGV (h5py 3.16, HDF5 2.0.0).
    Read from a bounded child, so that a regression fails this test instead of killing pytest."""
    from _bounded import BoundedWorker

    path = FIXTURES / "hdf5" / "lzf_chunk_flip.h5"
    with BoundedWorker(preload=("e3dpsm.data.readers",)) as worker:
        outcome = worker.call("e3dpsm.data.readers:read_events", path, bound_s=60)
    assert outcome.kind == "refused", outcome
    assert outcome.detail.startswith(f"DataError: {path}: ") and "\n" not in outcome.detail


def test_no_arrays_file_is_left_behind_after_a_value_a_crash_or_a_deadline(tmp_path, monkeypatch):
    import glob

    # A folder of this test's own: /dev/shm is shared with the other pytest-xdist worker,
    # whose calls create and remove their own arrays files meanwhile.
    folder = tmp_path / "shm"
    folder.mkdir()
    monkeypatch.setattr("e3dpsm.utils.isolate.SHARED_MEMORY", str(folder))
    before = set(glob.glob(os.path.join(folder, "e3dpsm-isolate-*")))
    call("typed_arrays", "10")
    for target, deadline in (("segfault", 30.0), ("spin", 1.0)):
        with pytest.raises(DataError):
            call(target, deadline_s=deadline)
    assert set(glob.glob(os.path.join(folder, "e3dpsm-isolate-*"))) == before == set()


def _group(pgid: int) -> list[int]:
    """Live processes in process group `pgid` (the helper and the children it forked)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            state, _, group = stat.read_text().rsplit(")", 1)[1].split()[:3]
        except (OSError, IndexError):
            continue
        if int(group) == pgid and state != "Z":  # not a child that ended and waits to be reaped
            members.append(int(stat.parent.name))
    return members


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads /proc")
def test_a_read_does_not_outlive_its_helper():
    """A helper killed while its child spins: the child dies with it (it once spun on, orphaned)."""
    import signal
    import threading

    from e3dpsm.utils import isolate

    errors = []
    reader = threading.Thread(target=lambda: errors.append(pytest.raises(DataError, call, "spin", deadline_s=120)))
    reader.start()
    # The helper is the one the spinning call went to (a helper that died since an earlier
    # call is replaced by then), found once that call holds the lock and has a live helper.
    # The bound is generous: on a loaded CI host a fork and an import took seconds.
    deadline = time.monotonic() + 90
    helper, child = None, []
    while not child and reader.is_alive() and time.monotonic() < deadline:
        running = isolate._helper
        if running is not None and isolate._lock.locked() and running.process.poll() is None:
            helper = running.process.pid
            child = [pid for pid in _group(helper) if pid != helper]
        time.sleep(0.05)
    assert child, (f"the spinning child did not start within 90 s (helper {helper}, "
                   f"reader {'running' if reader.is_alive() else 'ended: ' + repr(errors)})")
    try:
        os.kill(helper, signal.SIGKILL)
        reader.join(60)
        deadline = time.monotonic() + 10
        while _group(helper) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _group(helper) == [], "a child outlived its helper"
        assert "stopped answering" in str(errors[0].value)
    finally:
        for pid in child:
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)
