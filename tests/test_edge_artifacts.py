"""ExecuTorch (.pte) and LiteRT (.tflite) artifacts of the trained tiny against its ONNX graph:
the golden check (the runtime carrying its own states), the state layout's round trip, the
torch-free LiteRT runner, batches stepped row by row, and every bad input of docs/edge.md."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.cli import main
from e3dpsm.errors import DataError
from e3dpsm.golden.check import check_golden
from e3dpsm.golden.store import load_golden
from e3dpsm.golden.tolerances import PROFILES
from e3dpsm.runtime.stepping import open_stepper

RUNTIMES = ["executorch", "litert"]


@pytest.mark.parametrize("artifact", RUNTIMES, indirect=True)
def test_golden_check_passes_against_the_onnx_graph(artifact, edge_golden, tmp_path, capsys) -> None:
    """fp32 profile: every pose within 0.01 mm of the ONNX graph's, every state within 1e-4 of
    its magnitude, at every step of a rollout whose states the artifact's runtime carries."""
    assert main(["golden", "check", "--model", str(artifact), "--golden", str(edge_golden), "--out",
                 str(tmp_path / "chk"), "--threads", "1"]) == 0
    report = json.loads((tmp_path / "chk" / "check.json").read_text())
    assert report["passed"] and report["runtime"] == open_stepper(artifact).runtime
    pose = next(t for t in report["tensors"] if t["name"] == "pose")
    assert 0 < pose["max"] < 0.01  # not bit-equal: XNNPACK's kernels are not ONNX Runtime's
    assert "PASSED" in capsys.readouterr().out


def test_several_artifacts_are_reported_by_the_runtime_each_ran_on(pte_path, tflite_path, edge_golden,
                                                                     tmp_path) -> None:
    assert main(["golden", "check", "--model", str(pte_path), str(tflite_path), "--golden", str(edge_golden),
                 "--out", str(tmp_path / "chk"), "--threads", "1"]) == 0
    summary = json.loads((tmp_path / "chk" / "summary.json").read_text())
    folders = {Path(c["report"]).parent.name: c["runtime"] for c in summary["checks"]}
    assert folders == {f"{pte_path.stem}-executorch": "executorch", f"{tflite_path.stem}-litert": "litert"}
    assert all((tmp_path / "chk" / folder / "check.json").is_file() for folder in folders)


def test_an_int8_artifact_is_checked_against_the_hosts_rollout_of_it(tflite_path, edge_model, edge_golden,
                                                                       tmp_path) -> None:
    """A converted INT8 artifact says so in its metadata, as a quantised ONNX graph does: golden
    check holds it to the int8 profile (the task budget), and asks whether this device computes
    what the host computed for it, from the host rollout `golden record --also` keeps under the
    artifact's own runtime (not under onnxruntime, where the check would never find it)."""
    from e3dpsm.export.litert_export import LiteRTOptions, embed_contract
    from e3dpsm.golden.host import record_host_rollouts
    from e3dpsm.golden.verify import verify_graph

    content, _ = embed_contract(tflite_path.read_bytes(), edge_model, LiteRTOptions(), "int8",
                                {"budget": {"mpjpe_pct": 2.0}})
    path = tmp_path / "step_int8.tflite"
    path.write_bytes(content)
    meta = open_stepper(path, threads=1).meta
    assert meta.quantization == {"mode": "int8", "format": "litert", "budget": {"mpjpe_pct": 2.0}}
    golden = tmp_path / "golden"
    shutil.copytree(edge_golden, golden)
    entries = record_host_rollouts(golden, [path], ["onnxruntime", "openvino"], threads=1)
    assert [e["runtime"] for e in entries] == ["litert"]
    result, report = verify_graph(path, golden, threads=1)
    assert report["profile"]["name"] == "int8" and report["runtime"] == "litert"
    assert result.questions["same_as_host"] is True  # the same file, the same kernels
    assert report["model"]["quantization"]["budget"]["mpjpe_pct"] == 2.0
    fp32 = open_stepper(tflite_path, threads=1).meta
    assert fp32.quantization is None  # an fp32 artifact keeps the fp32 profile


class _Offset:
    """An artifact's runner whose fused pose is shifted by `offset_mm`: a known error."""

    def __init__(self, runner, offset_mm: float) -> None:
        self.runner, self.offset_mm, self.meta = runner, offset_mm, runner.meta

    def init_state(self, batch: int = 1):
        return self.runner.init_state(batch)

    def step(self, lnes, state, window_ms):
        out, state = self.runner.step(lnes, state, window_ms)
        return {**out, "pose": out["pose"] + np.float32(self.offset_mm)}, state


