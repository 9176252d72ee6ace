"""The step contract carried by non-ONNX artifacts (e3dpsm/runtime/artifact_metadata.py) and
the TFLite metadata table it lives in (e3dpsm/runtime/tflite_metadata.py), on hand-built
flatbuffers (the TFLite schema's own `ModelT`), read back with the schema's reader: named
buffers set, replaced and read, a buffer stored past the flatbuffer (as ai-edge-quantizer
writes large weights) read from its offset and moved inside on a rewrite."""
from __future__ import annotations

import json

import numpy as np
import pytest

from _edge_helpers import skip_without
from e3dpsm.graph_metadata import GraphMetadata, MetadataError
from e3dpsm.runtime import artifact_metadata
from e3dpsm.state import StateSpec

META = GraphMetadata(states=(StateSpec("s5_re", (2, 3)), StateSpec("pose_state", (4,), init=(0.0, 1.0, 2.0, 3.0))),
                     inputs={"frame": {"name": "lnes", "shape": [1, 2, 8, 8]}, "window": {"name": "window_ms"}},
                     outputs=[{"name": "pose"}], config={"variant": "tiny", "train_window_ms": 20.0},
                     joints=["head", "neck"], quantization={"mode": "int8"}, extra={"e3dpsm.parents": "[-1, 0]"})
ARTIFACT = {"format": "litert", "precision": "int8", "versions": {"litert_torch": "0.10.0"}}


def test_the_contract_round_trips_and_its_text_does_not_depend_on_key_order() -> None:
    text = artifact_metadata.encode(META, ARTIFACT)
    assert artifact_metadata.decode(text, "x") == (META, ARTIFACT)
    assert artifact_metadata.decode(text.encode("utf-8"), "x") == (META, ARTIFACT)
    assert artifact_metadata.encode(META, dict(reversed(list(ARTIFACT.items())))) == text
    props = json.loads(text)
    assert list(props) == sorted(props)
    assert json.loads(props[artifact_metadata.KEY_ARTIFACT]) == ARTIFACT and props["e3dpsm.artifact"]
    assert all(isinstance(value, str) for value in props.values())  # as an ONNX graph's metadata_props
    without = {k: v for k, v in props.items() if k != "e3dpsm.artifact"}
    assert artifact_metadata.decode(json.dumps(without), "x") == (META, {})  # written before the record existed


def test_the_places_a_runtime_reads_are_the_documented_ones() -> None:
    """docs/edge.md's table of where each format keeps the contract: what runners on other
    machines (and other people's tools) look for."""
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "edge.md").read_text(encoding="utf-8")
    assert f"| `.pte` | a constant method `{artifact_metadata.PTE_METHOD}` returning the JSON" in doc
    assert f"| `.tflite` | a model metadata buffer named `{artifact_metadata.EMBEDDED_NAME}`" in doc
    assert (artifact_metadata.PTE_METHOD, artifact_metadata.EMBEDDED_NAME) == ("e3dpsm_metadata", "e3dpsm")


@pytest.mark.parametrize("text, why", [
    ("[1, 2]", "expected an object of strings"),
    ('{"e3dpsm.states": 3}', "expected an object of strings"),
    ('{"e3dpsm.artifact": "{no"}', "Expecting property name"),
    ("not json", "Expecting value"),
])
def test_broken_contract_text_is_one_metadata_error(text, why) -> None:
    with pytest.raises(MetadataError) as info:
        artifact_metadata.decode(text, "step.pte")
    assert str(info.value).startswith(f"step.pte carries broken e3dpsm metadata: {why}")


def test_a_sidecar_sits_beside_its_artifact(tmp_path) -> None:
    engine = tmp_path / "step.engine"
    assert artifact_metadata.sidecar_path(engine) == tmp_path / "step.engine.json"
    assert artifact_metadata.sidecar_path("v1.2/step.plan") == artifact_metadata.sidecar_path("v1.2/step.plan")
    assert str(artifact_metadata.sidecar_path("v1.2/step.plan")) == "v1.2/step.plan.json"
    with pytest.raises(MetadataError) as info:
        artifact_metadata.read_sidecar(engine)
    assert str(info.value) == (f"{engine} has no state layout: step.engine.json is not beside it (the converter "
                               "writes it; copy it with the artifact)")
    (tmp_path / "step.engine.json").write_text(artifact_metadata.encode(META, ARTIFACT), encoding="utf-8")
    assert artifact_metadata.read_sidecar(engine) == (META, ARTIFACT)
    (tmp_path / "step.engine.json").write_text("[]", encoding="utf-8")
    with pytest.raises(MetadataError, match=r"step\.engine\.json carries broken e3dpsm metadata"):
        artifact_metadata.read_sidecar(engine)


