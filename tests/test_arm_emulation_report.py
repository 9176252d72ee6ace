"""benchmarks/arm_emulation.py's verdicts and report, on hand-made checks and traces (no arm64
root needed): which trace names what departs, and where each kind lands in the report."""
from __future__ import annotations

from pathlib import Path

from _benchmark_scripts import load_benchmark

SCRIPT = load_benchmark("arm_emulation")
CODE = {"name": "e3dpsm_code_11", "tensor_name": "s0t1521", "operator": 182, "fed_by": "ADD",
        "read_by": ["FULLY_CONNECTED"], "first_step": 9}
CODE_TRACE = {"steps": 60, "codes": 71, "apart_by_end": 58, "first_step": 9, "first_departures": [CODE],
              "per_code": [CODE]}
PARTITION = {"instruction": 19, "output": 3, "kernel": "DELEGATE_CALL", "operators": 3, "position": 21,
             "operator_names": ["Convert (NC) #1", "Convolution (NHWC, QC8) IGEMM #1", "Add (ND) #1"], "first_step": 2}
PTE_TRACE = {"steps": 60, "outputs": 291, "apart_by_end": 200, "first_step": 2, "first_departures": [PARTITION],
             "per_output": [PARTITION]}
KERNEL_TRACE = {"codes": 149, "first_departures": ["q28"], "propagated": [{"first_step": 3}], "isolated_identical": 148,
                "isolated": [{"name": "q28", "segment": ["LayerNormalization"], "first_step": 3, "steps_apart": 3,
                              "apart": 3, "elements": 12288, "max_codes": 1}]}


def _check(model: str, same: bool | None) -> dict:
    return {"model": model, "status": "failed", "same_as_host": same, "profile": "int8", "host_rollout": {
        "pose": {"measure": "host_distance_mm", "max": 2.4, "mean": 1.34, "passed": False, "mean_limit": 0.5,
                 "step_limit": 5.0}}}


def test_a_tflite_is_named_by_its_code_trace_an_onnx_graph_by_its_kernel_trace():
    tflite = SCRIPT.arm_ready(_check("lt8.tflite", False), None, CODE_TRACE)
    assert tflite == {"ready": False, "first_step": 9,
                      "departs_first": ["e3dpsm_code_11 (operator 182: ADD -> QUANTIZE -> FULLY_CONNECTED)"]}
    onnx = SCRIPT.arm_ready(_check("q.onnx", False), KERNEL_TRACE)
    assert onnx["departs_first"] == ["q28"] and onnx["responsible"][0]["segment"] == ["LayerNormalization"]
    assert SCRIPT.arm_ready(_check("lt8.tflite", True), None, CODE_TRACE) == {"ready": True}
    untraced = {"not_traced": "this ExecuTorch runtime (executorch 1.1.0) records no ETDump: ..."}
    assert SCRIPT.arm_ready(_check("et8.pte", False), None, untraced) == {"ready": False, **untraced}
    pte = SCRIPT.arm_ready(_check("et8.pte", False), None, PTE_TRACE)
    assert pte == {"ready": False, "first_step": 2, "departs_first": [
        "instruction 19 (XNNPACK partition of 3 operators, 1 of them 8-bit; value 3)"]}


def test_the_report_gives_each_trace_kind_its_section():
    machine = {"qemu": "qemu 10", "machine": "aarch64", "python": "3.11", "isa": {"kind": "neon", "flags": ["asimd"]},
               "onnxruntime": "1.31.1", "numpy": "2.4.6", "ai_edge_litert": "2.3.0"}
    checks = [{**_check("q.onnx", False), "arm_ready": {"ready": False}},
              {**_check("lt8.tflite", False), "arm_ready": {"ready": False}, "xnnpack_partitions": 6}]
    report = {"steps": 60, "load_average": 0.5, "host": {"isa": {"kind": "vnni", "flags": ["avx2"]},
                                                         "onnxruntime": "1.31.1", "numpy": "2.4.6"},
              "runs": [{"cpu": "cortex-a72", "emulated": machine, "checks": checks,
                        "traces": {"q.onnx": KERNEL_TRACE},
                        "code_traces": {"lt8.tflite": CODE_TRACE, "et8.pte": PTE_TRACE,
                                        "old.pte": {"not_traced": "no ETDump here"}}}]}
    text = SCRIPT.markdown(report)
    assert "## lt8.tflite on `cortex-a72`: where the codes part (71 code tensors)" in text
    assert "code tensors part first at step 9, first in graph order e3dpsm_code_11" in text
    assert "## q.onnx on `cortex-a72`: where the codes depart (149 quantised activations)" in text
    assert ("## et8.pte on `cortex-a72`: where the instruction outputs part (291 values ETDump logs per step)\n\n"
            "instruction outputs part first at step 2, first in execution order instruction 19 (XNNPACK partition "
            "of 3 operators, 1 of them 8-bit; value 3); 200 of 291 instruction outputs apart by step 59.") in text
    assert "## old.pte on `cortex-a72`: not traced\n\nno ETDump here." in text
    assert "| q28 | LayerNormalization | 3 | 3 | 3 / 12288 | 1 |" in text
    assert "XNNPACK partitions LiteRT made on `cortex-a72` (0 would mean its builtin kernels ran): lt8.tflite 6." in text
    assert "| cortex-a72 | lt8.tflite | int8 | pose | host_distance_mm | 2.4 | 1.34 | 0.5 / 5.0 | **over** | **no** |" in text


