"""`e3dpsm compare` at its edges: a change exactly at its limit is no
regression, and each kind of figure is held to its own limit. Hand-made reports whose
figures make the percentages exact in binary (10 -> 11 is +10.0 exactly, 200 -> 201 is
+0.5 exactly), so float noise never decides a verdict."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from e3dpsm.cli import main
from e3dpsm.pipeline.compare import Change, compare


def _profile(path: Path, p50_ms: float, model_bytes: int) -> Path:
    path.write_text(json.dumps({"command": "profile", "targets": [
        {"name": "ort-cpu-fp32", "available": True, "latency_ms": {"p50": p50_ms}, "model_bytes": model_bytes}]}))
    return path


def _validate(path: Path, mpjpe_mm: float) -> Path:
    path.write_text(json.dumps({"command": "validate", "rows": [{"variant": "tiny", "mpjpe_mm": mpjpe_mm}]}))
    return path


@pytest.mark.parametrize("base, new, limit, regressed", [
    (10.0, 11.0, 10.0, False),            # exactly +10 %: at the limit, allowed
    (10.0, 11.0 + 2**-40, 10.0, True),    # the least bit over
    (200.0, 201.0, 0.5, False),           # exactly +0.5 % (the MPJPE default)
    (200.0, 201.0 + 2**-30, 0.5, True),
    (10.0, 10.0, 0.0, False),             # no change under a zero limit
    (10.0, 10.0 + 2**-40, 0.0, True),
])
def test_a_change_exactly_at_its_limit_is_no_regression(base, new, limit, regressed):
    change = Change("latency:x", "latency", base, new, limit)
    assert (change.change_pct == limit) is (not regressed)  # the percentages are exact
    assert change.regressed is regressed


def test_cli_exactly_at_the_latency_limit_passes_and_just_over_fails(tmp_path, capsys):
    base = _profile(tmp_path / "base.json", 10.0, 10_000_000)
    at = _profile(tmp_path / "at.json", 11.0, 10_000_000)
    over = _profile(tmp_path / "over.json", 11.0 + 2**-40, 10_000_000)
    assert main(["compare", str(base), str(at), "--max-latency-regression", "10%"]) == 0
    assert "+10.00% | +10% | ok |" in capsys.readouterr().out
    assert main(["compare", str(base), str(over), "--max-latency-regression", "10%"]) == 1


def test_cli_exactly_at_the_default_mpjpe_limit_passes(tmp_path):
    base = _validate(tmp_path / "base.json", 200.0)
    assert main(["compare", str(base), str(_validate(tmp_path / "at.json", 201.0))]) == 0
    assert main(["compare", str(base), str(_validate(tmp_path / "over.json", 201.0 + 2**-30))]) == 1


@pytest.mark.parametrize("flags, size_limit, code", [
    ([], None, 0),                                                            # size is not checked by default
    (["--max-latency-regression", "60%"], None, 0),                           # the latency limit is not the size's
    (["--max-size-growth", "10%"], 10.0, 1),
    (["--max-size-growth", "10%", "--max-latency-regression", "60%"], 10.0, 1),
    (["--max-size-growth", "60%", "--max-latency-regression", "5%"], 60.0, 0),
    (["--max-size-growth", "50%", "--max-latency-regression", "5%"], 50.0, 0),  # exactly at the limit
])
def test_size_growth_is_held_to_its_own_limit(tmp_path, flags, size_limit, code):
    """Size +50 % (10 MB -> 15 MB, exact), latency unchanged: only the size limit decides."""
    base = _profile(tmp_path / "base.json", 10.0, 10_000_000)
    bigger = _profile(tmp_path / "new.json", 10.0, 15_000_000)
    assert main(["compare", str(base), str(bigger), *flags, "--json", str(tmp_path / "c.json")]) == code
    report = json.loads((tmp_path / "c.json").read_text())
    size = next(c for c in report["changes"] if c["name"] == "size:ort-cpu-fp32")
    latency = next(c for c in report["changes"] if c["name"] == "latency:ort-cpu-fp32")
    assert size["change_pct"] == 50.0 and latency["change_pct"] == 0.0
    assert size["limit_pct"] == size_limit and size["regressed"] is (code == 1)
    assert report["regressions"] == (["size:ort-cpu-fp32"] if code else [])


def test_each_kind_reads_its_own_limit(tmp_path):
    """compare(): a limit given for one kind never applies to another."""
    base = _profile(tmp_path / "base.json", 10.0, 10_000_000)
    new = _profile(tmp_path / "new.json", 12.0, 15_000_000)  # latency +20 %, size +50 %
    changes = {c.name: c for c in compare(base, new, {"latency": 30.0, "size": 40.0})}
    assert changes["latency:ort-cpu-fp32"].limit_pct == 30.0 and not changes["latency:ort-cpu-fp32"].regressed
    assert changes["size:ort-cpu-fp32"].limit_pct == 40.0 and changes["size:ort-cpu-fp32"].regressed
