"""The LiteRT converter's own work after litert-torch has converted (export/litert_export.py):
the operator histogram, the XNNPACK partitions, the short tensor names, the contract embedded
and the file written, on the numpy-sized `.tflite` of tests/_toy_tflite.py. litert-torch's
conversion itself runs in the edge fixtures (tests/_edge_helpers.py)."""
from __future__ import annotations

import sys
import time

import pytest

pytest.importorskip("ai_edge_litert", reason="ai-edge-litert (pip extra litert) is not installed")

from _model_helpers import converter_tiny  # noqa: E402
from _io_helpers import record_temporaries  # noqa: E402
from _toy_tflite import toy_tflite  # noqa: E402
from e3dpsm.export import litert_export  # noqa: E402
from e3dpsm.export.edge_export import artifact_contract  # noqa: E402
from e3dpsm.export.litert_export import (MAC_OPS, LiteRTOptions, convert_litert, delegate_partitions, embed_contract,  # noqa: E402
                                         tflite_op_histogram, write_litert)
from e3dpsm.runtime.artifact_metadata import EMBEDDED_NAME, decode  # noqa: E402
from e3dpsm.runtime.tflite_metadata import is_short_tensor_name, read_metadata  # noqa: E402


@pytest.fixture(scope="module")
def model():
    return converter_tiny()


def _tensor_names(content: bytes) -> list[str]:
    from ai_edge_litert import schema_py_generated as schema

    graph = schema.Model.GetRootAs(content, 0).Subgraphs(0)
    return [graph.Tensors(i).Name().decode() for i in range(graph.TensorsLength())]


def test_the_histogram_counts_builtins_most_frequent_first() -> None:
    assert list(tflite_op_histogram(toy_tflite()).items()) == [("QUANTIZE", 2), ("ADD", 1), ("DEQUANTIZE", 1)]
    assert MAC_OPS == ("CONV_2D", "DEPTHWISE_CONV_2D", "FULLY_CONNECTED", "BATCH_MATMUL")


def test_the_toys_delegated_partitions_are_counted() -> None:
    # XNNPACK takes the ADD and the QUANTIZE / DEQUANTIZE it supports; the count is what the
    # interpreter reports as DELEGATE nodes.
    from ai_edge_litert.interpreter import Interpreter

    interpreter = Interpreter(model_content=toy_tflite(), num_threads=1)
    interpreter.allocate_tensors()
    expected = sum(1 for d in interpreter._get_ops_details() if d["op_name"] == "DELEGATE")
    assert delegate_partitions(toy_tflite()) == expected >= 1
    assert delegate_partitions(toy_tflite(), threads=2) == expected


@pytest.mark.parametrize("keep_names", [False, True])
def test_write_litert_embeds_the_contract_and_reports_the_file(model, tmp_path, monkeypatch, keep_names) -> None:
    monkeypatch.setattr(litert_export, "MAC_OPS", ("QUANTIZE", "CONV_2D"))  # the toy has no multiply-accumulates
    path = tmp_path / "out" / "step.tflite"
    options = LiteRTOptions(attention_form="grid_sample", keep_tensor_names=keep_names)
    result = write_litert(toy_tflite(), model, path, options, "int8", {"convert": 1.5, "quantize": 2.25},
                          {"budget": {"limit_pct": 1.0}, "calibration": "x"})
    content = path.read_bytes()
    assert result.path == str(path) and result.bytes == len(content)
    assert [p.name for p in path.parent.iterdir()] == ["step.tflite"]
    names = _tensor_names(content)
    assert all(is_short_tensor_name(n) for n in names) is not keep_names
    if keep_names:
        assert names == _tensor_names(toy_tflite())
    meta, record = decode(read_metadata(content)[EMBEDDED_NAME], "x")
    expected_meta, expected_record = artifact_contract(model, "litert", "int8", "grid_sample",
                                                       ("litert-torch", "ai-edge-litert"),
                                                       {"budget": {"limit_pct": 1.0}, "calibration": "x"})
    assert meta.to_props() == expected_meta.to_props()  # as text: JSON gives tuples back as lists
    assert record == expected_record and result.artifact == record
    assert meta.quantization["mode"] == "int8" and set(record["versions"]) == {"torch", "litert-torch", "ai-edge-litert"}
    assert result.ops == {"histogram": {"QUANTIZE": 2, "ADD": 1, "DEQUANTIZE": 1}, "mac_ops": {"QUANTIZE": 2},
                          "xnnpack_partitions": delegate_partitions(content)}
    assert result.options == {"attention_form": "grid_sample", "keep_tensor_names": keep_names}
    seconds = result.seconds
    assert list(seconds) == ["convert", "quantize", "write", "total"] and seconds["convert"] == 1.5
    assert seconds["total"] == round(1.5 + 2.25 + seconds["write"], 2) and seconds["write"] == round(seconds["write"], 2)
    assert result.to_dict()["ops"] == result.ops


