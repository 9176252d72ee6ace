"""e3dpsm/golden/pte_trace.py on the toy `.pte` of tests/_toy_pte.py (its arithmetic one XNNPACK
partition) and on hand-made traces: what a record holds (the program's outputs digested
against numpy's own toy poses and states), where two traces part, the lines it prints and the
input it refuses. The trace of a real INT8 program on emulated ARM is
benchmarks/arm_emulation.py --trace (docs/edge.md)."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")

from _golden_fakes import STATE_SHAPE, parted_record, write_golden  # noqa: E402
from _toy_pte import toy_pose, toy_pte  # noqa: E402
from e3dpsm.errors import DataError, InputError  # noqa: E402
from e3dpsm.golden import pte_trace  # noqa: E402
from e3dpsm.golden.pte_trace import compare, describe, main, read_trace, record, summary  # noqa: E402

STEPS = 5


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "step.pte"
    path.write_bytes(toy_pte(delegated=True))
    return path


@pytest.fixture(scope="module")
def golden(tmp_path_factory) -> Path:
    return write_golden(tmp_path_factory.mktemp("golden") / "golden", STEPS)


@pytest.fixture(scope="module")
def trace(toy, golden) -> dict:
    return record(toy, golden)


def _digest(array: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(array, np.float32).tobytes(), digest_size=8).hexdigest()


def test_a_record_digests_every_value_the_program_logs_at_every_step(trace, golden) -> None:
    """The program's own outputs, digested here from numpy's toy arithmetic (pose = 2 lnes +
    window, state + window from zero), are the record's last two values at every step."""
    from e3dpsm.golden.store import load_golden

    assert trace["steps"] == STEPS and len(trace["digests"]) == STEPS
    kinds = [o["kernel"] for o in trace["outputs"]]
    assert kinds[0] == "_to_dim_order_copy.out"  # a portable kernel, named without ETDump's "native_call_"
    assert kinds[-2:] == [pte_trace.PROGRAM_OUTPUT] * 2 and pte_trace.DELEGATE_CALL in kinds
    assert [o["instruction"] for o in trace["outputs"][-2:]] == [-1, -1]  # what the method returns: no instruction
    partition = next(o for o in trace["outputs"] if o["kernel"] == pte_trace.DELEGATE_CALL)
    assert partition["operators"] == len(partition["operator_names"]) >= 2
    assert any(n.startswith("Multiply") for n in partition["operator_names"])
    assert any(n.startswith("Add") for n in partition["operator_names"])
    values = {}
    for o in trace["outputs"]:
        values[o["instruction"]] = values.get(o["instruction"], -1) + 1
        assert o["output"] == values[o["instruction"]]  # numbered per instruction, in order
    record_golden = load_golden(golden)
    state = np.zeros((1, *STATE_SHAPE), np.float32)
    for step in range(STEPS):
        window = record_golden.window_ms(step)
        pose = toy_pose(record_golden.frame(step)[None], window)
        state = state + np.float32(window)
        assert trace["digests"][step][-2:] == [_digest(pose), _digest(state)], step
    assert trace["isa"]["kind"]


def test_the_same_program_on_the_same_machine_never_parts(trace) -> None:
    report = compare(trace, json.loads(json.dumps(trace)))
    assert report["first_step"] is None and report["apart_by_end"] == 0 and report["first_departures"] == []
    assert summary(report) == f"all {len(trace['outputs'])} instruction outputs the same at every one of {STEPS} steps"


def test_the_first_departure_is_the_earliest_step_then_the_first_in_execution_order(trace) -> None:
    partition = next(o for o in trace["outputs"] if o["kernel"] == pte_trace.DELEGATE_CALL)
    first = trace["outputs"].index(partition)
    last = len(trace["outputs"]) - 1
    device = parted_record(trace, 3, [last])
    device = parted_record(device, 2, [first + 1, last - 1])
    report = compare(trace, device)
    assert report["first_step"] == 2 and report["apart_by_end"] == 3
    assert [o["position"] for o in report["first_departures"]] == [first + 1, last - 1]
    assert [o["first_step"] for o in report["per_output"] if o["first_step"] is not None] == [2, 2, 3]
    line = summary(report)
    assert line.startswith(f"instruction outputs part first at step 2, first in execution order instruction "
                           f"{partition['instruction']} (XNNPACK partition of {partition['operators']} operators, "
                           f"0 of them 8-bit; value 1), then 1 more after it at that step; 3 of")
    assert line.endswith(f"outputs apart by step {STEPS - 1}")


