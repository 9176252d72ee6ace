"""e3dpsm/golden/artifact_trace.py on the toy programs (tests/_toy_pte.py, tests/_toy_tflite.py):
the host's half that `golden record --kernel-trace` keeps in the golden folder (digests against
numpy's codes), and the device half `golden check` runs where its rollout is not the host's,
naming the first tap or code apart."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from _golden_fakes import STATE_SHAPE, parted_record, write_golden
from e3dpsm.golden.artifact_trace import HOST_FILE, TAPS_PROGRAM, find_host_trace, record_host, run_device, trace_module

STEPS = 4


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _digest(array: np.ndarray) -> str:
    return hashlib.blake2b(np.ascontiguousarray(array).tobytes(), digest_size=8).hexdigest()


@pytest.fixture(scope="module")
def golden(tmp_path_factory) -> Path:
    return write_golden(tmp_path_factory.mktemp("golden") / "golden", STEPS)


@pytest.fixture(scope="module")
def programs(tmp_path_factory) -> dict[str, Path]:
    pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")
    from _toy_pte import toy_pte

    folder = tmp_path_factory.mktemp("et8")
    made = {"step.pte": toy_pte(precision="int8"), "step_taps.pte": toy_pte(precision="int8", taps=True),
            "alone.pte": toy_pte(precision="int8", pose_offset=0.25)}
    for name, content in made.items():
        (folder / name).write_bytes(content)
    return {name: folder / name for name in made}


def test_each_artifact_kind_has_its_trace() -> None:
    assert trace_module("a/step.pte").TRACE.name == "pte_taps"
    assert trace_module("a/step.tflite").TRACE.name == "tflite_trace"
    assert trace_module("a/step_int8.onnx") is None and trace_module("a/step.mlpackage") is None
    with pytest.raises(ValueError, match=r"^a/q\.onnx: an artifact trace is of a \.tflite or a \.pte$"):
        record_host("golden", "a/q.onnx", 3)


def test_a_ptes_taps_program_travels_in_the_golden_with_the_hosts_digests(golden, programs) -> None:
    from _toy_pte import toy_taps

    from e3dpsm.golden.store import load_golden

    shipped = programs["step.pte"]
    folder, what = record_host(golden, shipped, STEPS - 1)
    assert folder == golden / "kernels" / f"step-{_sha256(shipped)[:12]}" and what == f"{STEPS - 1} steps of 2 taps"
    assert (folder / TAPS_PROGRAM).read_bytes() == programs["step_taps.pte"].read_bytes()
    host = json.loads((folder / HOST_FILE).read_text())
    assert (host["model"], host["sha256"], host["trace"], host["program"]) == (
        "step.pte", _sha256(shipped), "pte_taps", TAPS_PROGRAM)
    stored, state = load_golden(golden), np.zeros((1, *STATE_SHAPE), np.float32)
    assert host["steps"] == STEPS - 1 and len(host["digests"]) == STEPS - 1
    for step in range(STEPS - 1):
        state = state + np.float32(stored.window_ms(step))
        assert host["digests"][step] == [_digest(t) for t in toy_taps(stored.frame(step)[None], state)], step
    assert find_host_trace(golden, _sha256(shipped)) == folder
    assert find_host_trace(golden, _sha256(programs["alone.pte"])) is None and find_host_trace(golden, None) is None
    assert sorted(p.name for p in folder.parent.iterdir()) == [folder.name]  # no temporary left


def test_a_pte_without_its_taps_program_is_not_traced(golden, programs) -> None:
    folder, why = record_host(golden, programs["alone.pte"], STEPS)
    assert folder is None and why == ("no alone_taps.pte beside it to trace (write it with `e3dpsm convert "
                                      "executorch --quantize int8 --taps`)")
    assert run_device(golden, programs["alone.pte"], _sha256(programs["alone.pte"])) is None


def test_a_taps_program_of_another_conversion_is_refused_and_nothing_written(tmp_path, programs) -> None:
    from _toy_pte import toy_pte

    from e3dpsm.errors import DataError

    golden = write_golden(tmp_path / "golden", STEPS)
    shipped = tmp_path / "step.pte"
    shipped.write_bytes(programs["step.pte"].read_bytes())
    (tmp_path / "step_taps.pte").write_bytes(toy_pte(precision="int8", taps=True, pose_offset=0.5))
    with pytest.raises(DataError, match=rf"^{tmp_path}/step_taps\.pte does not compute step\.pte's steps \(they "
                                        r"differ from step 0\): write both with one `e3dpsm convert executorch "
                                        r"--quantize int8 --taps`$"):
        record_host(golden, shipped, STEPS)
    assert not (golden / "kernels").exists()


def test_the_device_half_names_the_first_tap_apart(tmp_path, programs) -> None:
    golden = write_golden(tmp_path / "golden", STEPS)
    shipped = programs["step.pte"]
    folder, _ = record_host(golden, shipped, STEPS)
    same = run_device(golden, shipped, _sha256(shipped))
    assert same["trace"] == "pte_taps" and same["first_step"] is None and same["steps"] == STEPS
    assert same["summary"] == f"all 2 taps the same at every one of {STEPS} steps"
    host = json.loads((folder / HOST_FILE).read_text())
    parted = parted_record(parted_record(host, 2, [0]), 1, [1])  # tap 1 from step 1, tap 0 from step 2
    (folder / HOST_FILE).write_text(json.dumps(parted))
    apart = run_device(golden, shipped, _sha256(shipped))
    assert apart["first_step"] == 1 and [t["tap"] for t in apart["first_departures"]] == ["toy.state:codes"]
    assert apart["apart_by_end"] == 2 and apart["summary"].startswith(
        "taps part first at step 1, first in program order toy.state:codes (tap 1, after add, round, clamp)")


def test_a_tflites_codes_are_traced_from_the_artifact_itself(tmp_path) -> None:
    pytest.importorskip("ai_edge_litert", reason="ai-edge-litert (pip extra litert) is not installed")
    from _toy_tflite import toy_tflite

    from e3dpsm.golden.tflite_trace import record

    golden = write_golden(tmp_path / "golden", STEPS)
    model = tmp_path / "step_int8.tflite"
    model.write_bytes(toy_tflite())
    folder, what = record_host(golden, model, STEPS)
    assert what == f"{STEPS} steps of 2 code tensors" and not (folder / TAPS_PROGRAM).exists()
    host = json.loads((folder / HOST_FILE).read_text())
    assert host["program"] is None and host["trace"] == "tflite_trace"
    assert host["digests"] == record(model, golden, STEPS)["digests"]
    host["digests"][3][1] = "0" * 16
    (folder / HOST_FILE).write_text(json.dumps(host))
    apart = run_device(golden, model, _sha256(model))
    assert apart["first_step"] == 3 and [c["name"] for c in apart["first_departures"]] == ["e3dpsm_code_1"]


def test_a_tflite_that_rounds_nothing_at_run_time_has_no_trace(tmp_path, monkeypatch) -> None:
    from e3dpsm.golden import artifact_trace

    monkeypatch.setattr(artifact_trace, "_has_codes", lambda model: False)
    folder, why = record_host(tmp_path, tmp_path / "step.tflite", STEPS)
    assert folder is None and why == "no quantised activations (nothing is rounded at run time)"
    assert not (tmp_path / "kernels").exists()


def test_golden_record_and_check_say_where_in_one_line_each(golden, programs, tmp_path, capsys) -> None:
    """The CLI halves: `golden record --kernel-trace` with an INT8 .pte (traced by its taps, or
    not, saying why), and the line `golden check` prints from check.json's code_trace."""
    import types

    from e3dpsm.cli.golden import _print_check, _record_kernel_traces

    _record_kernel_traces(str(golden), [str(programs["step.pte"]), str(programs["alone.pte"])], 2)
    folder = golden / "kernels" / f"step-{_sha256(programs['step.pte'])[:12]}"
    assert capsys.readouterr().out.splitlines() == [
        f"golden record: code trace of step.pte: 2 steps of 2 taps -> {folder}",
        "golden record: no code trace of alone.pte: no alone_taps.pte beside it to trace (write it with `e3dpsm "
        "convert executorch --quantize int8 --taps`)"]
    result = types.SimpleNamespace(profile=types.SimpleNamespace(name="int8"), summary=lambda: "FAILED", tensors=[],
                                   budget=None)
    report = {"ms_per_step": 1.0, "isa": {"host": {"kind": "dotprod", "flags": ["asimddp"]}, "same_kind": None},
              "budget_runtimes": {"checked_here": None},
              "code_trace": {"trace": "pte_taps", "steps": 60, "summary": "taps part first at step 4, ..."}}
    _print_check("step.pte", "executorch", result, report, tmp_path)
    assert capsys.readouterr().out.splitlines()[-1] == (
        "  where this machine departs from the host (pte_taps, 60 steps): taps part first at step 4, ...")


def test_the_names_in_the_golden_and_one_thread_unless_told(golden, programs, monkeypatch) -> None:
    """The file names docs/golden-and-diagnose.md gives, and both halves on one thread unless
    told, as the kernel trace of a QDQ graph runs."""
    from e3dpsm.golden import pte_taps

    assert (HOST_FILE, TAPS_PROGRAM) == ("host_trace.json", "step_taps.pte")
    seen, real = [], pte_taps.record
    monkeypatch.setattr(pte_taps, "record", lambda model, golden_dir, steps, threads: (
        seen.append(threads) or real(model, golden_dir, steps, threads)))
    shipped = programs["step.pte"]
    record_host(golden, shipped, 2)
    run_device(golden, shipped, _sha256(shipped))
    record_host(golden, shipped, 2, threads=3)
    run_device(golden, shipped, _sha256(shipped), threads=2)
    assert seen == [1, 1, 3, 2]
