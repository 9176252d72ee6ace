"""The pipeline index's line on how far the INT8 budget carried to unseen data."""
from __future__ import annotations

import json

from e3dpsm.pipeline.report import budget_gap


def _check(folder, runtime: str, means: list[float], scale_mm: float) -> None:
    folder.mkdir(parents=True)
    tensors = [{"kind": "output", "name": n, "mean": m} for n, m in zip(("pose", "pose_direct", "pose_delta"), means)]
    tensors.append({"kind": "state", "name": "fusion_pose", "mean": None})
    (folder / "check.json").write_text(json.dumps({"runtime": runtime, "scale_mm": scale_mm, "tensors": tensors}))


def test_gap_between_the_search_and_the_golden_checks(tmp_path) -> None:
    report = {"holdout": {"bound_pct": 0.5, "split": "val", "frames": 100}, "quantization": {"budget_pct": 1.0}}
    # worst output / scale: 1.5 / 200 = 0.75% on ORT (1.5x the search's 0.5%), 0.25 / 200 on OpenVINO
    _check(tmp_path / "golden/checks/step_int8-onnxruntime", "onnxruntime", [1.0, 1.5, 0.2], 200.0)
    _check(tmp_path / "golden/checks/step_int8-openvino", "openvino", [0.25, 0.1, 0.05], 200.0)
    _check(tmp_path / "golden/checks/step_fp16-onnxruntime", "onnxruntime", [9.0, 9.0, 9.0], 200.0)  # not int8
    line = budget_gap(tmp_path, report)
    assert "measured 0.500% on `val` (100 frames)" in line
    assert "0.750% on onnxruntime (1.50x), 0.125% on openvino (0.25x)" in line and line.endswith("budget 1%.")


def test_no_golden_check_no_line(tmp_path) -> None:
    assert budget_gap(tmp_path, {"holdout": {"bound_pct": 0.5, "split": "val", "frames": 100}}) is None
    assert budget_gap(tmp_path, {}) is None


def test_index_gives_the_serve_command_for_the_held_out_sequence(tmp_path) -> None:
    import shlex

    from e3dpsm.pipeline.report import serve_command, write_index

    out = tmp_path / "my run"  # a space: the command must stay one pasteable line
    assert serve_command(out) is None  # nothing exported yet: no line
    (out / "export").mkdir(parents=True)
    (out / "export/step.onnx").write_bytes(b"graph")
    (out / "data/seq_0002").mkdir(parents=True)
    (out / "data/seq_0002/events.h5").write_bytes(b"events")
    (out / "data/test.txt").write_text("seq_0002\nseq_0005\n")
    write_index(out, {"variant": "tiny", "seed": 1, "window_ms": 20, "threads": 2}, [])
    text = (out / "report/index.md").read_text()
    line = next(line for line in text.splitlines() if "e3dpsm serve" in line and "--model" in line)
    argv = shlex.split(line.strip("`"))
    assert argv == ["e3dpsm", "serve", "--model", str((out / "export/step.onnx").resolve()), "--source",
                    str((out / "data/seq_0002/events.h5").resolve()), "--threads", "2"]
    assert "e3dpsm serve" in (out / "report/index.html").read_text()


def test_gap_names_a_lowest_budget_reference(tmp_path) -> None:
    report = {"holdout": {"bound_pct": 0.8, "split": "val", "frames": 100, "budget_reference": "lowest",
                          "budget_mpjpe_mm": 101.04, "fp32_mpjpe_mm": 352.08}, "quantization": {"budget_pct": 1.0}}
    _check(tmp_path / "golden/checks/step_int8-onnxruntime", "onnxruntime", [0.3, 0.6, 0.1], 170.0)
    line = budget_gap(tmp_path, report)
    assert "(100 frames, relative to 101.0 mm, the lowest fp32 MPJPE of any sequence it measured; `val` pooled: " \
           "352.1 mm)" in line
    assert "0.353% on onnxruntime (0.44x)" in line


def test_gap_names_each_runtime_the_search_measured_on(tmp_path) -> None:
    report = {"holdout": {"bound_pct": 0.4614, "split": "val", "frames": 100,
                          "bound_pct_by_runtime": {"onnxruntime": 0.4614, "openvino": 0.4370}},
              "quantization": {"budget_pct": 1.0}}
    _check(tmp_path / "golden/checks/step_int8-openvino", "openvino", [0.3, 0.4, 0.1], 200.0)
    line = budget_gap(tmp_path, report)
    assert "measured 0.461% on `val` (the worse of onnxruntime 0.461%, openvino 0.437%; 100 frames)" in line
    report["holdout"]["bound_pct_by_runtime"] = {"onnxruntime": 0.4614}  # one runtime: nothing to name
    assert "measured 0.461% on `val` (100 frames)" in budget_gap(tmp_path, report)
