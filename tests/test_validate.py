"""e3dpsm validate: streams, metrics against the shared formulas, outputs, bad input."""
from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from _quantize_helpers import fast, mean_pose_model
from e3dpsm.checkpoint import save_checkpoint
from e3dpsm.cli import main
from e3dpsm.data.prepared import PreparedData
from e3dpsm.errors import DataError
from e3dpsm.joints import JOINT_NAMES
from e3dpsm.metrics import e_smooth, mpjpe
from e3dpsm.quantize import quantize_graph
from e3dpsm.runtime import StepSession
from e3dpsm.validation import onnx_stream, validate_variants

FRAMES = 30


@pytest.fixture(scope="session")
def fp16_graph(tmp_path_factory, tiny_graph, quant_data):  # noqa: F811
    out = tmp_path_factory.mktemp("v") / "fp16"
    quantize_graph(tiny_graph, quant_data, out, fast(mode="fp16", exclude="recurrent", holdout_frames=10))
    return out / "step_fp16.onnx"


def test_validate_table_matches_the_shared_metrics(tmp_path, capsys, tiny_graph, fp16_graph, quant_data):  # noqa: F811
    model = mean_pose_model(quant_data)
    save_checkpoint(tmp_path / "tiny.pt", model)
    code = main(["validate", "--models", str(fp16_graph), str(tiny_graph), "--checkpoint", str(tmp_path / "tiny.pt"),
                 "--data", str(quant_data), "--out", str(tmp_path / "val"), "--frames", str(FRAMES)])
    assert code == 0
    report = json.loads((tmp_path / "val" / "report.json").read_text())
    rows = {r["precision"] + "/" + r["kind"]: r for r in report["rows"]}
    assert report["reference"] == rows["fp32/onnx"]["variant"]  # the fp32 graph, though listed second
    ref = rows["fp32/onnx"]
    assert ref["delta_mpjpe_mm"] == 0.0 and ref["deviation_from_reference_mm"] == 0.0

    seq = PreparedData.open(quant_data).split("test")[0]
    poses = onnx_stream(StepSession(tiny_graph), seq.lnes, 20.0, FRAMES)
    gt = seq.j3d_mm[:FRAMES]
    assert ref["mpjpe_mm"] == pytest.approx(mpjpe(poses, gt), rel=1e-6)
    assert ref["e_smooth_mm"] == pytest.approx(e_smooth(poses, gt), rel=1e-6)
    occluded = seq.visible[:FRAMES] == 0
    if occluded.any():
        assert ref["occluded_mpjpe_mm"] == pytest.approx(mpjpe(poses, gt, occluded), rel=1e-6)
    # PyTorch and fp32 ONNX agree to float round-off; fp16 within 0.1 % of the MPJPE.
    assert rows["fp32/pytorch"]["deviation_from_reference_mm"] < 0.05
    assert abs(rows["fp16/onnx"]["delta_mpjpe_pct"]) < 0.1
    assert rows["fp16/onnx"]["delta_mpjpe_mm"] == pytest.approx(rows["fp16/onnx"]["mpjpe_mm"] - ref["mpjpe_mm"])

    with open(tmp_path / "val" / "validation.csv", newline="") as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 3 and f"mpjpe_{JOINT_NAMES[-1]}" in table[0]
    per_joint = [float(table[1][f"mpjpe_{j}"]) for j in JOINT_NAMES]
    assert np.mean(per_joint) == pytest.approx(float(table[1]["mpjpe_mm"]), rel=1e-6)
    md = (tmp_path / "val" / "validation.md").read_text()
    assert md.count("\n|") == 5 and "PA-MPJPE" in md  # header, rule, three variants
    assert (tmp_path / "val" / "validation.png").read_bytes()[:4] == b"\x89PNG"
    assert "MPJPE" in capsys.readouterr().out


def test_validate_refuses_mismatched_data(tmp_path, capsys, quant_data):  # noqa: F811
    from e3dpsm.export import export_step

    graph = export_step(mean_pose_model(quant_data, height=96, width=128), tmp_path / "small_frames.onnx")
    with pytest.raises(DataError, match="96 x 128"):
        validate_variants([graph], quant_data, frames=FRAMES)
    code = main(["validate", "--models", str(graph), "--data", str(quant_data), "--out", str(tmp_path / "v"),
                 "--window-ms", "50"])
    assert code == 2 and "50 ms" in capsys.readouterr().err
    assert not (tmp_path / "v").exists()
    with pytest.raises(DataError, match="no sequences in split 'nope'"):
        validate_variants([graph], quant_data, split="nope")