# ---- tflite_metadata.py ---------------------------------------------------------------------------------
def _flatbuffer(tensors: int = 3, outside: bytes = b"", placeholder_offset: bool = False) -> bytes:
    """A TFLite model of one subgraph with `tensors` named tensors and, with `outside`, one
    buffer whose bytes lie past the flatbuffer (offset, size), named as metadata `outside`."""
    import flatbuffers
    from ai_edge_litert import schema_py_generated as schema

    model = schema.ModelT()
    model.version = 3
    graph = schema.SubGraphT()
    graph.tensors = []
    for t in range(tensors):
        tensor = schema.TensorT()
        tensor.name = f"e3dpsm.layers.residual.EncoderStage_{t}/conv;{t}"
        tensor.shape = [1, t + 1]
        graph.tensors.append(tensor)
    model.subgraphs = [graph]
    model.buffers = [schema.BufferT()]
    metadata = schema.MetadataT()
    metadata.name, metadata.buffer = "min_runtime_version", 1
    first = schema.BufferT()
    first.data = np.frombuffer(b"1.5.0\0", np.uint8)
    if placeholder_offset:
        first.offset, first.size = 1, 1
    model.buffers.append(first)
    model.metadata = [metadata]

    def pack() -> bytes:
        builder = flatbuffers.Builder(1024)
        builder.Finish(model.Pack(builder), file_identifier=b"TFL3")
        return bytes(builder.Output())

    if not outside:
        return pack()
    far = schema.BufferT()
    far.offset, far.size = 1, len(outside)  # placeholders of the packed size, fixed below
    model.buffers.append(far)
    entry = schema.MetadataT()
    entry.name, entry.buffer = "outside", len(model.buffers) - 1
    model.metadata.append(entry)
    size = len(pack())
    far.offset = size + 16  # past the flatbuffer, 16-byte aligned padding between
    assert len(pack()) == size  # the offset's value does not change the packed size
    return pack() + b"\0" * 16 + outside


def test_metadata_entries_are_set_replaced_and_read_by_name() -> None:
    skip_without("ai_edge_litert")
    from e3dpsm.runtime import tflite_metadata

    content = _flatbuffer()
    assert tflite_metadata.read_metadata(content) == {"min_runtime_version": b"1.5.0\0"}
    once = tflite_metadata.with_metadata(content, "e3dpsm", b'{"a": "1"}')
    assert tflite_metadata.read_metadata(once) == {"min_runtime_version": b"1.5.0\0", "e3dpsm": b'{"a": "1"}'}
    twice = tflite_metadata.with_metadata(once, "e3dpsm", b"")
    assert tflite_metadata.read_metadata(twice) == {"min_runtime_version": b"1.5.0\0", "e3dpsm": b""}
    assert twice[4:8] == b"TFL3"
    with pytest.raises(ValueError) as info:
        tflite_metadata.read_metadata(b"\0" * 4 + b"TFL2" + content[8:])
    assert str(info.value) == "not a TFLite flatbuffer (no TFL3 identifier)"


def test_a_buffer_whose_offset_is_one_keeps_its_data_inside() -> None:
    """The TFLite schema (schema.fbs, Buffer): data lies outside the flatbuffer only "if offset
    > 1"; an offset of 1 is a placeholder and the buffer's own data counts."""
    skip_without("ai_edge_litert")
    from e3dpsm.runtime import tflite_metadata

    content = _flatbuffer(placeholder_offset=True)
    assert tflite_metadata.read_metadata(content) == {"min_runtime_version": b"1.5.0\0"}
    rewritten = tflite_metadata.with_metadata(content, "e3dpsm", b"y")
    assert tflite_metadata.read_metadata(rewritten) == {"min_runtime_version": b"1.5.0\0", "e3dpsm": b"y"}


def test_a_buffer_past_the_flatbuffer_is_read_there_and_moved_inside_on_a_rewrite() -> None:
    skip_without("ai_edge_litert")
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.runtime import tflite_metadata

    payload = bytes(range(200)) * 3
    content = _flatbuffer(outside=payload)
    assert tflite_metadata.read_metadata(content)["outside"] == payload
    rewritten = tflite_metadata.with_metadata(content, "e3dpsm", b"x")
    assert tflite_metadata.read_metadata(rewritten) == {"min_runtime_version": b"1.5.0\0", "outside": payload,
                                                        "e3dpsm": b"x"}
    model = schema.ModelT.InitFromPackedBuf(bytearray(rewritten), 0)
    assert all(buffer.offset in (0, None) for buffer in model.buffers) and len(rewritten) > len(payload)


def test_short_tensor_names_replace_module_paths_and_nothing_else() -> None:
    skip_without("ai_edge_litert")
    from ai_edge_litert import schema_py_generated as schema

    from e3dpsm.runtime import tflite_metadata

    content = _flatbuffer(tensors=12)
    short = tflite_metadata.with_short_tensor_names(content)
    graph = schema.ModelT.InitFromPackedBuf(bytearray(short), 0).subgraphs[0]
    assert [t.name.decode() for t in graph.tensors] == [f"s0t{t}" for t in range(12)]
    assert [list(t.shape) for t in graph.tensors] == [[1, t + 1] for t in range(12)]
    assert len(short) < len(content) and tflite_metadata.read_metadata(short) == tflite_metadata.read_metadata(content)
    assert [tflite_metadata.is_short_tensor_name(n) for n in ("s0t12", "s10t0", "s0t", "st1", "s0t1x", "xs0t1",
                                                               "model.s0t1")] == [True, True] + [False] * 5
    assert tflite_metadata.short_tensor_name(2, 31) == "s2t31"
