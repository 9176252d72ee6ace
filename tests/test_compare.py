"""e3dpsm compare: regressions between two reports fail (exit 1), identical reports pass."""
from __future__ import annotations

import copy
import json
from pathlib import Path

import pytest

from e3dpsm.cli import main


@pytest.fixture(scope="module")
def profile_report(tmp_path_factory, tiny_step_graph) -> Path:  # noqa: F811
    out = tmp_path_factory.mktemp("cmp") / "prof"
    assert main(["profile", "--model", str(tiny_step_graph), "--targets", "ort-cpu-fp32", "--out", str(out),
                 "--steps", "10", "--warmup", "2", "--profile-steps", "0"]) == 0
    return out / "report.json"


def _variant(src: Path, dst: Path, edit) -> Path:
    report = json.loads(src.read_text())
    edit(report)
    dst.write_text(json.dumps(report))
    return dst


def _slower(factor: float):
    def edit(report):
        target = next(t for t in report["targets"] if t["name"] == "ort-cpu-fp32")
        target["latency_ms"]["p50"] *= factor
    return edit


def test_identical_reports_pass(profile_report, tmp_path, capsys) -> None:
    assert main(["compare", str(profile_report), str(profile_report), "--json", str(tmp_path / "c.json")]) == 0
    result = json.loads((tmp_path / "c.json").read_text())
    assert result["passed"] and not result["regressions"]
    assert "| latency:ort-cpu-fp32 |" in capsys.readouterr().out


@pytest.mark.parametrize("limit, code", [("10%", 1), ("25%", 0)])
def test_a_20_percent_latency_regression(profile_report, tmp_path, capsys, limit, code) -> None:
    slower = _variant(profile_report, tmp_path / "new.json", _slower(1.2))
    assert main(["compare", str(profile_report), str(slower), "--max-latency-regression", limit]) == code
    out = capsys.readouterr().out
    assert ("REGRESSION" in out) == (code == 1) and "+20.00%" in out
    # a faster run is never a regression
    faster = _variant(profile_report, tmp_path / "fast.json", _slower(0.5))
    assert main(["compare", str(profile_report), str(faster)]) == 0


def test_mpjpe_and_size_limits(tmp_path) -> None:
    validate = {"command": "validate", "rows": [{"variant": "step_int8 (int8)", "mpjpe_mm": 100.0}]}
    base = tmp_path / "base.json"
    base.write_text(json.dumps(validate))
    for growth, code in ((1.006, 1), (1.004, 0)):  # default limit 0.5 %
        worse = copy.deepcopy(validate)
        worse["rows"][0]["mpjpe_mm"] *= growth
        (tmp_path / "new.json").write_text(json.dumps(worse))
        assert main(["compare", str(base), str(tmp_path / "new.json")]) == code, growth


def test_bad_reports_are_refused(profile_report, tmp_path, capsys) -> None:
    (tmp_path / "junk.json").write_text("not json")
    (tmp_path / "train.json").write_text(json.dumps({"command": "train"}))
    assert main(["compare", str(profile_report), str(tmp_path / "junk.json")]) == 2
    assert main(["compare", str(profile_report), str(tmp_path / "train.json")]) == 2
    err = capsys.readouterr().err
    assert "cannot read report" in err and "'train' report" in err
