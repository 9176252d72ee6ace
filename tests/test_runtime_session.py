"""e3dpsm.runtime.session on a step graph small enough to write out in numpy: the checked feeds
of a step (shapes, dtype, window broadcast), ONNX Runtime's session settings, the outputs and
states a step returns, and a runner carrying its own state."""
from __future__ import annotations

import numpy as np
import onnx
import pytest

from _toy_step_graph import INIT, STATE, toy_lnes, toy_numpy_step, toy_step_graph
from e3dpsm.errors import DataError, InputError
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.runtime.session import (CarriedStateRunner, MetadataStepper, StepSession, build_feeds,
                                    exact_arithmetic_options, make_session)
from e3dpsm.state import StateSpec, state_input_name, state_output_name


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("session_toy") / "step.onnx"
    onnx.save(toy_step_graph(), str(path))
    return path


@pytest.fixture(scope="module")
def meta(toy_path) -> GraphMetadata:
    return GraphMetadata.from_onnx(onnx.load(str(toy_path)))


def test_feeds_name_every_input_and_broadcast_one_window_over_the_batch(meta) -> None:
    lnes = toy_lnes(3)
    state64 = np.asfortranarray(np.arange(9, dtype=np.float64).reshape(3, 3))  # a caller's array, any layout
    feeds = build_feeds(meta, lnes, {STATE: state64}, 20.0)
    assert set(feeds) == {"lnes", "window_ms", state_input_name(STATE)}
    assert feeds["lnes"] is lnes
    assert feeds["window_ms"].dtype == np.float32 and feeds["window_ms"].tolist() == [20.0, 20.0, 20.0]
    fed = feeds[state_input_name(STATE)]
    assert fed.dtype == np.float32 and fed.flags.c_contiguous and np.array_equal(fed, state64)
    per_stream = build_feeds(meta, lnes, {STATE: state64}, np.array([10.0, 20.0, 30.0]))
    assert per_stream["window_ms"].tolist() == [10.0, 20.0, 30.0]
    single = build_feeds(meta, lnes[:1], {STATE: state64[:1]}, np.array([[7.5]]))
    assert single["window_ms"].shape == (1,) and single["window_ms"][0] == 7.5
    short = build_feeds(meta, lnes, {STATE: state64}, 0.25)  # any positive length, however short
    assert short["window_ms"].tolist() == [0.25] * 3


@pytest.mark.parametrize("lnes, message", [
    (np.zeros((2, 2, 3), np.float32), r"^LNES has shape \[2, 2, 3\], expected \[B, 2, 2, 3\]$"),
    (np.zeros((1, 2, 3, 2), np.float32), r"^LNES has shape \[1, 2, 3, 2\], expected \[B, 2, 2, 3\]$"),
    (np.zeros((1, 1, 2, 2, 3), np.float32), r"^LNES has shape \[1, 1, 2, 2, 3\], expected"),
    ([[[[0.0]]]], r"^LNES has shape list, expected \[B, 2, 2, 3\]$"),
    (np.zeros((1, 2, 2, 3), np.float64), r"^LNES has dtype float64, expected float32$"),
])
def test_feeds_refuse_a_frame_of_another_shape_or_dtype(meta, lnes, message) -> None:
    with pytest.raises(InputError, match=message):
        build_feeds(meta, lnes, {STATE: np.zeros((1, 3), np.float32)}, 20.0)


@pytest.mark.parametrize("window", [np.array([10.0, 20.0]), 0.0, -5.0, np.array([10.0, 0.0, 5.0]), np.nan])
def test_feeds_refuse_windows_that_are_not_one_or_batch_positive_values(meta, window) -> None:
    with pytest.raises(InputError, match=r"^window_ms must hold one positive value or 3, got \["):
        build_feeds(meta, toy_lnes(3), {STATE: np.zeros((3, 3), np.float32)}, window)


def test_feeds_refuse_states_of_another_batch_or_name(meta) -> None:
    with pytest.raises(InputError, match=r"^state 'mem_a' has shape \[2, 3\], expected \[3, 3\]$"):
        build_feeds(meta, toy_lnes(3), {STATE: np.zeros((2, 3), np.float32)}, 20.0)
    with pytest.raises(InputError, match=r"^state is missing \['mem_a'\]"):
        build_feeds(meta, toy_lnes(1), {"other": np.zeros((1, 3), np.float32)}, 20.0)


def test_a_session_is_bounded_and_computes_8_bit_weights_in_float(toy_path) -> None:
    session = make_session(toy_path, threads=2, spin=False)
    options = session.get_session_options()
    assert (options.intra_op_num_threads, options.inter_op_num_threads) == (2, 1)
    assert options.get_session_config_entry("session.qdq_matmulnbits_accuracy_level") == "1"
    assert options.get_session_config_entry("session.intra_op.allow_spinning") == "0"
    assert session.get_providers() == ["CPUExecutionProvider"]
    import warnings

    with warnings.catch_warnings(record=True) as caught:  # ONNX Runtime warns of a provider it does not know
        warnings.simplefilter("always")
        make_session(toy_path)
    assert [str(w.message) for w in caught] == []
    default = make_session(toy_path).get_session_options()
    assert default.intra_op_num_threads == 0  # ONNX Runtime's own choice when no count is given
    assert default.get_session_config_entry("session.qdq_matmulnbits_accuracy_level") == "1"
    with pytest.raises(Exception):  # the entry is never set: spinning stays ONNX Runtime's default
        default.get_session_config_entry("session.intra_op.allow_spinning")
    exact = make_session(toy_path, options=exact_arithmetic_options()).get_session_options()
    import onnxruntime as ort

    assert exact.graph_optimization_level == ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    assert exact.get_session_config_entry("session.qdq_matmulnbits_accuracy_level") == "1"


