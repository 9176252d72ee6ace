"""e3dpsm/golden/tflite_trace.py on a `.tflite` written out in numpy (tests/_toy_tflite.py) and
on hand-made traces: which codes it exposes and how, the digests a record holds (against
numpy's codes, digested here), where two traces part, the lines it prints and the input it
refuses. The trace of the trained tiny's INT8 artifact is in test_litert_int8.py."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ai_edge_litert", reason="ai-edge-litert (pip extra litert) is not installed")

from _golden_fakes import FRAME, STATE, golden_writer  # noqa: E402
from _toy_tflite import LNES_SCALE, LNES_ZERO, STATE_SCALE, STATE_ZERO, quantize_i8, toy_pose, toy_tflite  # noqa: E402
from e3dpsm.errors import DataError, InputError  # noqa: E402
from e3dpsm.golden import tflite_trace  # noqa: E402
from e3dpsm.runtime.tflite_metadata import read_metadata  # noqa: E402
from e3dpsm.state import state_input_name, state_output_name  # noqa: E402
from e3dpsm.golden.tflite_trace import (CODE_PREFIX, compare, describe, main, read_trace, record, summary,  # noqa: E402
                                        with_exposed_codes)


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "step_int8.tflite"
    path.write_bytes(toy_tflite())
    return path


@pytest.fixture(scope="module")
def golden(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("golden") / "golden"
    writer, manifest = golden_writer(5)
    writer.write(folder, {**manifest, "window_ms": 20.0, "joints": [f"j{i}" for i in range(16)]})
    return folder


def _schema_model(content: bytes):
    from ai_edge_litert import schema_py_generated as schema

    return schema.ModelT.InitFromPackedBuf(bytearray(content), 0)


def test_every_quantize_output_becomes_a_graph_and_signature_output(toy) -> None:
    content = toy.read_bytes()
    exposed, codes = with_exposed_codes(content)
    assert codes == [  # the names the module docstring documents: e3dpsm_code_<k>
        {"name": "e3dpsm_code_0", "tensor": 4, "tensor_name": "s_codes", "operator": 1, "fed_by": "ADD", "read_by": []},
        {"name": "e3dpsm_code_1", "tensor": 5, "tensor_name": "lnes_codes", "operator": 2, "fed_by": "(graph input)",
         "read_by": ["DEQUANTIZE"]}]
    before, after = _schema_model(content), _schema_model(exposed)
    assert list(after.subgraphs[0].outputs) == [*before.subgraphs[0].outputs, 4, 5]
    signature = after.signatureDefs[0]
    assert [(o.name.decode(), o.tensorIndex) for o in signature.outputs] == [
        ("pose", 6), (state_output_name(STATE), 3), (f"{CODE_PREFIX}0", 4), (f"{CODE_PREFIX}1", 5)]
    assert [i.name for i in signature.inputs] == [i.name for i in before.signatureDefs[0].inputs]
    assert len(after.subgraphs[0].operators) == len(before.subgraphs[0].operators)  # nothing else changed
    assert read_metadata(exposed) == read_metadata(content)  # the contract travels with the copy


def test_an_operator_the_schema_does_not_name_reads_custom(toy, monkeypatch) -> None:
    """An operator code newer than the installed schema (here: ADD hidden from the names)."""
    names = tflite_trace._op_names()
    monkeypatch.setattr(tflite_trace, "_op_names", lambda: {k: v for k, v in names.items() if v != "ADD"})
    _, codes = with_exposed_codes(toy.read_bytes())
    assert [c["fed_by"] for c in codes] == ["CUSTOM", "(graph input)"]


def test_a_code_that_is_already_a_graph_output_is_not_listed_twice() -> None:
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.runtime.tflite_metadata import rewrite_model

    def code_as_output(model) -> None:
        graph = model.subgraphs[0]
        graph.outputs = np.append(graph.outputs, 5).astype(np.int32)
        entry = schema.TensorMapT()
        entry.name, entry.tensorIndex = b"lnes_codes", 5
        model.signatureDefs[0].outputs.append(entry)
    content = rewrite_model(toy_tflite(), code_as_output)
    exposed, codes = with_exposed_codes(content)
    outputs = list(_schema_model(exposed).subgraphs[0].outputs)
    assert outputs == [6, 3, 5, 4] and [c["tensor"] for c in codes] == [4, 5]


def test_the_exposed_copy_hands_out_the_codes_numpy_computes(toy, tmp_path) -> None:
    from ai_edge_litert.interpreter import Interpreter

    exposed, _ = with_exposed_codes(toy.read_bytes())
    runner = Interpreter(model_content=exposed, num_threads=1).get_signature_runner()
    rng = np.random.default_rng(3)
    lnes = rng.uniform(-0.1, 1.0, (1, *FRAME)).astype(np.float32)
    state = rng.normal(0, 4, (1, 6)).astype(np.float32)
    got = runner(lnes=lnes, window_ms=np.array([20.0], np.float32), **{state_input_name(STATE): state})
    np.testing.assert_array_equal(got[f"{CODE_PREFIX}0"], quantize_i8(state + 20.0, STATE_SCALE, STATE_ZERO))
    np.testing.assert_array_equal(got[f"{CODE_PREFIX}1"], quantize_i8(lnes, LNES_SCALE, LNES_ZERO))
    np.testing.assert_allclose(got["pose"], toy_pose(lnes), rtol=0, atol=1e-7)


def _digest(codes: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(codes).tobytes(), digest_size=8).hexdigest()


def test_a_record_digests_every_code_at_every_step_with_the_state_carried(toy, golden) -> None:
    """Step k's state is the initial state (zeros) plus the windows so far: code 0 digests
    quantize(20 (k + 1)) of all six state values; code 1 the golden's frame k."""
    from e3dpsm.golden.store import load_golden

    trace = record(toy, golden, steps=3)
    frames = load_golden(golden)
    assert trace["model"] == str(toy) and trace["steps"] == 3 and len(trace["digests"]) == 3
    assert [c["name"] for c in trace["codes"]] == [f"{CODE_PREFIX}0", f"{CODE_PREFIX}1"]
    for step, row in enumerate(trace["digests"]):
        state = np.full((1, 6), 20.0 * (step + 1), np.float32)
        frame = frames.frame(step).astype(np.float32)
        assert row == [_digest(quantize_i8(state, STATE_SCALE, STATE_ZERO)),
                       _digest(quantize_i8(frame.reshape(1, *FRAME), LNES_SCALE, LNES_ZERO))]
    assert trace["isa"]["kind"] and "flags" in trace["isa"]
    assert record(toy, golden)["steps"] == 5 and record(toy, golden, steps=99)["steps"] == 5  # at most the golden's
    assert record(toy, golden, steps=1)["digests"] == trace["digests"][:1]