def test_pte_programs_are_skipped_with_the_reason_where_torch_cannot_start(monkeypatch) -> None:
    """The root's torch needs ARMv8.2: an illegal instruction (SIGILL, -4) says so; any other
    failure gives its exit status; a clean import lets the programs run."""
    import subprocess
    from pathlib import Path

    asked = []

    def fake(root, cmd, cpu, executorch, code=0, stderr=""):
        asked.append((cmd, executorch))
        return subprocess.CompletedProcess(cmd, code, "", stderr)

    cpu = SCRIPT.EmulatedCPU("cortex-a72")
    monkeypatch.setattr(SCRIPT, "_emulated_process", fake)
    assert SCRIPT.executorch_refusal(Path("/root"), cpu) is None
    assert asked == [(["python3", "-c", "import torch, executorch.runtime"], True)]
    monkeypatch.setattr(SCRIPT, "_emulated_process", lambda *a: fake(*a, code=-4))
    assert SCRIPT.executorch_refusal(Path("/root"), cpu) == (
        "torch 2.10.0 for aarch64 dies of an illegal instruction on `cortex-a72`")
    monkeypatch.setattr(SCRIPT, "_emulated_process", lambda *a: fake(*a, code=132, stderr="Illegal instruction"))
    assert SCRIPT.executorch_refusal(Path("/root"), cpu).endswith("dies of an illegal instruction on `cortex-a72`")
    monkeypatch.setattr(SCRIPT, "_emulated_process", lambda *a: fake(*a, code=1))
    assert SCRIPT.executorch_refusal(Path("/root"), cpu) == (
        "`import torch, executorch.runtime` exited 1 on `cortex-a72`")
    assert SCRIPT.has_pte([Path("a.onnx"), Path("b.pte")]) and not SCRIPT.has_pte([Path("a.onnx"), Path("b.tflite")])


def test_only_int8_step_programs_are_traced_and_a_taps_program_stands_in_without_an_event_tracer(
        tmp_path, monkeypatch) -> None:
    """pte_traces without an arm64 root: the emulated `pte_trace record` answers as PyPI's aarch64
    ExecuTorch does (no event tracer, exit 3). An fp32 program and a taps program passed among the
    graphs are not traced; an INT8 program with its `_taps.pte` beside it is traced by its taps,
    one without is reported not traced, saying how to write one."""
    import subprocess

    import pytest

    pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")
    from _toy_pte import toy_pte
    from e3dpsm.golden.pte_trace import NO_EVENT_TRACER_EXIT

    int8 = toy_pte(precision="int8")
    for name, content in {"fp.pte": toy_pte(), "toy.pte": int8, "toy_taps.pte": toy_pte(precision="int8", taps=True),
                          "bare.pte": int8}.items():
        (tmp_path / name).write_bytes(content)
    recorded, tapped = [], []

    def emulated(root, cmd, cpu, executorch):
        recorded.append(Path(cmd[4]).name)
        return subprocess.CompletedProcess(cmd, NO_EVENT_TRACER_EXIT, "", "pte_trace: error: no ETDump here\n")

    def taps_trace(root, taps, folder, work, steps, cpu, host_python):
        tapped.append((taps.name, folder.name, steps))
        return {"first_step": 4}

    monkeypatch.setattr(SCRIPT, "_emulated_process", emulated)
    monkeypatch.setattr(SCRIPT, "taps_trace", taps_trace)
    graphs = [tmp_path / n for n in ("step.onnx", "fp.pte", "toy.pte", "toy_taps.pte", "bare.pte")]
    traces = SCRIPT.pte_traces(tmp_path, graphs, tmp_path / "work", 7)
    assert recorded == ["toy.pte", "bare.pte"]
    assert tapped == [("toy_taps.pte", "toy", 7)]
    assert traces == {"toy.pte": {"first_step": 4}, "bare.pte": {"not_traced": (
        "no ETDump here; and no bare_taps.pte beside it to trace instead (e3dpsm convert executorch --quantize "
        "int8 --taps)")}}
