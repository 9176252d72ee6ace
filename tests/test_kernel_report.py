"""`python -m e3dpsm.golden.kernel_report host|device` on a toy QDQ step graph and a hand-made
golden (tests/_golden_fakes.py): what the host half writes (the two graphs, the trace, its
manifest), that the device half on the same host finds every code the same, and that a code
changed in the host's trace is named where it departs, first in the propagated rollout and on
its own in the isolated one."""
from __future__ import annotations

import hashlib
import json

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from _golden_fakes import FRAME, STATE, STATE_SHAPE, golden_writer
from _qdq_reference import qdq_u8
from e3dpsm.golden import kernel_trace as kt
from e3dpsm.golden.kernel_report import (CUT, EXPOSED, HOST_TRACE, KERNELS_FOLDER, ORDER, find_trace, main,
                                         record_host, responsible_lines, run_device, trace_folder)
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.state import StateSpec, state_input_name, state_output_name
from e3dpsm.utils.isa import detect_isa

S_IN, S_OUT = state_input_name(STATE), state_output_name(STATE)


def _toy_qdq(path) -> None:
    """a = Q(s / 2 + mean(lnes) + window / 100) [scale 0.05]; s' = DQ(Q(DQ(a) * 0.5)) [0.02]."""
    inits = [numpy_helper.from_array(np.array(v, np.float32 if isinstance(v, float) else np.uint8), n)
             for n, v in (("s_a", 0.05), ("z_a", 128), ("s_h", 0.02), ("z_h", 128), ("half", 0.5), ("hundredth", 0.01))]
    inits.append(numpy_helper.from_array(np.array([-1, 1], np.int64), "column"))
    nodes = [helper.make_node("ReduceMean", ["lnes"], ["mean"], axes=[1, 2, 3], keepdims=0),
             helper.make_node("Mul", ["window_ms", "hundredth"], ["w"]),
             helper.make_node("Add", ["mean", "w"], ["drive"]),
             helper.make_node("Reshape", ["drive", "column"], ["drive_col"]),
             helper.make_node("Mul", [S_IN, "half"], ["kept"]),
             helper.make_node("Add", ["kept", "drive_col"], ["sum"]),
             helper.make_node("QuantizeLinear", ["sum", "s_a", "z_a"], ["a_q"]),
             helper.make_node("DequantizeLinear", ["a_q", "s_a", "z_a"], ["a"]),
             helper.make_node("Mul", ["a", "half"], ["halved"]),
             helper.make_node("QuantizeLinear", ["halved", "s_h", "z_h"], ["h_q"]),
             helper.make_node("DequantizeLinear", ["h_q", "s_h", "z_h"], [S_OUT]),
             helper.make_node("Identity", [S_OUT], ["pose"])]
    value = lambda name, *shape: helper.make_tensor_value_info(name, TensorProto.FLOAT, ["B", *shape])  # noqa: E731
    graph = helper.make_graph(nodes, "toy", [value("lnes", *FRAME), value("window_ms"), value(S_IN, *STATE_SHAPE)],
                              [value("pose", *STATE_SHAPE), value(S_OUT, *STATE_SHAPE)], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    GraphMetadata(states=(StateSpec(STATE, STATE_SHAPE, init=tuple(np.linspace(-1, 1, 6))),),
                  inputs={"frame": {"name": "lnes", "shape": ["B", *FRAME]}, "window": {"name": "window_ms", "shape": ["B"]}},
                  outputs=[{"name": "pose"}], config={"variant": "toy"}, joints=["j"]).write_to(model)
    onnx.save(model, str(path))


def _write_golden(folder, steps: int) -> None:
    writer, manifest = golden_writer(steps)
    writer.write(folder, {**manifest, "window_ms": 20.0, "joints": [f"j{i}" for i in range(16)]})


@pytest.fixture(scope="module")
def host_half(tmp_path_factory):
    root = tmp_path_factory.mktemp("kernel_report")
    graph, golden = root / "step_int8.onnx", root / "golden"
    _toy_qdq(graph)
    _write_golden(golden, 12)
    digest = hashlib.sha256(graph.read_bytes()).hexdigest()
    folder = trace_folder(golden, graph, digest)
    return graph, golden, folder, record_host(graph, golden, folder, steps=7)


def test_the_host_half_writes_both_graphs_its_trace_and_the_manifest(host_half) -> None:
    from e3dpsm.golden.store import load_golden

    graph, golden_dir, folder, manifest = host_half
    digest = hashlib.sha256(graph.read_bytes()).hexdigest()
    assert folder == golden_dir / "kernels" / f"step_int8-{digest[:12]}" and KERNELS_FOLDER == "kernels"
    # the names a device's copy of the folder is read by (the module doc): written out, not the constants
    assert sorted(p.name for p in folder.iterdir()) == ["codes.json", "cut.onnx", "exposed.onnx", "host.npz"]
    assert manifest == json.loads((folder / ORDER).read_text())
    assert manifest == {"graph": str(graph), "sha256": digest, "codes": ["a_q", "h_q"],
                        "segments": {"a_q": ["ReduceMean", "Mul", "Add", "Mul", "Add"], "h_q": ["Mul"]},  # Reshape: bookkeeping
                        "steps": 7, "state_inputs": [S_IN]}
    assert find_trace(golden_dir, digest) == folder and find_trace(golden_dir, None) is None
    assert find_trace(golden_dir, "0" * 64) is None
    trace = kt.load_trace(folder / HOST_TRACE)
    golden = load_golden(golden_dir)
    state = np.float32(np.linspace(-1, 1, 6))[None]
    for step in range(7):  # the golden's frames, the state carried, the codes as numpy computes them
        frame = golden.frame(step)
        assert np.array_equal(trace[kt.IN + "lnes"][step], frame)
        assert np.array_equal(trace[kt.IN + S_IN][step], state)
        drive = frame.astype(np.float32).mean(axis=(1, 2, 3)) + np.float32(20.0) * np.float32(0.01)
        a_codes, a = qdq_u8(state * np.float32(0.5) + drive[:, None], 0.05, 128)
        h_codes, state = qdq_u8(a * np.float32(0.5), 0.02, 128)
        assert np.array_equal(trace[kt.CODE + "a_q"][step], a_codes), step
        assert np.array_equal(trace[kt.CODE + "h_q"][step], h_codes), step
    assert len(np.unique(trace[kt.CODE + "a_q"])) > 3  # the codes move: the check below is not of constants


def test_the_device_half_on_the_same_host_finds_every_code_the_same(host_half, tmp_path, capsys) -> None:
    _, _, folder, _ = host_half
    report = run_device(folder, out=tmp_path / "device.json")
    assert report == json.loads((tmp_path / "device.json").read_text())
    assert report["graph"] == str(host_half[0])
    assert (report["steps"], report["codes"], report["isolated_identical"]) == (7, 2, 2)
    assert report["isolated"] == [] and report["first_departures"] == []
    assert [d["apart"] for d in report["propagated"]] == [0, 0]
    assert report["isa"]["kind"] == detect_isa().kind
    work = tmp_path / "trace"
    work.mkdir()
    for name in (EXPOSED, CUT, HOST_TRACE, ORDER):
        (work / name).write_bytes((folder / name).read_bytes())
    assert main(["device", str(work)]) == 0
    assert capsys.readouterr().out == (f"kernel trace on {detect_isa().kind}: first departure none; "
                                       "0 of 2 segments depart on their own\n")
    assert (work / f"device-{detect_isa().kind}.json").is_file()


def test_a_code_changed_in_the_host_trace_is_named_where_it_departs(host_half, tmp_path, capsys) -> None:
    """a_q moved by one code at step 3 in the host's trace: the device's own a_q departs there,
    on its own (isolated: computed from the host's inputs) and in the rollout."""
    _, _, folder, _ = host_half
    work = tmp_path / "trace"
    work.mkdir()
    for name in (EXPOSED, CUT, ORDER):
        (work / name).write_bytes((folder / name).read_bytes())
    trace = kt.load_trace(folder / HOST_TRACE)
    trace[kt.CODE + "a_q"][3, 0, 2] += 1
    trace[kt.CODE + "h_q"][5, 0, 4] += 1
    np.savez(work / HOST_TRACE, **trace)
    assert main(["device", str(work)]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"kernel trace on {detect_isa().kind}: first departure ['a_q']; ")
    report = json.loads((work / f"device-{detect_isa().kind}.json").read_text())
    first = report["isolated"][0]
    assert (first["name"], first["first_step"], first["apart"], first["max_codes"]) == ("a_q", 3, 1, 1)
    assert first["segment"] == ["ReduceMean", "Mul", "Add", "Mul", "Add"]
    propagated = {d["name"]: d for d in report["propagated"]}
    assert (propagated["a_q"]["first_step"], propagated["a_q"]["apart"]) == (3, 1)
    assert report["first_departures"] == ["a_q", "h_q"]  # the line names the first only
    assert report["isolated_identical"] == 2 - len(report["isolated"])
    assert f"{len(report['isolated'])} of 2 segments depart on their own" in out


def test_responsible_lines_name_the_segment_and_cut_the_list() -> None:
    entry = lambda name, ops: {"name": name, "segment": ops, "apart": 3, "steps_apart": 2, "first_step": 5,  # noqa: E731
                               "max_codes": 1}
    report = {"isolated": [entry("a_q", ["Conv", "Relu"]), entry("b_q", []), *(entry(f"c{i}", ["Add"]) for i in range(6))]}
    lines = responsible_lines(report)
    assert lines[0] == "a_q (Conv Relu): 3 codes apart over 2 steps from step 5, at most 1"
    assert lines[1] == "b_q (data movement): 3 codes apart over 2 steps from step 5, at most 1"
    assert len(lines) == 7 and lines[-1] == "... and 2 more (check.json)"
    assert responsible_lines(report, limit=7)[-1] == "... and 1 more (check.json)"
    assert len(responsible_lines(report, limit=8)) == 8 and "more" not in responsible_lines(report, limit=8)[-1]
    assert responsible_lines({"isolated": []}) == []


def test_the_host_command_records_and_says_what(tmp_path, capsys) -> None:
    graph, golden = tmp_path / "step_int8.onnx", tmp_path / "golden"
    _toy_qdq(graph)
    _write_golden(golden, 4)
    assert main(["host", str(graph), str(golden), str(tmp_path / "trace")]) == 0
    assert capsys.readouterr().out == f"kernel trace: 2 quantised activations over 4 steps -> {tmp_path / 'trace'}\n"
    assert json.loads((tmp_path / "trace" / ORDER).read_text())["steps"] == 4  # all of the golden's steps
    assert main(["host", str(graph), str(golden), str(tmp_path / "long"), "--steps", "50"]) == 0
    assert json.loads((tmp_path / "long" / ORDER).read_text())["steps"] == 4  # no more than the golden has


def test_one_step_is_enough_and_a_folder_can_be_recorded_again(tmp_path, monkeypatch) -> None:
    """The smallest trace (one step) records and checks; recording into the same folder
    replaces it; both halves run one thread unless asked."""
    threads: list[int] = []
    for name in ("rollout", "isolated"):
        original = getattr(kt, name)
        monkeypatch.setattr(kt, name, lambda *a, _f=original, **k: threads.append(a[3]) or _f(*a, **k))
    graph, golden = tmp_path / "step_int8.onnx", tmp_path / "golden"
    _toy_qdq(graph)
    _write_golden(golden, 3)
    for _ in range(2):
        manifest = record_host(graph, golden, tmp_path / "trace", steps=1)
        assert manifest["steps"] == 1
    report = run_device(tmp_path / "trace", out=tmp_path / "device.json")
    assert report["steps"] == 1 and report["isolated_identical"] == 2
    assert threads == [1, 1, 1, 1]  # host rollout twice, then the device's rollout and isolated run


def test_a_graph_without_quantisation_and_a_trace_without_steps_say_how_to_fix_them(tmp_path) -> None:
    from e3dpsm.errors import DataError

    model = onnx.helper.make_model(onnx.helper.make_graph(
        [helper.make_node("Relu", ["x"], ["y"])], "float", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])]), opset_imports=[helper.make_opsetid("", 13)])
    onnx.save(model, str(tmp_path / "float.onnx"))
    with pytest.raises(DataError, match=r"^\S+float\.onnx: no QuantizeLinear on a computed tensor: not a QDQ graph "
                                        r"\(write one with `e3dpsm quantize --mode int8`\)$"):
        record_host(tmp_path / "float.onnx", tmp_path / "golden", tmp_path / "trace")
    (tmp_path / "trace").mkdir()
    (tmp_path / "trace" / ORDER).write_text('{"codes": [], "segments": {}, "steps": "3"}')
    with pytest.raises(DataError, match=r"^\S+codes\.json: the host trace holds no steps \('3'\); record it again "
                                        r"with `python -m e3dpsm\.golden\.kernel_report host`$"):
        run_device(tmp_path / "trace")


def test_the_module_runs_as_a_command_and_needs_a_half(tmp_path) -> None:
    import subprocess
    import sys

    with pytest.raises(SystemExit) as exited:
        main([])
    assert exited.value.code == 2
    (tmp_path / "bad.onnx").write_text("not onnx")
    done = subprocess.run([sys.executable, "-m", "e3dpsm.golden.kernel_report", "portable", str(tmp_path / "bad.onnx"),
                           str(tmp_path / "out.onnx")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and done.stderr.startswith("python -m e3dpsm.golden.kernel_report portable: error: ")