def test_a_record_of_no_steps_is_refused(toy, golden) -> None:
    for steps in (0, -2):
        with pytest.raises(InputError, match=rf"^--steps {steps}: a trace needs at least one step$"):
            record(toy, golden, steps=steps)


# -- comparing and describing hand-made traces --------------------------------------------------------
def code(k: int, **fields) -> dict:
    return {"name": f"{CODE_PREFIX}{k}", "tensor": 10 + k, "tensor_name": f"s0t{10 + k}", "operator": 100 + k,
            "fed_by": "ADD", "read_by": ["CONV_2D"], **fields}


def trace(digests: list[list[str]], codes: int = 3, isa: str = "vnni") -> dict:
    return {"model": "m.tflite", "steps": len(digests), "codes": [code(k) for k in range(codes)], "digests": digests,
            "isa": {"kind": isa}}


HOST = trace([["a", "b", "c"], ["d", "e", "f"], ["g", "h", "i"], ["j", "k", "l"]])


def test_two_traces_part_where_a_code_first_differs() -> None:
    device = trace([["a", "b", "c"], ["d", "X", "f"], ["g", "X", "X"], ["X", "k", "X"]], isa="arm")
    report = compare(HOST, device)
    assert [c["first_step"] for c in report["per_code"]] == [3, 1, 2]
    assert report["first_step"] == 1 and [c["name"] for c in report["first_departures"]] == [f"{CODE_PREFIX}1"]
    assert (report["steps"], report["codes"], report["apart_by_end"]) == (4, 3, 3)
    assert (report["host_isa"], report["device_isa"]) == ({"kind": "vnni"}, {"kind": "arm"})
    assert report["per_code"][0] == {**code(0), "first_step": 3}
    same = compare(HOST, HOST)
    assert same["first_step"] is None and same["apart_by_end"] == 0 and same["first_departures"] == []


