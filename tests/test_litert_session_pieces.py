"""The LiteRT step session (runtime/litert_session.py) and what every edge artifact's session
shares (runtime/artifact_session.py), on the numpy-sized `.tflite` of tests/_toy_tflite.py: the
numbers it steps against numpy, a batch of streams stepped row by row, and each way a file is
refused, in one line naming it."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("ai_edge_litert", reason="ai-edge-litert (pip extra litert) is not installed")

from _golden_fakes import FRAME, STATE  # noqa: E402
from _toy_tflite import toy_pose, toy_tflite  # noqa: E402
from e3dpsm.errors import DataError, InputError  # noqa: E402
from e3dpsm.graph_metadata import MetadataError  # noqa: E402
from e3dpsm.runtime.litert_session import LiteRTStepSession  # noqa: E402


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "step.tflite"
    path.write_bytes(toy_tflite())
    return path


def test_a_step_gives_the_toys_pose_and_carries_its_state(toy) -> None:
    session = LiteRTStepSession(toy, threads=1)
    assert session.runtime == "litert" and session.path == toy and [s.name for s in session.meta.states] == [STATE]
    rng = np.random.default_rng(0)
    state = session.init_state(1)
    np.testing.assert_array_equal(state[STATE], np.zeros((1, 6), np.float32))
    for window in (20.0, 33.0):
        lnes = rng.uniform(0, 1, (1, *FRAME)).astype(np.float32)
        outputs, new_state = session.step(lnes, state, window)
        assert list(outputs) == ["pose"]
        np.testing.assert_allclose(outputs["pose"], toy_pose(lnes), rtol=0, atol=1e-7)
        np.testing.assert_array_equal(new_state[STATE], state[STATE] + np.float32(window))
        state = new_state


def test_a_batch_is_stepped_row_by_row_and_put_back_together(toy) -> None:
    """Three streams with their own windows and states: each row as if stepped alone."""
    session = LiteRTStepSession(toy, threads=1)
    rng = np.random.default_rng(1)
    lnes = rng.uniform(0, 1, (3, *FRAME)).astype(np.float32)
    state = {STATE: rng.normal(0, 5, (3, 6)).astype(np.float32)}
    windows = np.array([10.0, 20.0, 40.0], np.float32)
    outputs, new_state = session.run_feeds(session.feeds(lnes, state, windows))
    assert outputs["pose"].shape == (3, *FRAME) and new_state[STATE].shape == (3, 6)
    for row in range(3):
        alone, alone_state = session.step(lnes[row:row + 1], {STATE: state[STATE][row:row + 1]}, float(windows[row]))
        np.testing.assert_array_equal(outputs["pose"][row:row + 1], alone["pose"])
        np.testing.assert_array_equal(new_state[STATE][row:row + 1], alone_state[STATE])
    np.testing.assert_array_equal(new_state[STATE], state[STATE] + windows[:, None])


def _rewritten(edit) -> bytes:
    from e3dpsm.runtime.tflite_metadata import rewrite_model

    return rewrite_model(toy_tflite(), edit)


def _without_metadata(model) -> None:
    model.metadata = []


def _broken_metadata(model) -> None:
    model.buffers[model.metadata[0].buffer].data = np.frombuffer(b"{not json", np.uint8)


def _state_output_renamed(model) -> None:
    for entry in model.signatureDefs[0].outputs:
        if entry.name.decode().startswith("s_"):
            entry.name = b"renamed"


def _no_signature(model) -> None:
    model.signatureDefs = []


@pytest.mark.parametrize("content, error, message", [
    (None, DataError, r"^model {path} does not exist$"),
    (b"ONNX" * 8, DataError, r"^{path} is not a TFLite model \(no TFL3 identifier\)$"),
    (b"\x08\x00\x00\x00TFL3" + b"\xff" * 24, DataError, r"^{path} is not a readable TFLite model: "),
    ("without metadata", MetadataError, r"^{path} carries no e3dpsm state layout \(no 'e3dpsm' metadata buffer\); "
                                        r"write it with `e3dpsm convert litert`$"),
    ("broken metadata", MetadataError, r"^{path} carries broken e3dpsm metadata: "),
    ("renamed output", InputError, r"^{path}: inputs \[.*\] / outputs \[.*'renamed'.*\] do not match its metadata "
                                   r"\(.*\); convert it again$"),
    ("no signature", DataError, r"^LiteRT cannot load {path}: "),
])
def test_a_file_that_is_not_a_step_model_is_one_error_naming_it(tmp_path, content, error, message) -> None:
    edits = {"without metadata": _without_metadata, "broken metadata": _broken_metadata,
             "renamed output": _state_output_renamed, "no signature": _no_signature}
    path = tmp_path / "model.tflite"
    if content is not None:
        path.write_bytes(_rewritten(edits[content]) if isinstance(content, str) else content)
    with pytest.raises(error, match=message.format(path=str(path).replace(".", r"\."))) as refused:
        LiteRTStepSession(path)
    assert "\n" not in str(refused.value)


def test_two_streams_are_two_rows(toy) -> None:
    session = LiteRTStepSession(toy, threads=1)
    lnes = np.stack([np.zeros(FRAME, np.float32), np.ones(FRAME, np.float32)])
    outputs, state = session.run_feeds(session.feeds(lnes, session.init_state(2), np.float32([20.0, 30.0])))
    np.testing.assert_allclose(outputs["pose"], toy_pose(lnes), rtol=0, atol=1e-7)
    np.testing.assert_array_equal(state[STATE], [[20.0] * 6, [30.0] * 6])


def test_without_ai_edge_litert_the_error_names_the_extra(toy, monkeypatch) -> None:
    import sys

    from e3dpsm.errors import ConfigError

    monkeypatch.setitem(sys.modules, "ai_edge_litert", None)
    with pytest.raises(ConfigError, match=r"^ai_edge_litert is not installed \(to run \.tflite models\): .*litert"):
        LiteRTStepSession(toy)


def test_a_runtimes_long_message_is_cut_to_one_short_line(toy, tmp_path, monkeypatch) -> None:
    """The loader's message: its first line, at most 300 characters; the schema reader's: 200."""
    import e3dpsm.runtime.litert_session as litert_session
    import e3dpsm.runtime.tflite_metadata as tflite_metadata

    class Interpreter:
        def __init__(self, **kwargs) -> None:
            raise ValueError("x" * 400 + "\nsecond line")

    monkeypatch.setattr(litert_session, "require", lambda module, purpose: type("M", (), {"Interpreter": Interpreter}))
    with pytest.raises(DataError) as refused:
        LiteRTStepSession(toy)
    assert str(refused.value) == f"LiteRT cannot load {toy}: " + "x" * 300

    def unreadable(content: bytes) -> dict:
        raise RuntimeError("y" * 250 + "\nmore")
    monkeypatch.setattr(tflite_metadata, "read_metadata", unreadable)
    with pytest.raises(DataError) as refused:
        LiteRTStepSession(toy)
    assert str(refused.value) == f"{toy} is not a readable TFLite model: " + "y" * 200
