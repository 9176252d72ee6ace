"""The test run's own scheduling (tests/conftest.py): under `pytest -n 2` each worker keeps
its own cores."""
from __future__ import annotations

import pytest

from tests.conftest import worker_cores


@pytest.mark.parametrize("worker, count, cores, expected", [
    ("gw0", 2, [0, 1], [0]),
    ("gw1", 2, [1, 0], [1]),                 # the affinity set's order does not matter
    ("gw1", 2, [0, 1, 2, 3], [1, 3]),        # a larger host: every second core
    ("gw2", 3, [4, 5, 6, 7, 8, 9], [6, 9]),
    ("gw0", 1, [0, 1], None),                # one worker: the whole machine
    ("gw1", 2, [0], None),                   # fewer cores than workers: nothing to split
    ("", 2, [0, 1], None),                   # not an xdist worker
    ("master", 2, [0, 1], None),
])
def test_each_worker_keeps_every_nth_core(worker: str, count: int, cores: list[int], expected) -> None:
    assert worker_cores(worker, count, cores) == expected


def test_two_workers_share_no_core_and_leave_none_out() -> None:
    cores = [0, 1, 2, 3, 4]
    mine = [worker_cores(f"gw{i}", 2, cores) for i in range(2)]
    assert sorted(mine[0] + mine[1]) == cores and not set(mine[0]) & set(mine[1])