@pytest.mark.parametrize("offset_mm, passes", [(0.012, False), (0.004, True)])
def test_the_tolerance_bites_near_the_threshold(tflite_path, edge_golden, offset_mm, passes) -> None:
    """A pose 0.012 mm off fails the 0.01 mm limit, 0.004 mm passes (the runtime's own error
    is below 2e-3 mm here, test above)."""
    result = check_golden(_Offset(open_stepper(tflite_path, threads=1), offset_mm), load_golden(edge_golden),
                          PROFILES["fp32"])
    assert result.passed is passes
    pose = next(t for t in result.tensors if t.name == "pose")
    assert pose.errors.max() == pytest.approx(offset_mm, abs=2e-3)


@pytest.mark.parametrize("artifact", RUNTIMES, indirect=True)
def test_state_layout_round_trip(artifact, trained_graph) -> None:
    """artifact -> its metadata -> the same layout as the ONNX graph's (batch 1 fixed)."""
    onnx_meta = open_stepper(trained_graph).meta
    meta = open_stepper(artifact).meta
    assert [s.to_metadata() for s in meta.states] == [s.to_metadata() for s in onnx_meta.states]
    assert meta.outputs == [{**o, "shape": [1, *o["shape"][1:]]} for o in onnx_meta.outputs]
    assert meta.joints == onnx_meta.joints and meta.extra == onnx_meta.extra
    assert meta.frame_input["shape"] == [1, *onnx_meta.frame_input["shape"][1:]]
    assert meta.config["model_config"] == onnx_meta.config["model_config"] and meta.config["static_batch"] == 1


@pytest.mark.parametrize("artifact", RUNTIMES, indirect=True)
def test_a_batch_is_stepped_row_by_row(artifact) -> None:
    runner = open_stepper(artifact, threads=1)
    rng = np.random.default_rng(3)
    frames = (rng.random((2, *runner.meta.frame_input["shape"][1:])) < 0.05).astype(np.float32)
    both, state = runner.step(frames, runner.init_state(2), 20.0)
    for row in range(2):
        one, one_state = runner.step(frames[row:row + 1], runner.init_state(1), 20.0)
        np.testing.assert_array_equal(both["pose"][row], one["pose"][0])
        np.testing.assert_array_equal(state["fusion_cov"][row], one_state["fusion_cov"][0])


def test_litert_run_needs_no_torch(tflite_path, quant_data, tmp_path) -> None:
    """`e3dpsm run --model step.tflite` in a process where torch cannot be imported."""
    events = Path(quant_data).parent / "raw" / "seq_0003" / "events.h5"
    out = tmp_path / "poses.csv"
    code = (f"import sys; sys.modules['torch'] = None\n"
            f"from e3dpsm.cli import main\n"
            f"code = main(['run', '--model', {str(tflite_path)!r}, '--events', {str(events)!r}, '--out', {str(out)!r},"
            f" '--threads', '1', '--no-progress'])\n"
            f"assert 'torch' not in sys.modules or sys.modules['torch'] is None\n"
            f"sys.exit(code)")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    rows = out.read_text().splitlines()
    assert len(rows) > 10 and rows[0].startswith("t_us,")


# -- bad input: one line, exit 2, nothing written ------------------------------------------

def _fails_with(capsys, argv: list[str], *needles: str) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith(f"e3dpsm {argv[0]}: error:"), err
    for needle in needles:
        assert needle in err, err
    return err


@pytest.mark.parametrize("module, fmt, extra", [("executorch", "executorch", "executorch"),
                                                ("litert_torch", "litert", "litert"),
                                                ("coremltools", "coreml", "coreml")])
def test_a_missing_extra_names_its_install_line(monkeypatch, capsys, tmp_path, module, fmt, extra) -> None:
    monkeypatch.setitem(sys.modules, module, None)  # as if not installed
    out = tmp_path / "out"
    _fails_with(capsys, ["convert", fmt, "--variant", "tiny", "--out", str(out)], f'pip install -e ".[{extra}]"')
    assert not out.exists()


def test_a_missing_runtime_extra_is_one_line(monkeypatch, capsys, tflite_path, edge_golden, tmp_path) -> None:
    monkeypatch.setitem(sys.modules, "ai_edge_litert", None)
    _fails_with(capsys, ["golden", "check", "--model", str(tflite_path), "--golden", str(edge_golden), "--out",
                         str(tmp_path / "chk")], 'pip install -e ".[litert]"')
    assert not (tmp_path / "chk").exists()


