"""Evaluation core on hand-made predictions, and `e3dpsm evaluate` end to end."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.cli import main
from e3dpsm.evaluation.core import evaluate_predictions
from e3dpsm.metrics import mpjpe




def _case() -> dict:
    """Two sequences; action 0 has 6 frames offset by 10 mm, action 1 has 2 frames offset
    by 40 mm, 2 frames are unlabelled (-1) with 20 mm."""
    n, j = 10, 16
    gt = np.zeros((n, j, 3))
    gt[:, :, 0] = np.arange(n)[:, None] * 5.0  # constant velocity, 5 mm/frame
    offsets = np.array([10.0] * 6 + [40.0] * 2 + [20.0] * 2)
    pred = gt.copy()
    pred[:, :, 1] += offsets[:, None]
    action = np.array([0] * 6 + [1] * 2 + [-1] * 2)
    visible = np.ones((n, j), dtype=np.uint8)
    visible[:, 0] = 0
    pred[:, 0, 1] += 100.0  # occluded joint is much worse
    sequence_ids = np.array([0] * 7 + [1] * 3)
    return dict(pred_mm=pred, gt_mm=gt, visible=visible, action=action, action_names=["walk", "crouch"],
                sequence_ids=sequence_ids, sequence_names=["a", "b"])


def test_totals_are_unweighted_means_of_action_means() -> None:
    case = _case()
    res = evaluate_predictions(**case)
    assert set(res["per_action"]) == {"walk", "crouch", "unknown"}
    per = {k: v["mpjpe"] for k, v in res["per_action"].items()}
    assert per["walk"] == pytest.approx(10.0 + 100.0 / 16)
    assert per["crouch"] == pytest.approx(40.0 + 100.0 / 16)
    assert res["totals"]["mpjpe"] == pytest.approx(np.mean(list(per.values())))
    assert res["frame_weighted"]["mpjpe"] == pytest.approx(mpjpe(case["pred_mm"], case["gt_mm"]))
    assert res["per_action"]["walk"]["mpjpe_occluded"] == pytest.approx(110.0)


def test_smoothness_never_pairs_frames_across_sequences() -> None:
    case = _case()
    # Within each sequence the offset changes only at the action boundaries: frames 6->7
    # (seq a: 10 -> 40 mm) and 8->9 (seq b: 40 -> 20 mm). Frame 7 starts sequence b.
    res = evaluate_predictions(**case)
    # Speeds: gt 5 mm/frame; pred at the 6->7 jump sqrt(5^2 + 30^2).
    jump = abs(np.hypot(5.0, 30.0) - 5.0)
    assert res["per_action"]["crouch"]["e_smooth"] == pytest.approx(jump)  # only the pair 5->6 is valid
    assert res["per_sequence"]["b"]["frames"] == 3


def test_shape_mismatch_is_rejected() -> None:
    case = _case()
    case["action"] = case["action"][:-1]
    with pytest.raises(ValueError, match="frames"):
        evaluate_predictions(**case)


@pytest.mark.parametrize("mode", ["--causal", "--non-causal"])
def test_evaluate_cli_writes_consistent_report(training_runs: dict[str, Path], prepared_small: Path,
                                               tmp_path: Path, mode: str) -> None:
    out = tmp_path / "ev"
    rc = main(["evaluate", "--checkpoint", str(training_runs["full"] / "checkpoint.pt"), "--data",
               str(prepared_small), "--out", str(out), "--split", "all", mode, "--no-progress"])
    assert rc == 0
    report = json.loads((out / "metrics.json").read_text())
    arrays = np.load(out / "predictions.npz")
    assert report["frame_weighted"]["mpjpe"] == pytest.approx(mpjpe(arrays["pred_mm"], arrays["gt_mm"]), rel=1e-6)
    assert report["frames"] == arrays["gt_mm"].shape[0]
    assert "| total |" in (out / "metrics.md").read_text()
    assert (out / "per_joint.png").stat().st_size > 1000
    assert main(["evaluate", "--checkpoint", str(training_runs["full"] / "checkpoint.pt"), "--data",
                 str(prepared_small), "--out", str(out)]) == 2  # exists, no --force


def _ablation_row(mpjpe: float, e_smooth: float, over_time: list[float], non_causal: float) -> dict:
    causal = {"mpjpe": mpjpe, "e_smooth": e_smooth, "error_over_time": over_time}
    return {"causal": causal, "non_causal": {"mpjpe": non_causal, "e_smooth": e_smooth, "error_over_time": over_time}}


def test_paper_claims_hold_and_fail_on_hand_made_ablation_rows() -> None:
    from e3dpsm.evaluation.ablation import paper_claims

    rows = {
        "full": _ablation_row(100.0, 4.0, [100.0, 100.0], non_causal=98.0),
        "naive_fusion": _ablation_row(300.0, 3.0, [100.0, 500.0], non_causal=290.0),
        "direct_only": _ablation_row(105.0, 8.0, [105.0, 105.0], non_causal=104.0),
    }
    assert [c["holds"] for c in paper_claims(rows)] == [True, True, True, True, True]
    assert paper_claims(rows)[2]["figures"]["ratio"] == pytest.approx(2.0)
    assert paper_claims(rows)[3]["figures"] == {"full": 100.0, "direct_only": 105.0}
    assert paper_claims(rows)[4]["figures"]["gap_pct"] == pytest.approx(100.0 * 2.0 / 98.0)

    rows["direct_only"] = _ablation_row(105.0, 5.0, [105.0, 105.0], non_causal=104.0)  # only 1.25x smoother
    rows["naive_fusion"] = _ablation_row(90.0, 3.0, [100.0, 90.0], non_causal=90.0)    # no drift, better
    rows["full"] = _ablation_row(100.0, 4.0, [100.0, 100.0], non_causal=80.0)           # 25% causal gap
    rows["direct_only"]["causal"]["mpjpe"] = 99.0                                      # direct-only more accurate
    assert [c["holds"] for c in paper_claims(rows)] == [False, False, False, False, False]
    rows["static_fusion"] = _ablation_row(100.0, 4.0, [100.0, 100.0], non_causal=100.0)  # a tie is no win
    rows["no_ssm"] = _ablation_row(120.0, 4.0, [120.0, 120.0], non_causal=120.0)
    claims = {c["claim"].split(" (")[0]: c["holds"] for c in paper_claims(rows)}
    assert claims["learned fusion beats static fusion"] is False
    assert claims["the SSM blocks lower MPJPE"] is True
    assert paper_claims({"naive_fusion": rows["naive_fusion"]}) == []


def test_ablation_command_trains_evaluates_and_checks_the_claims(prepared_small: Path, tmp_path: Path) -> None:
    out = tmp_path / "abl"
    rc = main(["ablation", "--variant", "tiny", "--data", str(prepared_small), "--split", "all",
               "--test-data", str(prepared_small), "--out", str(out), "--ablations", "full", "naive_fusion",
               "direct_only", "--steps", "2", "--seq-len", "3", "--batch-size", "2", "--threads", "2"])
    assert rc == 0
    table = json.loads((out / "ablation.json").read_text())
    assert list(table["rows"]) == ["full", "naive_fusion", "direct_only"]
    assert table["rows"]["naive_fusion"]["overrides"] == {"fusion": "naive"}
    full = table["rows"]["full"]
    assert full["causal"]["mpjpe"] > 0 and full["non_causal"]["mpjpe"] > 0
    claims = {c["claim"]: c for c in table["claims"]}
    assert len(claims) == 5  # static fusion and no SSM were not run: their claims are left out
    smooth = next(c for name, c in claims.items() if "e_smooth" in name)
    assert smooth["figures"]["ratio"] == pytest.approx(
        table["rows"]["direct_only"]["causal"]["e_smooth"] / full["causal"]["e_smooth"])
    ordering = next(c for name, c in claims.items() if name.startswith("learned fusion beats direct-only"))
    direct_mpjpe = table["rows"]["direct_only"]["causal"]["mpjpe"]
    assert ordering["figures"] == {"full": full["causal"]["mpjpe"], "direct_only": direct_mpjpe}
    assert ordering["holds"] == (full["causal"]["mpjpe"] < direct_mpjpe)
    md = (out / "ablation.md").read_text()
    assert "The paper's claims" in md and "naive_fusion (causal)" in md