def test_the_shorter_trace_sets_the_steps_compared() -> None:
    device = trace([["a", "b", "c"], ["d", "e", "f"]])
    longer_apart = trace([["a", "b", "c"], ["d", "e", "f"], ["X", "X", "X"]])
    assert compare(HOST, device)["steps"] == 2 and compare(HOST, device)["first_step"] is None
    assert compare(longer_apart, device)["first_step"] is None  # step 2 is past the device's end
    assert compare(HOST, longer_apart)["first_step"] == 2


def test_several_codes_parting_at_one_step_are_all_first_departures() -> None:
    device = trace([["a", "b", "c"], ["X", "e", "X"], ["g", "h", "i"], ["j", "k", "l"]])
    report = compare(HOST, device)
    assert [c["name"] for c in report["first_departures"]] == [f"{CODE_PREFIX}0", f"{CODE_PREFIX}2"]
    line = summary(report)
    assert line == (f"code tensors part first at step 1, first in graph order {describe(code(0))}, then 1 more "
                    "downstream at that step; 2 of 3 code tensors apart by step 3")


def test_traces_of_different_graphs_are_refused() -> None:
    renamed = {**HOST, "codes": [code(0), code(1), code(7)]}
    with pytest.raises(ValueError, match=r"^the two traces are of different graphs \(their code tensors differ\)$"):
        compare(HOST, renamed)
    with pytest.raises(ValueError, match="different graphs"):
        compare(HOST, trace([["a", "b"]] * 4, codes=2))


def test_summary_lines() -> None:
    assert summary(compare(HOST, HOST)) == "all 3 code tensors the same at every one of 4 steps"
    device = trace([["a", "b", "c"], ["d", "e", "f"], ["g", "h", "X"], ["j", "k", "X"]])
    assert summary(compare(HOST, device)) == (f"code tensors part first at step 2, first in graph order "
                                              f"{describe(code(2))}; 1 of 3 code tensors apart by step 3")


def test_describe_names_the_operators_around_a_code_and_a_kept_tensor_name() -> None:
    assert describe(code(4)) == f"{CODE_PREFIX}4 (operator 104: ADD -> QUANTIZE -> CONV_2D)"
    both = code(1, read_by=["BATCH_MATMUL", "FULLY_CONNECTED"], fed_by="(graph input)")
    assert describe(both) == f"{CODE_PREFIX}1 (operator 101: (graph input) -> QUANTIZE -> BATCH_MATMUL/FULLY_CONNECTED)"
    assert describe(code(2, read_by=[])) == f"{CODE_PREFIX}2 (operator 102: ADD -> QUANTIZE -> output)"
    long = "x" * 30 + "/model.stages.0.block.1/Conv2d_proj" + "y" * 40 + ";12_quantized;more"
    kept = long.split(";")[0][-80:]
    assert len(long.split(";")[0]) > 80 and describe(code(3, tensor_name=long)).endswith(f"-> CONV_2D, {kept})")
    assert describe(code(3, tensor_name="proj;1")).endswith("-> CONV_2D, proj)")
    assert describe(code(3, tensor_name="s12t3")).endswith("-> CONV_2D)")


# -- reading traces -------------------------------------------------------------------------------------
def write(path: Path, value) -> Path:
    path.write_text(json.dumps(value) if not isinstance(value, str) else value, encoding="utf-8")
    return path


@pytest.mark.parametrize("broken, message", [
    ("{not json", r"not a JSON trace"),
    ([1, 2], r"not a tflite_trace record \(it needs model, steps, codes, digests, isa\)"),
    ({k: v for k, v in HOST.items() if k != "isa"}, r"not a tflite_trace record"),
    ({**HOST, "steps": 0, "digests": []}, r"a trace of 0 steps compares nothing"),
    ({**HOST, "steps": True}, r"a trace of True steps compares nothing"),
    ({**HOST, "steps": "4"}, r"a trace of '4' steps compares nothing"),
    ({**HOST, "codes": ["e3dpsm_code_0"]}, r"its codes are not a list of named code tensors"),
    ({**HOST, "codes": {"name": "x"}}, r"its codes are not a list of named code tensors"),
    ({**HOST, "codes": [code(0), {"tensor": 3}, code(2)]}, r"its codes are not a list of named code tensors"),
    ({**HOST, "steps": 5}, r"its digests are not 5 steps of 3 code tensors each"),
    ({**HOST, "digests": [["a", "b"]] * 4}, r"its digests are not 4 steps of 3 code tensors each"),
    ({**HOST, "digests": "abc"}, r"its digests are not 4 steps"),
    ({**HOST, "digests": ["abc"] * 4}, r"its digests are not 4 steps"),
])
def test_a_broken_trace_is_one_data_error_naming_the_file(tmp_path, broken, message) -> None:
    path = write(tmp_path / "t.json", broken)
    with pytest.raises(DataError, match=rf"^{tmp_path / 't.json'}: {message}"):
        read_trace(path)


