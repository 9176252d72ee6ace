"""`golden check` under emulated aarch64 (benchmarks/arm_emulation.py): the trained tiny's fp32
and INT8 graphs, host against emulated ARM. Slow, and only where an arm64 root set up by that
script is named by E3DPSM_ARM_ROOT (it needs root and qemu-user-static, and takes minutes)."""
from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

import pytest

from _benchmark_scripts import load_benchmark
from _edge_helpers import edge_model, pte_path, tflite_path  # noqa: F401
from _quantize_helpers import int8_dir, int8_test_budget, quant_data, trained_graph  # noqa: F401

ARM_ROOT = os.environ.get("E3DPSM_ARM_ROOT")
STEPS = 20

pytestmark = pytest.mark.slow


def _script():
    return load_benchmark("arm_emulation")


@pytest.fixture(scope="module")
def arm_root() -> Path:
    if not ARM_ROOT:
        pytest.skip("E3DPSM_ARM_ROOT is not set: set up an arm64 root with benchmarks/arm_emulation.py "
                    "(root, qemu-user-static, debootstrap) and name it there")
    root = Path(ARM_ROOT)
    script = _script()
    if not (root / script.STAMP).is_file():
        pytest.skip(f"{root} is not an arm64 root finished by benchmarks/arm_emulation.py (no {script.STAMP})")
    if os.geteuid() != 0:
        pytest.skip("chroot into the arm64 root needs root")
    script.enable_binfmt()
    script.describe_cpu(root)
    script.install_packages(root, litert=importlib.util.find_spec("ai_edge_litert") is not None)
    return root


def test_tiny_checks_under_emulation(arm_root, trained_graph, int8_dir, quant_data) -> None:  # noqa: F811
    """The fp32 graph computes on emulated aarch64 what it computes here (within fp32 parity,
    0.01 mm); the INT8 graph's check runs there against this host's rollout of it; and where
    its codes depart, no segment that is one integer kernel departs on its own (ONNX Runtime's
    integer GEMMs accumulate exactly and requantise alike on both ISAs)."""
    script = _script()
    work = arm_root / script.WORK / f"pytest-{os.getpid()}"
    try:
        graphs = script.stage_graphs([trained_graph, int8_dir / "step_int8.onnx"], work)
        script.host_golden(graphs[0], graphs[1:], str(quant_data), STEPS, work)
        checks = {Path(c["model"]).name: c for c in script.emulated_checks(arm_root, graphs, work)}
        machine = script.emulated_machine(arm_root)
        assert machine["machine"] == "aarch64" and machine["isa"]["kind"] in ("dotprod", "neon")
        fp32 = checks[graphs[0].name]
        assert fp32["status"] == "passed" and fp32["profile"] == "fp32"
        assert all(f["max"] <= 0.01 for f in fp32["host_rollout"].values())
        int8 = checks[graphs[1].name]
        assert int8["profile"] == "int8" and isinstance(int8["same_as_host"], bool)
        assert {"pose"} <= set(int8["host_rollout"])
        trace = script.kernel_traces(arm_root, graphs[1:], work, STEPS)[graphs[1].name]
        assert trace["codes"] > 0 and trace["isa"]["kind"] == machine["isa"]["kind"]
        from e3dpsm.golden.kernel_cut import integer_only

        assert not [d["name"] for d in trace["isolated"] if integer_only(d["segment"])]
    finally:
        shutil.rmtree(work, ignore_errors=True)


def test_tiny_tflite_under_emulation(arm_root, trained_graph, tflite_path, quant_data) -> None:  # noqa: F811
    """The fp32 `.tflite` on emulated aarch64, through XNNPACK (the root's own /proc/cpuinfo and
    CPU lists let cpuinfo start, so LiteRT creates the delegate: at least one partition), within
    fp32 parity (0.01 mm) of this host's ONNX Runtime rollout at every step."""
    script = _script()
    work = arm_root / script.WORK / f"pytest-lt-{os.getpid()}"
    try:
        graphs = script.stage_graphs([trained_graph, tflite_path], work)
        script.host_golden(graphs[0], graphs[1:], str(quant_data), STEPS, work)
        checks = {Path(c["model"]).name: c for c in script.emulated_checks(arm_root, graphs, work)}
        partitions = script.emulated_delegation(arm_root, graphs)
        assert list(partitions) == [graphs[1].name] and partitions[graphs[1].name] >= 1
        tflite = checks[graphs[1].name]
        assert tflite["status"] == "passed" and tflite["profile"] == "fp32"
        assert all(0 < f["max"] <= 0.01 for f in tflite["host_rollout"].values())
    finally:
        shutil.rmtree(work, ignore_errors=True)


