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


# -- replaying a plan's cuts elsewhere (prune --replay) ----------------------------------------
@pytest.fixture(scope="module")
def planned_tiny(tmp_path_factory, quant_data) -> Path:
    """A plan without recovery (--steps 0), two rounds: the kind of run whose cuts replay."""
    out = tmp_path_factory.mktemp("plan") / "tiny_plan"
    code = main(["prune", "--checkpoint", str(TRAINED_TINY), "--data", str(quant_data), "--out", str(out),
                 "--target-macs", "0.6", "--rounds", "2", "--steps", "0", "--eval-frames", "10",
                 "--timing-steps", "5", "--threads", "1", "--no-int8", "--no-progress"])
    assert code == 0
    return out


def test_replay_rebuilds_the_planned_model_bit_for_bit(planned_tiny, tmp_path, capsys):
    import torch

    from e3dpsm.checkpoint import load_checkpoint, read_checkpoint

    report = json.loads((planned_tiny / "report.json").read_text())
    assert report["best"] == 2, "the plan should cut in two rounds (each round cuts the previous one's model)"
    out = tmp_path / "replayed"
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--replay", str(planned_tiny / "report.json"),
                 "--out", str(out)]) == 0
    assert "replayed 2 round(s)" in capsys.readouterr().out
    planned, _ = load_checkpoint(planned_tiny / "checkpoint.pt")
    replayed, _ = load_checkpoint(out / "checkpoint.pt")
    assert replayed.config == planned.config
    planned_state, replayed_state = planned.state_dict(), replayed.state_dict()
    assert planned_state.keys() == replayed_state.keys()
    for name, value in planned_state.items():
        assert torch.equal(value, replayed_state[name]), name
    payload = read_checkpoint(out / "checkpoint.pt")
    assert payload["step"] == 0 and payload["prune"]["cuts"] == [r["cuts"] for r in report["rounds"][1:3]]


def test_replay_refuses_a_recovered_run_and_a_foreign_teacher(pruned_tiny, planned_tiny, tmp_path, capsys):
    out = tmp_path / "never"
    # pruned_tiny recovered (--steps 2) between its cuts: its keep lists read changed weights.
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--replay", str(pruned_tiny / "report.json"),
                 "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--steps 2" in err and "--steps 0" in err
    # A report whose MACs the replayed cuts do not reproduce was made from another teacher.
    report = json.loads((planned_tiny / "report.json").read_text())
    report["rounds"][report["best"]]["macs"] += 1
    forged = tmp_path / "report.json"
    forged.write_text(json.dumps(report))
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--replay", str(forged), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "was not made by pruning this checkpoint" in err
    report["rounds"][1]["cuts"] = {"stages.9.block1": 4}
    forged.write_text(json.dumps(report))
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--replay", str(forged), "--out", str(out)]) == 2
    assert "round 1's cuts do not fit this model" in capsys.readouterr().err
    forged.write_text("{not json")
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--replay", str(forged), "--out", str(out)]) == 2
    assert "cannot read the prune report" in capsys.readouterr().err
    assert not out.exists()


def test_prune_without_data_or_with_a_target_on_replay_is_one_line(tmp_path, capsys):
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--out", str(tmp_path / "o"), "--target-macs", "0.5"]) == 2
    assert "needs --data" in capsys.readouterr().err
    assert main(["prune", "--checkpoint", str(TRAINED_TINY), "--replay", "r.json", "--target-macs", "0.5",
                 "--out", str(tmp_path / "o")]) == 2
    assert "takes no --target-macs" in capsys.readouterr().err
