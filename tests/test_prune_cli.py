"""`e3dpsm prune` from the command line: bad input in one line, and prune -> export -> parity
-> quantize on the trained tiny."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.cli import main
from tests._quantize_helpers import TRAINED_TINY


@pytest.mark.parametrize("targets, message", [
    (["--target-macs", "0.5", "--target-latency-ms", "5"], "exactly one target"),
    ([], "exactly one target"),
    (["--target-macs", "1.0"], "in (0, 1)"),
    (["--target-macs", "1.5"], "in (0, 1)"),
    (["--target-macs", "0"], "in (0, 1)"),
    (["--target-latency-ms", "-3"], "must be positive"),
])
def test_bad_targets_exit_2_with_one_line(targets, message, tmp_path, capsys):
    code = main(["prune", "--checkpoint", str(TRAINED_TINY), "--data", str(tmp_path), "--out",
                 str(tmp_path / "out"), *targets])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and message in err
    assert not (tmp_path / "out").exists()


def test_missing_checkpoint_exits_2(tmp_path, capsys):
    code = main(["prune", "--checkpoint", str(tmp_path / "nope.pt"), "--data", str(tmp_path), "--out",
                 str(tmp_path / "out"), "--target-macs", "0.5"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "does not exist" in err


@pytest.fixture(scope="module")
def pruned_tiny(tmp_path_factory, quant_data) -> Path:
    out = tmp_path_factory.mktemp("prune") / "tiny_pruned"
    code = main(["prune", "--checkpoint", str(TRAINED_TINY), "--data", str(quant_data), "--out", str(out),
                 "--target-macs", "0.7", "--rounds", "1", "--steps", "2", "--eval-frames", "20",
                 "--timing-steps", "10", "--threads", "1", "--no-progress"])
    assert code == 0
    return out


def test_prune_meets_the_macs_target_and_reports_it(pruned_tiny):
    from e3dpsm.checkpoint import load_checkpoint
    from e3dpsm.compress.plan import total_macs

    report = json.loads((pruned_tiny / "report.json").read_text())
    assert report["met"] and report["best"] == 1
    model, _ = load_checkpoint(pruned_tiny / "checkpoint.pt")
    original, _ = load_checkpoint(TRAINED_TINY)
    # The MACs the report gives are the rebuilt checkpoint's, at most the target.
    assert report["rounds"][1]["macs"] == total_macs(model)
    assert total_macs(model) <= 0.7 * total_macs(original)
    assert report["rounds"][0]["macs"] == total_macs(original)
    for name in ("report.md", "front.png", "graphs/round0.onnx", "graphs/round1.onnx"):
        assert (pruned_tiny / name).is_file(), name
    assert set(report["final_timing_ms"]) >= {"r0_ort_fp32", "r1_ort_fp32", "r1_ort_int8"}
    assert "| round | MACs" in (pruned_tiny / "report.md").read_text()


def test_pruned_checkpoint_exports_keeps_parity_and_quantizes(pruned_tiny, quant_data, tmp_path):
    """prune -> export -> parity (three windows) -> quantize, with the numbers checked."""
    ckpt = pruned_tiny / "checkpoint.pt"
    assert main(["export", "--checkpoint", str(ckpt), "--out", str(tmp_path / "export")]) == 0
    graph = tmp_path / "export" / "step.onnx"
    report = tmp_path / "parity.json"
    assert main(["parity", "--model", str(graph), "--checkpoint", str(ckpt), "--data", str(quant_data),
                 "--steps", "40", "--window-ms", "20", "25", "50", "--pose-atol-mm", "0.01",
                 "--report", str(report)]) == 0
    parity = json.loads(report.read_text())
    assert parity["passed"]
    assert main(["quantize", "--model", str(graph), "--data", str(quant_data), "--out", str(tmp_path / "q"),
                 "--exclude", "recurrent", "--frames", "16", "--holdout-frames", "40", "--threads", "1",
                 "--timing-steps", "10"]) == 0
    q = json.loads((tmp_path / "q" / "report.json").read_text())
    # INT8 of a pruned model stays a usable pose model: its held-out error moves by little.
    mpjpe = q["check"]["by_runtime"]["onnxruntime"]["metrics"]["mpjpe"]
    assert np.isfinite(mpjpe["value_mm"]) and abs(mpjpe["change_pct"]) < 25.0


def test_latency_percentage_is_checked_in_one_line(tmp_path, capsys):
    code = main(["prune", "--checkpoint", str(TRAINED_TINY), "--data", str(tmp_path), "--out",
                 str(tmp_path / "out"), "--target-latency-ms", "120%"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "(0, 100)%" in err
