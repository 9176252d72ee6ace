"""The pipeline index: the INT8 verdict on top, its budget table, the serve command."""
from __future__ import annotations

import json

from e3dpsm.pipeline.report import edge_section, int8_section, write_index


def _quantize_report() -> dict:
    metric = lambda name, change, upper, limit: {"name": name, "change_pct": change, "upper_pct": upper,  # noqa: E731
                                                 "limit_pct": limit, "within": upper <= limit}
    metrics = {"mpjpe": metric("mpjpe", 0.2, 0.6, 1.0), "pa_mpjpe": metric("pa_mpjpe", -0.1, 0.3, 1.0),
               "jitter": metric("jitter", 4.0, 5.5, 5.0)}
    return {"verdict": {"headline": "Verdict: over budget, do not ship: jitter ..."},
            "check": {"data": "prepared/test", "frames": 200, "within": False,
                      "by_runtime": {"openvino": {"metrics": metrics}}}}


def test_int8_section_lists_each_metric_against_its_limit() -> None:
    lines = int8_section(_quantize_report())
    assert lines[0] == "## INT8 against its budget" and "On 200 held-out frames (prepared/test)" in lines[2]
    assert "| openvino | mpjpe | +0.200 | +0.600 | +1 | yes |" in lines
    assert "| openvino | jitter | +4.000 | +5.500 | +5 | **no** |" in lines
    assert int8_section({}) == [] and int8_section({"check": {"by_runtime": {}}}) == []


def test_index_opens_with_the_int8_verdict(tmp_path) -> None:
    (tmp_path / "quantize/int8").mkdir(parents=True)
    (tmp_path / "quantize/int8/report.json").write_text(json.dumps(_quantize_report()))
    write_index(tmp_path, {"variant": "tiny", "seed": 1, "window_ms": 20, "threads": 2}, [])
    text = (tmp_path / "report/index.md").read_text().splitlines()
    assert text[2] == "**Verdict: over budget, do not ship: jitter ...**"
    assert "## INT8 against its budget" in text


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




def test_the_edge_section_reads_each_conversion_record_and_the_check(tmp_path) -> None:
    assert edge_section(tmp_path) == []
    (tmp_path / "edge/executorch").mkdir(parents=True)
    (tmp_path / "edge/executorch/convert.json").write_text(json.dumps({
        "bytes": 6_043_210, "seconds": {"total": 108.5}, "options": {"attention_form": "grid_sample"},
        "delegation": {"delegated_share": 0.99712}}))
    lines = edge_section(tmp_path)
    assert lines[0] == "## Edge artifacts"
    assert lines[-2:] == ["| [edge/executorch/step.pte](../edge/executorch/step.pte) | 6.04 | 108 | grid_sample | "
                          "XNNPACK runs 99.7% of the MACs |", ""]
    (tmp_path / "edge/litert").mkdir(parents=True)
    (tmp_path / "edge/litert/convert.json").write_text(json.dumps({
        "bytes": 6_130_000, "seconds": {"total": 70.2}, "options": {"attention_form": "gather"},
        "ops": {"xnnpack_partitions": 6}}))
    (tmp_path / "edge/checks").mkdir()
    (tmp_path / "edge/checks/summary.md").write_text("| model | status |\n|---|---|\n| step.pte | passed |\n")
    write_index(tmp_path, {"variant": "small", "seed": 0, "window_ms": 20, "threads": 2}, [])
    text = (tmp_path / "report/index.md").read_text()
    section = text[text.index("## Edge artifacts"):]
    assert ("| [edge/litert/step.tflite](../edge/litert/step.tflite) | 6.13 | 70 | gather | 6 XNNPACK partitions |\n\n"
            "| model | status |\n|---|---|\n| step.pte | passed |\n") in section
    assert section.index("executorch/step.pte") < section.index("litert/step.tflite")


def test_the_edge_section_whole_with_the_litert_stage_alone(tmp_path) -> None:
    (tmp_path / "edge/litert").mkdir(parents=True)
    (tmp_path / "edge/litert/convert.json").write_text(json.dumps({
        "bytes": 5_000_000, "seconds": {"total": 9.4}, "ops": {"xnnpack_partitions": 6}}))  # a record without options
    (tmp_path / "edge/checks").mkdir()
    (tmp_path / "edge/checks/summary.md").write_text("| check |\n|---|\n\n")
    assert edge_section(tmp_path) == [
        "## Edge artifacts", "",
        "The checkpoint converted for the edge runtimes (`e3dpsm convert`, fp32; docs/edge.md in the repository), "
        "each checked against the golden rollout with its own runtime carrying the states, and timed in the profile "
        "beside the ONNX graphs.", "",
        "| artifact | size (MB) | conversion (s) | attention form | backend |", "|---|---:|---:|---|---|",
        "| [edge/litert/step.tflite](../edge/litert/step.tflite) | 5.00 | 9 | - | 6 XNNPACK partitions |", "",
        "| check |\n|---|", ""]