def test_the_embedded_contract_is_an_fp32_artifacts_by_default(model) -> None:
    content, record = embed_contract(toy_tflite(), model, LiteRTOptions(), "fp32")
    meta, embedded = decode(read_metadata(content)[EMBEDDED_NAME], "x")
    assert embedded == record and record["precision"] == "fp32" and record["attention_form"] == "gather"
    assert meta.quantization is None and meta.config["format"] == "litert"
    assert LiteRTOptions() == LiteRTOptions(attention_form="gather", keep_tensor_names=False)


def test_the_written_file_goes_through_a_hidden_tflite_temporary_timed_in_seconds(model, tmp_path,
                                                                                 monkeypatch) -> None:
    import dataclasses

    temporaries = record_temporaries(monkeypatch, litert_export)
    result = write_litert(toy_tflite(), model, tmp_path / "step.tflite", LiteRTOptions(), "fp32", {})
    assert len(temporaries) == 1 and temporaries[0].startswith(".step.tflite.") and temporaries[0].endswith(".tflite")
    assert 0 <= result.seconds["write"] < 60
    with pytest.raises(dataclasses.FrozenInstanceError):
        LiteRTOptions().attention_form = "grid_sample"
    bare = litert_export.LiteRTResult(path="p", bytes=1, seconds={}, ops={}, options={})
    assert bare.to_dict()["artifact"] == {}


@pytest.fixture()
def converted(monkeypatch):
    """litert_content replaced by the toy after 12 ms: what convert_litert asked for, in order."""
    calls = []

    def content(model, options):
        calls.append((model, options))
        time.sleep(0.0123)
        return toy_tflite()

    monkeypatch.setattr(litert_export, "litert_content", content)
    return calls


def test_convert_litert_writes_the_content_it_converted_timed_in_hundredths(model, tmp_path, converted) -> None:
    options = LiteRTOptions(attention_form="grid_sample")
    result = convert_litert(model, tmp_path / "step.tflite", options)
    assert converted == [(model, options)]
    assert (tmp_path / "step.tflite").read_bytes() == open(result.path, "rb").read()
    assert result.artifact["precision"] == "fp32" and result.artifact["attention_form"] == "grid_sample"
    assert "calibration" not in result.artifact
    seconds = result.seconds
    assert list(seconds) == ["convert", "write", "total"]
    assert 0.01 <= seconds["convert"] < 60 and seconds["convert"] == round(seconds["convert"], 2)
    assert seconds["total"] == round(seconds["convert"] + seconds["write"], 2)


def test_convert_litert_passes_the_precision_and_record_on(model, tmp_path, converted) -> None:
    result = convert_litert(model, tmp_path / "step.tflite", LiteRTOptions(), "int8", {"calibration": "x"})
    meta, record = decode(read_metadata((tmp_path / "step.tflite").read_bytes())[EMBEDDED_NAME], "x")
    assert record == result.artifact and record["precision"] == "int8" and record["calibration"] == "x"
    assert meta.quantization["mode"] == "int8"


@pytest.mark.parametrize("missing", ["litert_torch", "ai_edge_litert"])
def test_litert_content_names_the_extra_of_a_missing_converter(model, monkeypatch, missing) -> None:
    from e3dpsm.errors import ConfigError

    pytest.importorskip("litert_torch")  # imported first: it imports ai_edge_litert itself
    monkeypatch.setitem(sys.modules, missing, None)
    with pytest.raises(ConfigError, match=rf"^{missing} is not installed \(to write \.tflite models\): "
                                          r'pip install -e "\.\[litert\]"$'):
        litert_export.litert_content(model)