def test_a_missing_or_damaged_graph_is_one_line(tmp_path) -> None:
    with pytest.raises(DataError, match=r"^model .*absent\.onnx does not exist$"):
        make_session(tmp_path / "absent.onnx")
    (tmp_path / "folder.onnx").mkdir()
    with pytest.raises(DataError, match="does not exist"):
        make_session(tmp_path / "folder.onnx")
    (tmp_path / "damaged.onnx").write_bytes(b"\x08\x07garbage" * 50)
    with pytest.raises(DataError, match=r"^onnxruntime cannot load .*damaged\.onnx: ") as err:
        make_session(tmp_path / "damaged.onnx")
    assert "\n" not in str(err.value) and len(str(err.value)) < 420


def test_a_long_runtime_error_is_cut_to_its_first_300_characters(toy_path, monkeypatch) -> None:
    import onnxruntime as ort

    def refuse(*args, **kwargs):
        raise RuntimeError("x" * 500 + "\nsecond line")

    monkeypatch.setattr(ort, "InferenceSession", refuse)
    with pytest.raises(DataError) as err:
        make_session(toy_path)
    assert str(err.value) == f"onnxruntime cannot load {toy_path}: " + "x" * 300


def test_a_step_computes_what_numpy_does_and_returns_the_next_state(toy_path) -> None:
    session = StepSession(toy_path, threads=1)
    assert session.path == toy_path and session.init_state()[STATE].shape == (1, 3)  # one stream unless asked
    with pytest.raises(Exception):  # spinning left to ONNX Runtime unless asked
        session.session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning")
    assert session.input_names() == ["lnes", "window_ms", state_input_name(STATE)]
    assert session.output_names_all() == ["pose", state_output_name(STATE), "extra"]
    state = session.init_state(2)
    assert np.array_equal(state[STATE], np.tile(np.float32(INIT), (2, 1)))
    lnes = toy_lnes(2, seed=1)
    outputs, new_state = session.step(lnes, state, np.array([20.0, 40.0]))
    expected = toy_numpy_step(lnes, state[STATE], [20.0, 40.0])
    assert set(outputs) == {"pose"} and set(new_state) == {STATE}
    np.testing.assert_allclose(new_state[STATE], expected, rtol=1e-6)
    np.testing.assert_allclose(outputs["pose"], 2 * expected, rtol=1e-6)
    everything, _ = StepSession(toy_path, all_outputs=True).step(lnes, state, np.array([20.0, 40.0]))
    assert set(everything) == {"pose", state_output_name(STATE), "extra"}
    np.testing.assert_allclose(everything["extra"], expected - state[STATE], rtol=1e-5)
    raw = session.run_raw(session.feeds(lnes, state, 20.0))
    assert [r.shape for r in raw] == [(2, 3)] * 3
    again, next_state = session.collect(raw)
    np.testing.assert_allclose(next_state[STATE], toy_numpy_step(lnes, state[STATE], [20.0, 20.0]), rtol=1e-6)


def test_a_graph_whose_inputs_are_not_its_metadatas_is_refused(tmp_path) -> None:
    other = toy_step_graph(states=(StateSpec("other_a", (3,)),))
    onnx.save(other, str(tmp_path / "other.onnx"))
    with pytest.raises(InputError, match=r"graph inputs \['lnes', 'mem_a_in', 'window_ms'\] do not match its "
                                         r"metadata \['lnes', 'other_a_in', 'window_ms'\]$"):
        StepSession(tmp_path / "other.onnx")


def test_a_runner_carries_its_own_state_and_resets(toy_path) -> None:
    runner = CarriedStateRunner(StepSession(toy_path), window_ms=50.0)
    frames = [toy_lnes(1, seed=k) for k in range(4)]
    state = np.float64(INIT)[None]
    for frame in frames:
        runner.step(frame)
        state = toy_numpy_step(frame, state, [50.0])
    np.testing.assert_allclose(runner.state[STATE], state, rtol=1e-5)
    runner.reset()
    assert np.array_equal(runner.state[STATE], np.float32(INIT)[None])


def test_the_metadata_stepper_leaves_running_to_its_runtime(meta) -> None:
    class Bare(MetadataStepper):
        def __init__(self) -> None:
            self.meta, self._inputs, self._outputs = meta, ["a", "b"], ["c"]

    bare = Bare()
    assert bare.states == meta.states and bare.input_names() == ["a", "b"] and bare.output_names_all() == ["c"]
    assert bare.input_names() is not bare._inputs  # a copy: callers cannot change the runtime's list
    with pytest.raises(NotImplementedError):
        bare.step(toy_lnes(1), bare.init_state(1), 20.0)