def test_a_pte_from_another_executorch_version(pte_path, edge_golden, tmp_path, capsys) -> None:
    from e3dpsm.runtime.executorch_session import executorch_version

    recorded = f'\\"executorch\\": \\"{executorch_version()}\\"'.encode()
    content = pte_path.read_bytes()
    assert content.count(recorded) == 1
    other = tmp_path / "other_version.pte"
    other.write_bytes(content.replace(recorded, recorded.replace(executorch_version().encode(), b"0.9.9")))
    _fails_with(capsys, ["golden", "check", "--model", str(other), "--golden", str(edge_golden), "--out",
                         str(tmp_path / "chk")], "written by ExecuTorch 0.9.9")
    schema = tmp_path / "other_schema.pte"
    schema.write_bytes(content[:4] + b"ET99" + content[8:])  # another flatbuffer schema version
    _fails_with(capsys, ["golden", "check", "--model", str(schema), "--golden", str(edge_golden), "--out",
                         str(tmp_path / "chk")], "cannot load", "ET99")
    assert not (tmp_path / "chk").exists()


def test_a_pte_of_another_release_runs_when_asked(pte_path, tmp_path, monkeypatch) -> None:
    """E3DPSM_EXECUTORCH_OTHER_RELEASE=1 (the emulated aarch64 root's runtime is an older
    release): the same program, relabelled as written by 0.9.9, is read instead of refused."""
    from e3dpsm.runtime.executorch_session import OTHER_RELEASE_ENV, executorch_version, load_program, program_metadata

    recorded = f'\\"executorch\\": \\"{executorch_version()}\\"'.encode()
    other = tmp_path / "other_version.pte"
    other.write_bytes(pte_path.read_bytes().replace(recorded, recorded.replace(executorch_version().encode(), b"0.9.9")))
    monkeypatch.setenv(OTHER_RELEASE_ENV, "1")
    meta, artifact = program_metadata(other, load_program(other))
    assert artifact["versions"]["executorch"] == "0.9.9"
    assert meta == program_metadata(pte_path, load_program(pte_path))[0]
    monkeypatch.setenv(OTHER_RELEASE_ENV, "0")  # only "1" lets it through
    with pytest.raises(DataError) as refused:
        program_metadata(other, load_program(other))
    assert str(refused.value) == (f"{other} was written by ExecuTorch 0.9.9, this runtime is {executorch_version()}; "
                                  "convert it again here, or run it with executorch==0.9.9")


def _without_metadata(content: bytes, name: str) -> bytes:
    import flatbuffers
    from ai_edge_litert import schema_py_generated as schema

    model = schema.ModelT.InitFromPackedBuf(bytearray(content), 0)
    model.metadata = [m for m in model.metadata if m.name.decode() != name]
    builder = flatbuffers.Builder(len(content))
    builder.Finish(model.Pack(builder), file_identifier=b"TFL3")
    return bytes(builder.Output())


def test_a_tflite_without_the_state_layout(tflite_path, quant_data, tmp_path, capsys) -> None:
    bare = tmp_path / "bare.tflite"
    bare.write_bytes(_without_metadata(tflite_path.read_bytes(), "e3dpsm"))
    events = Path(quant_data).parent / "raw" / "seq_0003" / "events.h5"
    out = tmp_path / "poses.csv"
    _fails_with(capsys, ["run", "--model", str(bare), "--events", str(events), "--out", str(out)],
                "no e3dpsm state layout")
    assert not out.exists()


@pytest.mark.parametrize("artifact", RUNTIMES, indirect=True)
def test_a_mismatched_input_size(artifact, prepared_small, tmp_path, capsys) -> None:
    """Data prepared at 96 x 128 for an artifact that takes 192 x 256."""
    out = tmp_path / "val"
    _fails_with(capsys, ["validate", "--models", str(artifact), "--data", str(prepared_small), "--out", str(out),
                         "--split", "all"], "96 x 128")
    assert not out.exists()


def test_an_unknown_artifact_type(tmp_path, capsys, edge_golden) -> None:
    odd = tmp_path / "step.bin"
    odd.write_bytes(b"0" * 16)
    _fails_with(capsys, ["golden", "check", "--model", str(odd), "--golden", str(edge_golden), "--out",
                         str(tmp_path / "chk")], "unknown model file type")
