"""`quantize --budget-reference lowest`: the budget relative to the lowest fp32 MPJPE of any
one held-out or calibration sequence, checked against numpy over the fp32 graph's streams."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from _quantize_helpers import RUNTIME

from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import ConfigError
from e3dpsm.quantize import QuantizeOptions, quantize_graph
from e3dpsm.quantize.holdout import HoldoutSet


def numpy_mpjpe(pred: np.ndarray, gt: np.ndarray) -> float:
    return float(np.linalg.norm(pred.astype(np.float64) - gt, axis=-1).mean())


def _holdout(errors_mm: list[float], frames: int = 5) -> HoldoutSet:
    """Sequences whose fp32 poses sit `e` mm from the ground truth along x, every joint."""
    gt = [np.zeros((frames, 16, 3), np.float32) for _ in errors_mm]
    fp32 = [{"pose": g + np.array([e, 0, 0], np.float32)} for g, e in zip(gt, errors_mm)]
    return HoldoutSet([np.zeros((frames, 1), np.float32)] * len(gt), gt, fp32, 20.0)


def test_lowest_reference_is_the_best_sequence_of_any_set() -> None:
    held = _holdout([300.0, 200.0])
    assert held.budget_mpjpe == pytest.approx(250.0)            # pooled by default
    lowest = held.with_lowest_reference(_holdout([120.0, 90.0]))
    assert lowest.budget_mpjpe == pytest.approx(90.0)           # a calibration sequence's
    assert lowest.fp32_mpjpe == pytest.approx(250.0)            # the MPJPE itself unchanged
    assert lowest.head(3).budget_mpjpe == pytest.approx(90.0)   # the ranking trials keep it
    assert held.with_lowest_reference().budget_mpjpe == pytest.approx(200.0)


def test_unknown_budget_reference_is_refused() -> None:
    with pytest.raises(ConfigError, match="budget reference"):
        QuantizeOptions(budget_reference="median")


def test_quantize_budgets_against_the_lowest_sequence(trained_graph: Path, quant_data: Path, tmp_path: Path) -> None:
    from e3dpsm.runtime import StepSession
    from e3dpsm.validation.streams import onnx_stream_outputs

    frames = 20
    report = quantize_graph(trained_graph, quant_data, tmp_path / "q", QuantizeOptions(
        mode="int8", exclude="recurrent", frames=16, holdout_frames=frames, budget_reference="lowest",
        **RUNTIME))
    held = report["holdout"]
    data = PreparedData.open(quant_data)
    session = StepSession(trained_graph)
    per_sequence = {}
    for split in ("val", "train"):
        for seq in data.split(split):
            poses = onnx_stream_outputs(session, np.asarray(seq.lnes[:frames], np.float32), 20.0)["pose"]
            per_sequence[seq.name] = numpy_mpjpe(poses, np.asarray(seq.j3d_mm[:frames]))
    assert len(per_sequence) >= 3
    val = {s.name for s in data.split("val")}
    assert min(v for k, v in per_sequence.items() if k not in val) < min(per_sequence[k] for k in val), \
        "the fixture's calibration sequences no longer include one easier than val: the test cannot tell " \
        "'lowest of val and train' from 'val only'"
    assert held["budget_reference"] == "lowest"
    assert held["budget_mpjpe_mm"] == pytest.approx(min(per_sequence.values()), rel=1e-5)
    assert held["budget_mpjpe_mm"] < held["fp32_mpjpe_mm"]  # the fixture's sequences differ
    assert held["bound_pct"] == pytest.approx(
        100.0 * max(held["deviation_by_output_mm"].values()) / held["budget_mpjpe_mm"], rel=1e-9)
    assert "`--budget-reference lowest`" in (tmp_path / "q" / "report.md").read_text()
