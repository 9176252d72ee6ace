"""Targets, devices, latency bookkeeping, memory sampling and the profile / model-info commands."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import pytest

from e3dpsm.cli import main
from e3dpsm.errors import ConfigError
from e3dpsm.profiles.devices import Device, bytes_per_step, load_devices, roofline
from e3dpsm.profiles.inputs import moving_edge_frames
from e3dpsm.profiles.latency import matmul_peak_gflops, measure_side_by_side
from e3dpsm.profiles.memory import RssSampler
from e3dpsm.profiles.targets import Target, availability, load_targets, select_targets

REQUIRED_TARGETS = {
    ("torch", "cpu", "fp32"), ("onnxruntime", "CPUExecutionProvider", "fp32"),
    ("onnxruntime", "CPUExecutionProvider", "int8"), ("onnxruntime", "CPUExecutionProvider", "fp16"),
    ("openvino", "CPU", "fp32"), ("openvino", "CPU", "int8"), ("onnxruntime", "CUDAExecutionProvider", "fp32"),
    ("onnxruntime", "TensorrtExecutionProvider", "fp16"), ("onnxruntime", "TensorrtExecutionProvider", "int8"),
}


# -- targets -----------------------------------------------------------------------------
def test_packaged_targets_cover_the_issue():
    targets = load_targets()
    assert REQUIRED_TARGETS <= {(t.runtime, t.provider, t.precision) for t in targets.values()}
    assert all(t.threads >= 1 for t in targets.values())


def test_unknown_target_lists_known_ones():
    known = load_targets()
    with pytest.raises(ConfigError) as err:
        select_targets(known, "ort-cpu-fp32,warp-drive")
    assert "warp-drive" in str(err.value)
    assert all(name in str(err.value) for name in known)


def test_thread_override_applies_to_every_target():
    chosen = select_targets(load_targets(), "all", threads=3)
    assert {t.threads for t in chosen} == {3}


def test_bad_targets_file(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text('[[target]]\nname = "x"\nruntime = "tflite"\nprovider = "cpu"\nprecision = "fp32"\n')
    with pytest.raises(ConfigError, match="runtime 'tflite'"):
        load_targets(path)
    path.write_text("[[target]\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_targets(path)


def test_unavailable_targets_say_why(tmp_path):
    missing_provider = Target("x", "onnxruntime", "NoSuchExecutionProvider", "fp32", "fp32", 2)
    status = availability(missing_provider, {"fp32": tmp_path / "g.onnx"}, has_torch_model=True)
    assert not status.available
    assert "NoSuchExecutionProvider not in onnxruntime.get_available_providers()" in status.reason
    int8 = Target("y", "onnxruntime", "CPUExecutionProvider", "int8", "int8", 2)
    status = availability(int8, {"fp32": tmp_path / "g.onnx", "int8": None}, has_torch_model=True)
    assert not status.available and status.reason.startswith("no int8 graph")
    eager = Target("z", "torch", "cpu", "fp32", "none", 2)
    assert availability(eager, {}, has_torch_model=True).available
    assert "no PyTorch model" in availability(eager, {}, has_torch_model=False).reason


# -- devices -----------------------------------------------------------------------------
def test_roofline_takes_the_tighter_bound():
    device = Device("toy", fp32_tflops=1.0, bandwidth_gbs=100.0)
    est = roofline(device, flops=1e9, bytes_moved=1e9)  # compute 1000 Hz, memory 100 Hz
    assert est["compute_bound_hz"] == pytest.approx(1000.0)
    assert est["hz_estimate"] == pytest.approx(100.0) and est["bound"] == "bandwidth" and est["estimate"]
    assert bytes_per_step(10, 20, 5, "int8") == 10 + 2 * 20 + 2 * 5 * 4


def test_reference_devices_carry_the_paper_rates():
    rates = {d.name.split()[0]: d.measured_hz for d in load_devices()}
    assert rates == {"A6000": 80.0, "RTX": 51.0, "Jetson": 30.0}


# -- measurement bookkeeping ----------------------------------------------------------------
class _Recorder:
    def __init__(self) -> None:
        self.seen: list[float] = []

    def reset(self) -> None:
        self.seen.clear()

    def step(self, lnes: np.ndarray) -> None:
        self.seen.append(float(lnes[0, 0, 0, 0]))


def test_side_by_side_feeds_every_runner_the_same_stream():
    frames = np.arange(7, dtype=np.float32).reshape(7, 1, 1, 1)
    runners = {"a": _Recorder(), "b": _Recorder()}
    times = measure_side_by_side(runners, frames, steps=10, warmup=3, chunk=4)
    expected = [float(k % 7) for k in range(13)]
    assert runners["a"].seen == expected and runners["b"].seen == expected
    assert {len(t) for t in times.values()} == {10}


def test_matmul_peak_is_the_best_library_measured():
    peak = matmul_peak_gflops(threads=1, size=96, repeats=3)
    libraries = {name.split()[0] for name in peak["by_library"]}
    assert libraries == {"torch", "onnxruntime"}  # both are installed in the test environment
    assert peak["gflops"] == max(peak["by_library"].values()) == peak["by_library"][peak["library"]]
    assert all(rate > 0.1 for rate in peak["by_library"].values())


def test_rss_sampler_sees_an_allocation():
    with RssSampler(interval_s=0.001) as rss:
        block = np.ones(40_000_000)  # 320 MB, touched
        block.sum()
        del block
    assert rss.growth_mb > 200


def test_synthetic_frames_are_sparse_lnes_and_seeded():
    a = moving_edge_frames(4, 96, 128, 20.0, seed=3)
    b = moving_edge_frames(4, 96, 128, 20.0, seed=3)
    assert np.array_equal(a.lnes, b.lnes)
    assert a.lnes.shape == (4, 2, 96, 128) and a.lnes.dtype == np.float32
    active = (a.lnes > 0).mean()
    assert 0.001 < active < 0.2
    assert a.lnes.min() >= 0 and a.lnes.max() < 1


# -- commands ------------------------------------------------------------------------------
def test_profile_command_report(tmp_path, tiny_step_graph, capsys):
    out = tmp_path / "prof"
    code = main(["profile", "--model", str(tiny_step_graph), "--targets", "ort-cpu-fp32,ort-cuda-fp32,ort-cpu-int8",
                 "--out", str(out), "--steps", "20", "--warmup", "2", "--profile-steps", "3"])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert {"versions", "machine", "counting", "targets", "devices"} <= set(report)
    by_name = {t["name"]: t for t in report["targets"]}
    fp32 = by_name["ort-cpu-fp32"]
    keys = {"name", "available", "reason", "params", "macs", "flops", "latency_ms", "hz", "peak_rss_mb", "model_bytes"}
    assert keys <= set(fp32)
    assert fp32["available"] and fp32["latency_ms"]["p50"] <= fp32["latency_ms"]["p90"] <= fp32["latency_ms"]["p99"]
    assert fp32["hz"] == pytest.approx(1e3 / fp32["latency_ms"]["p50"])
    assert fp32["flops"] == 2 * fp32["macs"] == report["counting"]["onnx"]["flops"]
    assert fp32["model_bytes"] == tiny_step_graph.stat().st_size
    assert not by_name["ort-cuda-fp32"]["available"] and "CUDAExecutionProvider" in by_name["ort-cuda-fp32"]["reason"]
    assert by_name["ort-cpu-int8"]["reason"].startswith("no int8 graph")
    assert report["ort_profiles"]["ort-cpu-fp32"]["steps"] == 3
    assert all(d["estimate"] for d in report["devices"])
    markdown = (out / "report.md").read_text()
    latency_table, agreement_table = markdown.split("## Latency per target")[1].split("## Against the runtimes' own timers")
    assert latency_table.count("| ort-cpu-fp32 |") == 1 and agreement_table.count("| ort-cpu-fp32 |") == 1
    assert fp32["runtime_ms"]["p50"] + fp32["overhead_ms"]["p50"] == pytest.approx(fp32["latency_ms"]["p50"], rel=0.2)
    assert fp32["outside"]["tool"] == "onnxruntime profiler (model_run)" and fp32["outside"]["runs"] == 3
    assert fp32["agreement_median"] == pytest.approx(fp32["beside_ms"] / fp32["outside"]["p50_ms"])
    assert fp32["agreement_fastest"] == pytest.approx(min(fp32["beside_burst_ms"]) / fp32["outside"]["p50_ms"])
    # The profiler has no per-turn medians: the bursts' median over its figure.
    assert fp32["agreement"] == pytest.approx(np.median(fp32["beside_burst_ms"]) / fp32["outside"]["p50_ms"])
    assert len(fp32["beside_burst_ms"]) == 4  # before each of the 3 profiler turns, and after the last
    assert min(fp32["beside_burst_ms"]) <= fp32["beside_ms"] <= max(fp32["beside_burst_ms"])
    if Path("/proc/stat").is_file():
        shares = report["cpu_time"]["timed_steps"]
        assert sum(shares.values()) == pytest.approx(1.0) and "stolen by the hypervisor" in markdown
    assert report["verdict"]["fastest"] == "ort-cpu-fp32" and report["verdict"]["not_measured"] == ["ort-cuda-fp32", "ort-cpu-int8"]
    assert (out / "latency.png").stat().st_size > 0 and (out / "macs_per_module.png").stat().st_size > 0


def test_profile_rejects_unknown_target_before_writing(tmp_path, tiny_step_graph, capsys):
    out = tmp_path / "never"
    assert main(["profile", "--model", str(tiny_step_graph), "--targets", "gpu9000", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "unknown target(s) gpu9000" in err and "ort-cpu-fp32" in err
    assert not out.exists()


def test_profile_rejects_graph_without_metadata(tmp_path, tiny_step_graph, capsys):
    bare = onnx.load(str(tiny_step_graph))
    del bare.metadata_props[:]
    path = tmp_path / "bare.onnx"
    onnx.save(bare, str(path))
    out = tmp_path / "never"
    assert main(["profile", "--model", str(path), "--targets", "ort-cpu-fp32", "--out", str(out)]) == 2
    assert "metadata" in capsys.readouterr().err.lower()
    assert not out.exists()


def test_model_info_json(tmp_path, capsys, tiny_model):
    path = tmp_path / "info.json"
    assert main(["model-info", "--variant", "tiny", "--json", str(path)]) == 0
    printed = capsys.readouterr().out
    assert "paper convention" in printed and "| cnn |" in printed
    report = json.loads(path.read_text())
    counts = report["counting"]["pytorch"]
    assert sum(m["params"] for m in counts["modules"].values()) == report["model"]["params"]
    assert report["model"]["params"] == sum(p.numel() for p in tiny_model.parameters())
    assert counts["flops"] == 2 * counts["macs"] == 2 * sum(m["macs"] for m in counts["modules"].values())


def test_ort_trace_summary_and_int8_bound_on_a_hand_made_trace(tmp_path) -> None:
    from e3dpsm.profiles.ort_profile import summarize_trace

    def kernel(node: str, op: str, us: float) -> dict:
        return {"cat": "Node", "name": f"{node}_kernel_time", "dur": us, "args": {"op_name": op, "provider": "CPU"}}

    events = []
    for _ in range(2):  # two steps: conv 6 ms + gemm 2 ms quantisable, grid sample 4 ms float
        events += [{"cat": "Session", "name": "model_run", "dur": 12_500},
                   kernel("/stem/Conv", "FusedConv", 6_000), kernel("/head/Gemm", "Gemm", 2_000),
                   kernel("/attn/GridSample", "GridSample", 4_000)]
    trace = tmp_path / "trace.json"
    trace.write_text(json.dumps(events))
    summary = summarize_trace(trace, {"/stem/Conv": "stem", "/head/Gemm": "head", "/attn/GridSample": "attention"})
    assert summary["steps"] == 2 and summary["run_ms_median"] == pytest.approx(12.5)
    assert summary["kernel_ms_per_step"] == pytest.approx(12.0)
    assert summary["by_module_ms"] == pytest.approx({"stem": 6.0, "attention": 4.0, "head": 2.0})
    bound = summary["int8_speedup_bound"]
    assert bound["quantisable_ms"] == pytest.approx(8.0) and bound["float_rest_ms"] == pytest.approx(4.0)
    assert bound["max_speedup"] == pytest.approx(3.0)


def test_int8_bound_counts_exactly_the_op_types_the_quantiser_replaces() -> None:
    """QUANTISABLE_OPS is written out in profiles (which must not import the quantiser's
    torch-heavy package); it must name each DEFAULT_OP_TYPES op and its ORT fusion only."""
    from e3dpsm.profiles.ort_profile import QUANTISABLE_OPS
    from e3dpsm.quantize.static import DEFAULT_OP_TYPES

    assert QUANTISABLE_OPS == {name for op in DEFAULT_OP_TYPES for name in (op, f"Fused{op}")}