def test_descriptions_name_kernels_partitions_and_program_outputs() -> None:
    assert describe({"instruction": 7, "kernel": "grid_sampler_2d.out", "output": 0}) == \
        "instruction 7 (grid_sampler_2d.out)"
    assert describe({"instruction": -1, "kernel": pte_trace.PROGRAM_OUTPUT, "output": 3, "position": 40}) == \
        "(program output) 40"
    names = ["Convert (NC) #1", "Fully Connected (NC, QS8, QC8W) GEMM #1", "Convolution (NHWC, QC8) IGEMM #1",
             "Add (ND) #1", "Add (ND, QS8) #2", "Average Pooling (NHWC, QU8) #1"]
    assert describe({"instruction": 19, "kernel": pte_trace.DELEGATE_CALL, "output": 2, "operators": 6,
                     "operator_names": names}) == \
        "instruction 19 (XNNPACK partition of 6 operators, 4 of them 8-bit; value 2)"


def test_traces_of_different_programs_do_not_compare(trace) -> None:
    other = json.loads(json.dumps(trace))
    other["outputs"][0]["instruction"] += 1
    with pytest.raises(ValueError, match=r"^the two traces are of different programs \(their instructions differ\)$"):
        compare(trace, other)


def test_a_comparison_keeps_each_machines_isa_and_one_departure_has_no_tail(trace) -> None:
    device = parted_record(trace, 1, [0])
    device["isa"] = {"kind": "dotprod", "flags": ["asimd"]}
    report = compare(trace, device)
    assert report["host_isa"] == trace["isa"] and report["device_isa"] == {"kind": "dotprod", "flags": ["asimd"]}
    assert summary(report) == (f"instruction outputs part first at step 1, first in execution order "
                               f"{describe(report['first_departures'][0])}; 1 of {len(trace['outputs'])} instruction "
                               f"outputs apart by step {STEPS - 1}")


def test_scalars_are_digested_by_value_and_unknown_tensor_types_refused() -> None:
    from types import SimpleNamespace as V

    scalar = V(tensor=None, tensor_list=None, int_value=3, float_value=None, double_value=None, bool_value=None)
    assert pte_trace._value_bytes(scalar, b"") == [b"[3]"]
    debug = np.arange(6, dtype=np.float32).tobytes() + np.arange(2, dtype=np.int64).tobytes()
    listed = V(tensor=None, tensor_list=V(tensors=[V(scalar_type=6, sizes=[2, 3], offset=0),
                                                   V(scalar_type=4, sizes=[2], offset=24)]))
    ends = []
    assert pte_trace._value_bytes(listed, debug, ends) == [debug[:24], debug[24:40]]
    assert ends == [0, 24, 24, 40] and pte_trace._used(ends) == 40
    assert pte_trace._used([]) == 0 and pte_trace._used([100, 150, 150, 300]) == 300
    assert pte_trace._used([50, 60, 10, 20]) == 60  # up to the furthest end, wherever it sits in the list
    zero_d = V(tensor=V(scalar_type=6, sizes=[], offset=4), tensor_list=None)
    assert pte_trace._value_bytes(zero_d, debug) == [debug[4:8]]
    with pytest.raises(ValueError, match=r"^ETDump tensor of scalar type 99: not one this trace reads$"):
        pte_trace._value_bytes(V(tensor=V(scalar_type=99, sizes=[1], offset=0), tensor_list=None), debug)


