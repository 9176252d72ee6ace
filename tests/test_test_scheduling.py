"""The test run's own scheduling (tests/conftest.py): under `pytest -n 2 --dist loadgroup`
each worker keeps its own cores, and the tests sharing a costly fixture go to one worker."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import _EXPENSIVE_FIXTURE_GROUPS, fixture_group, worker_cores

TESTS = Path(__file__).parent


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


def test_a_test_is_grouped_by_its_one_costly_fixture() -> None:
    # A fixture chain's names all appear in a test's closure; its first link names the group.
    assert fixture_group(["tmp_path", "int8_graph", "int8_dir", "int8_test_budget_pct", "int8_recurrent_dir"]) \
        == "int8_search"
    assert fixture_group(["fp16_dir", "int8_recurrent_dir"]) == "int8_search"  # the pipeline test
    assert fixture_group(["prepared_data", "synthetic_data"]) == "synthetic_data"
    assert fixture_group(["tmp_path", "quant_data"]) is None
    assert fixture_group(["int8_recurrent_dir", "pruned_tiny"]) is None  # two groups: on its own


def test_every_grouped_fixture_exists() -> None:
    """A renamed fixture would silently leave its tests ungrouped, built once per worker."""
    source = "\n".join(p.read_text(encoding="utf-8") for p in TESTS.glob("*.py"))
    defined = set(re.findall(r"@pytest\.fixture[^\n]*\ndef (\w+)\(", source))
    assert set(_EXPENSIVE_FIXTURE_GROUPS) <= defined, set(_EXPENSIVE_FIXTURE_GROUPS) - defined


def test_xdist_sees_the_groups(request: pytest.FixtureRequest) -> None:
    """Under `--dist loadgroup`, xdist's own hook turns the markers into test-id suffixes
    ("...@int8_search"), which its scheduler reads: the markers must be on before it runs
    (conftest's hook is tryfirst). Without that the INT8 search was built on both workers."""
    # In a worker xdist sets `loadgroup` (its `dist` option reads "no" there).
    if not hasattr(request.config, "workerinput") or not request.config.getoption("loadgroup", False):
        pytest.skip("runs inside a `pytest -n N --dist loadgroup` worker (the README's test command)")
    grouped = [(item, fixture_group(item.fixturenames)) for item in request.session.items
               if fixture_group(getattr(item, "fixturenames", [])) is not None]
    if not grouped:
        pytest.skip("no test of this run uses a costly fixture")
    assert all(item.nodeid.endswith(f"@{group}") for item, group in grouped), \
        [item.nodeid for item, group in grouped if not item.nodeid.endswith(f"@{group}")][:3]