def test_tiny_pte_under_emulation(arm_root, trained_graph, pte_path, quant_data) -> None:  # noqa: F811
    """The fp32 `.pte` on emulated aarch64 (ExecuTorch 1.1's runtime there, EXECUTORCH_PINS:
    the newest with a CPU build of torch for aarch64 on PyPI), within fp32 parity (0.01 mm) of
    this host's ONNX Runtime rollout at every step."""
    script = _script()
    script.install_executorch(arm_root)
    work = arm_root / script.WORK / f"pytest-et-{os.getpid()}"
    try:
        graphs = script.stage_graphs([trained_graph, pte_path], work)
        script.host_golden(graphs[0], graphs[1:], str(quant_data), STEPS, work)
        checks = {Path(c["model"]).name: c for c in script.emulated_checks(arm_root, graphs, work)}
        machine = script.emulated_machine(arm_root, executorch=True)
        assert machine["executorch"] == script.EXECUTORCH_PINS[1].split("==")[1]
        pte = checks[graphs[1].name]
        assert pte["status"] == "passed" and pte["profile"] == "fp32"
        assert all(0 < f["max"] <= 0.01 for f in pte["host_rollout"].values())
    finally:
        shutil.rmtree(work, ignore_errors=True)


def test_tiny_weight_only_artifacts_compute_the_hosts_poses_under_emulation(arm_root, trained_graph, tflite_path,
                                                                             edge_model, quant_data,
                                                                             tmp_path) -> None:  # noqa: F811
    """The weight-only INT8 `.tflite` (export/litert_weights8.py) and ONNX graph
    (quantize/weights.py) are held to the same-kind host tolerance on emulated ARM (0.01 mm
    mean, 0.1 at a step) and meet it: float arithmetic, nothing rounded to a code, so ARM's
    kernels part from the host's by round-off alone."""
    from e3dpsm.export.litert_export import LiteRTOptions, embed_contract
    from e3dpsm.export.litert_weights8 import MODE, weight_only_content
    from e3dpsm.quantize.options import QuantizeOptions
    from e3dpsm.quantize.pipeline import quantize_graph

    script = _script()
    work = arm_root / script.WORK / f"pytest-w8-{os.getpid()}"
    try:
        work.mkdir(parents=True)
        weights8 = work / "source" / "step_w8.tflite"
        weights8.parent.mkdir()
        weights8.write_bytes(embed_contract(weight_only_content(tflite_path.read_bytes()), edge_model,
                                            LiteRTOptions(), MODE)[0])
        quantize_graph(trained_graph, quant_data, tmp_path / "qw", QuantizeOptions(mode=MODE, threads=1))
        graphs = script.stage_graphs([trained_graph, weights8, tmp_path / "qw" / "step_int8_weights.onnx"], work)
        script.host_golden(graphs[0], graphs[1:], str(quant_data), STEPS, work)
        checks = {Path(c["model"]).name: c for c in script.emulated_checks(arm_root, graphs, work)}
        for graph in graphs[1:]:
            check = checks[graph.name]
            assert check["profile"] == "int8" and check["same_as_host"] is True, graph.name
            assert script.arm_ready(check, None)["ready"]
            for figures in check["host_rollout"].values():
                assert figures["mean_limit"] == 0.01 and figures["step_limit"] == 0.1 and figures["max"] <= 0.01
    finally:
        shutil.rmtree(work, ignore_errors=True)


def test_the_pte_trace_under_emulation_runs_or_traces_the_taps_program(arm_root) -> None:
    """pte_traces on a toy INT8-labelled `.pte` whose arithmetic is float (the same bits on any
    ISA): with the root's ExecuTorch built with the event tracer, the two traces never part;
    PyPI's aarch64 ExecuTorch 1.1.0 has none, so the taps program beside the first toy is traced
    instead (its taps never part either), and the second toy, without one, is not traced, for
    the reason the trace gives."""
    from _golden_fakes import golden_writer
    from _toy_pte import TAPS, toy_pte

    script = _script()
    script.install_executorch(arm_root)
    script.install_packages(arm_root, executorch=True)
    work = arm_root / script.WORK / f"pytest-pte-trace-{os.getpid()}"
    try:
        work.mkdir(parents=True)
        for name in ("toy.pte", "bare.pte"):
            (work / name).write_bytes(toy_pte(precision="int8", delegated=True))
        (work / "toy_taps.pte").write_bytes(toy_pte(precision="int8", delegated=True, taps=True))
        writer, manifest = golden_writer(4)
        writer.write(work / "golden", {**manifest, "window_ms": 20.0, "joints": [f"j{i}" for i in range(16)]})
        traces = script.pte_traces(arm_root, [work / "toy.pte", work / "bare.pte"], work, 4)
        if "outputs" in traces["toy.pte"]:  # a root whose ExecuTorch has the event tracer
            assert traces["toy.pte"]["first_step"] is None and traces["bare.pte"]["first_step"] is None
        else:
            taps = traces["toy.pte"]
            assert taps["taps"] == len(TAPS) and taps["steps"] == 4 and taps["first_step"] is None
            assert "asimd" in taps["device_isa"]["flags"] and "asimd" not in taps["host_isa"]["flags"]
            reason = traces["bare.pte"]["not_traced"]
            assert "records no ETDump" in reason and "EXECUTORCH_ENABLE_EVENT_TRACER" in reason
            assert reason.endswith("; and no bare_taps.pte beside it to trace instead (e3dpsm convert executorch "
                                   "--quantize int8 --taps)")
    finally:
        shutil.rmtree(work, ignore_errors=True)