def test_cli_records_and_compares_in_one_line(toy, golden, tmp_path, capsys) -> None:
    host = tmp_path / "host.json"
    assert main(["record", str(toy), str(golden), str(host), "--steps", "3"]) == 0
    written = read_trace(host)
    assert written["steps"] == 3
    out = tmp_path / "cmp.json"
    assert main(["compare", str(host), str(host), "--out", str(out)]) == 0
    assert capsys.readouterr().out.strip().endswith("the same at every one of 3 steps")
    assert json.loads(out.read_text())["first_step"] is None


@pytest.mark.parametrize("content, message", [
    ("not json", "not a JSON trace"),
    (json.dumps({"steps": 1}), "not a pte_trace record"),
    (json.dumps({"model": "m", "steps": 0, "outputs": [], "digests": [], "isa": {}}), "a trace of 0 steps"),
    (json.dumps({"model": "m", "steps": 1, "outputs": [{"x": 1}], "digests": [["a"]], "isa": {}}),
     "not a list of instruction outputs"),
    (json.dumps({"model": "m", "steps": 2, "outputs": [{"instruction": 1}], "digests": [["a"]], "isa": {}}),
     "not 2 steps of 1 outputs each"),
])
def test_a_broken_trace_is_one_line_and_exit_2(tmp_path, capsys, content, message) -> None:
    path = tmp_path / "t.json"
    path.write_text(content)
    with pytest.raises(DataError, match=message):
        read_trace(path)
    assert main(["compare", str(path), str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("pte_trace: error: ") and message in err and err.count("\n") == 1


def test_a_trace_of_no_steps_is_refused(toy, golden) -> None:
    with pytest.raises(InputError, match="^--steps 0: a trace needs at least one step$"):
        record(toy, golden, steps=0)
    assert record(toy, golden, steps=1)["steps"] == 1


def test_steps_run_in_chunks_whose_buffers_are_sized_from_the_first_step(trace, toy, golden, monkeypatch) -> None:
    """ExecuTorch aborts on a full debug buffer: the first step alone in a large one, the
    rest in chunks sized from what it used; the digests are those of one long run."""
    sizes, used = [], []
    load, written = pte_trace._traced_module, pte_trace._written
    monkeypatch.setattr(pte_trace, "CHUNK_STEPS", 2)
    monkeypatch.setattr(pte_trace, "_traced_module", lambda model, size: sizes.append(size) or load(model, size))
    def recorded(traced):
        found = written(traced)  # once: ETDump hands its runs out once
        used.append(found[2])
        return found

    monkeypatch.setattr(pte_trace, "_written", recorded)
    chunked = record(toy, golden)
    assert chunked["digests"] == trace["digests"] and chunked["outputs"] == trace["outputs"]
    assert sizes[0] == pte_trace.FIRST_STEP_DEBUG_BYTES and len(sizes) == 3  # steps 0 | 1-2 | 3-4
    per_step = used[0] + used[0] // 4 + (1 << 16)  # a quarter over what step 0 used, and 64 KiB
    assert 0 < used[0] < 4096 and sizes[1:] == [2 * per_step] * 2


def test_a_tensor_past_the_debug_buffer_is_an_error() -> None:
    from types import SimpleNamespace as V

    with pytest.raises(ValueError, match=r"^ETDump tensor at bytes 0-12 past its 8-byte debug buffer$"):
        pte_trace._value_bytes(V(tensor=V(scalar_type=6, sizes=[3], offset=0), tensor_list=None), bytes(8))


def test_a_runtime_without_the_event_tracer_is_named_in_one_line_exit_3(toy, golden, tmp_path, monkeypatch,
                                                                        capsys) -> None:
    """PyPI's aarch64 ExecuTorch 1.1.0 writes no ETDump (built without the event tracer): the
    trace says so instead of failing on the missing file."""

    class Untraced:
        def __init__(self, module) -> None:
            self.module = module

        def forward(self, inputs):
            return self.module.forward(inputs)

        def write_etdump_result_to_file(self, etdump, debug) -> None:  # what that build does: writes nothing
            pass

    load = pte_trace._traced_module
    monkeypatch.setattr(pte_trace, "_traced_module", lambda model, size: Untraced(load(model, size)))
    out = tmp_path / "t.json"
    assert main(["record", str(toy), str(golden), str(out)]) == pte_trace.NO_EVENT_TRACER_EXIT == 3
    err = capsys.readouterr().err
    assert err.startswith("pte_trace: error: this ExecuTorch runtime (executorch ") and err.count("\n") == 1
    assert err.endswith(") records no ETDump: it was built without its event tracer (EXECUTORCH_ENABLE_EVENT_TRACER); "
                        "trace with one that has it\n") and not out.exists()


def test_a_runtime_whose_release_is_unknown_says_so(monkeypatch) -> None:
    import importlib.metadata

    def unknown(name):
        raise importlib.metadata.PackageNotFoundError(name)

    monkeypatch.setattr(importlib.metadata, "version", unknown)
    assert pte_trace._release() == "executorch, release unknown"


def test_the_help_names_both_commands(capsys) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert ("record digests of every instruction output at every golden step, on this machine compare where two "
            "machines' instruction outputs part (host first) ") in out


def test_an_etdump_of_no_steps_holds_nothing(monkeypatch) -> None:
    from executorch.devtools.etdump import serialize

    from types import SimpleNamespace as V

    init = V(events=[V(profile_event=V(name="Method::init"), debug_event=None)])
    monkeypatch.setattr(serialize, "deserialize_from_etdump_flatcc", lambda data: V(run_data=[init]))
    assert pte_trace.instruction_outputs(b"", b"") == ([], [], 0)


def test_steps_that_ran_other_instructions_are_not_one_programs(monkeypatch) -> None:
    from executorch.devtools.etdump import serialize

    from types import SimpleNamespace as V

    def run(instruction):
        value = V(tensor=V(scalar_type=6, sizes=[1], offset=0), tensor_list=None)
        return V(events=[V(profile_event=None, debug_event=V(instruction_id=instruction, debug_entry=value))])

    monkeypatch.setattr(serialize, "deserialize_from_etdump_flatcc", lambda data: V(run_data=[run(3), run(4)]))
    with pytest.raises(ValueError, match="^step 1 ran other instructions than step 0: not one program's steps$"):
        pte_trace.instruction_outputs(b"", bytes(4))


@pytest.mark.parametrize("later, message", [
    ("other", "^steps from 1 ran other instructions than step 0: not one program's steps$"),
    ("short", "^ETDump holds 1 of steps 1-2$"),
])
def test_a_chunk_of_another_program_or_missing_steps_is_refused(toy, golden, monkeypatch, later, message) -> None:
    first = ([{"instruction": 1, "output": 0}], [["a"]], 100)
    chunks = iter([first, ([{"instruction": 2, "output": 0}], [["b"], ["c"]], 100) if later == "other"
                   else (first[0], [["b"]], 100)])
    monkeypatch.setattr(pte_trace, "CHUNK_STEPS", 2)
    monkeypatch.setattr(pte_trace, "_written", lambda traced: next(chunks))
    with pytest.raises(ValueError, match=message):
        record(toy, golden, steps=3)


def test_item_sizes_are_those_of_the_etdump_scalar_types_torch_names() -> None:
    """Each ETDump scalar type the trace reads takes the bytes torch's dtype of that name takes."""
    import torch
    from executorch.devtools.etdump.schema_flatcc import ScalarType

    dtypes = {"BYTE": torch.uint8, "CHAR": torch.int8, "SHORT": torch.int16, "INT": torch.int32, "LONG": torch.int64,
              "HALF": torch.float16, "FLOAT": torch.float32, "DOUBLE": torch.float64, "BOOL": torch.bool,
              "BFLOAT16": torch.bfloat16}
    assert pte_trace._ITEM_BYTES == {ScalarType[name].value: torch.empty(0, dtype=dtype).element_size()
                                     for name, dtype in dtypes.items()}