def test_a_good_trace_reads_back_as_written(tmp_path) -> None:
    assert read_trace(write(tmp_path / "t.json", HOST)) == HOST
    one_step = trace([["a", "b", "c"]])
    assert read_trace(write(tmp_path / "one.json", one_step)) == one_step  # one step is a trace
    (tmp_path / "bad.json").write_bytes(b"\xff\xfe{")
    with pytest.raises(DataError, match="not a JSON trace"):
        read_trace(tmp_path / "bad.json")


# -- the command --------------------------------------------------------------------------------------
def test_compare_prints_one_line_and_writes_the_report(tmp_path, capsys) -> None:
    device = trace([["a", "b", "c"], ["d", "X", "f"], ["g", "h", "i"], ["j", "k", "l"]])
    host_path, device_path = write(tmp_path / "host.json", HOST), write(tmp_path / "device.json", device)
    assert main(["compare", str(host_path), str(device_path), "--out", str(tmp_path / "cmp.json")]) == 0
    assert capsys.readouterr().out == summary(compare(HOST, device)) + "\n"
    assert json.loads((tmp_path / "cmp.json").read_text()) == compare(HOST, device)
    assert main(["compare", str(host_path), str(host_path)]) == 0
    assert capsys.readouterr().out.startswith("all 3 code tensors the same")


def test_the_command_refuses_bad_input_in_one_line_and_writes_nothing(toy, golden, tmp_path, capsys) -> None:
    host_path = write(tmp_path / "host.json", HOST)
    cases = [
        (["compare", str(host_path), str(tmp_path / "missing.json"), "--out", str(tmp_path / "o1.json")], "missing.json"),
        (["compare", str(host_path), str(write(tmp_path / "short.json", {**HOST, "steps": 0})),
          "--out", str(tmp_path / "o2.json")], "compares nothing"),
        (["compare", str(host_path), str(write(tmp_path / "other.json", trace([["a"]] * 4, codes=1))),
          "--out", str(tmp_path / "o3.json")], "different graphs"),
        (["record", str(toy), str(golden), str(tmp_path / "o4.json"), "--steps", "0"], "at least one step"),
        (["record", str(toy), str(tmp_path / "no-golden"), str(tmp_path / "o5.json")], "no-golden"),
    ]
    for argv, expected in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("tflite_trace: error: ") and expected in err, err
    assert not any((tmp_path / f"o{k}.json").exists() for k in range(1, 6))


def test_record_writes_the_trace_it_returns(toy, golden, tmp_path, capsys) -> None:
    out = tmp_path / "host.json"
    assert main(["record", str(toy), str(golden), str(out), "--steps", "2"]) == 0
    assert json.loads(out.read_text()) == json.loads(json.dumps(record(toy, golden, steps=2)))
    assert read_trace(out)["steps"] == 2 and capsys.readouterr().out == ""


def test_the_module_runs_as_a_command_and_names_itself_in_its_usage(tmp_path) -> None:
    import subprocess
    import sys

    host = write(tmp_path / "host.json", HOST)
    done = subprocess.run([sys.executable, "-m", "e3dpsm.golden.tflite_trace", "compare", str(host), str(host)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and done.stdout == "all 3 code tensors the same at every one of 4 steps\n"
    for argv in ([], ["record"]):
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
    usage = subprocess.run([sys.executable, "-m", "e3dpsm.golden.tflite_trace"], capture_output=True, text=True,
                           timeout=120)
    assert usage.returncode == 2 and usage.stderr.startswith("usage: python -m e3dpsm.golden.tflite_trace ")
