"""Benchmark reports are named by the CPU kind they ran on and written whole or not at all."""
from __future__ import annotations

import json

import pytest

from e3dpsm.utils.io import write_benchmark_report


def test_report_pair_is_named_by_isa_kind(tmp_path) -> None:
    report = {"isa": {"kind": "avx2"}, "p50_ms": 1.5}
    md = write_benchmark_report(tmp_path / "results" / "bench_x", report, "# x\n")
    assert md == tmp_path / "results" / "bench_x_avx2.md" and md.read_text() == "# x\n"
    assert json.loads((tmp_path / "results" / "bench_x_avx2.json").read_text()) == report


def test_an_unserialisable_report_leaves_no_file(tmp_path) -> None:
    with pytest.raises(TypeError, match="not JSON serialisable"):
        write_benchmark_report(tmp_path / "bench_y", {"isa": {"kind": "vnni"}, "bad": object()}, "# y\n")
    assert list(tmp_path.iterdir()) == []


def test_a_prefix_that_names_its_kind_or_holds_a_dot_is_kept_whole(tmp_path) -> None:
    """A results file's own name passed back as the prefix is not suffixed twice, and a dot in
    the name (a version) is not taken for a suffix to replace."""
    report = {"isa": {"kind": "vnni"}}
    assert write_benchmark_report(tmp_path / "edge_int8_vnni", report, "# a\n") == tmp_path / "edge_int8_vnni.md"
    assert write_benchmark_report(tmp_path / "run_v1.2", report, "# b\n") == tmp_path / "run_v1.2_vnni.md"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["edge_int8_vnni.json", "edge_int8_vnni.md",
                                                          "run_v1.2_vnni.json", "run_v1.2_vnni.md"]
