"""The stateful OpenVINO session (runtime/openvino_stateful.py) on the numpy-sized toy step
graph (tests/_toy_step_graph.py) made stateful the way `e3dpsm convert openvino --stateful`
makes it: every step against the toy's recurrence in numpy, reset, the states read back, the
explicit-state view parity uses, and every refusal. The trained tiny's IR is in
test_openvino_stateful.py."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
import pytest

pytest.importorskip("openvino", reason="openvino (pip extra openvino) is not installed")

from _toy_step_graph import INIT, STATE, toy_numpy_step, toy_step_graph  # noqa: E402
from e3dpsm.errors import InputError  # noqa: E402
from e3dpsm.graph_metadata import MetadataError  # noqa: E402
from e3dpsm.runtime.openvino_stateful import (RT_CONVERSION, ExplicitStateView, OpenVINOStatefulSession,  # noqa: E402
                                              metadata_from_ir, read_rt_section)
from e3dpsm.state import state_input_name, state_output_name  # noqa: E402

FRAME = (1, 2, 2, 3)


def toy_reference(frames: np.ndarray, windows: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """The toy's recurrence over one stream's frames [N, 1, ...] (toy_numpy_step), pose = 2 s'."""
    state, states = np.asarray([INIT], np.float64), []
    for frame, window in zip(frames, windows):
        state = toy_numpy_step(frame, state, window)
        states.append(state[0])
    return 2 * np.array(states), np.array(states)


@pytest.fixture(scope="module")
def toy_onnx(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "toy.onnx"
    onnx.save(toy_step_graph(), path)
    return path


@pytest.fixture(scope="module")
def toy_ir(toy_onnx) -> Path:
    from e3dpsm.export.openvino_ir import convert_step_graph, save_ir

    model, _ = convert_step_graph(toy_onnx, stateful=True)
    return save_ir(model, toy_onnx.with_name("stateful.xml"))[0]


def test_steps_follow_the_toys_recurrence_and_reset_starts_again(toy_ir) -> None:
    session = OpenVINOStatefulSession(toy_ir, threads=1)
    assert session.batch == 1 and session.input_names() == ["lnes", "window_ms"]
    assert session.output_names() == ["pose", "extra"] and session.variable_names() == [STATE]
    assert session.conversion["stateful"] is True and session.conversion["batch"] == 1
    rng = np.random.default_rng(0)
    frames = rng.uniform(0, 1, (4, *FRAME)).astype(np.float32)
    windows = [20.0, 33.0, 5.0, 20.0]
    poses, states = toy_reference(frames, windows)
    for k in range(4):
        outputs = session.step(frames[k], np.float32(windows[k]))
        assert list(outputs) == ["pose"]
        np.testing.assert_allclose(outputs["pose"][0], poses[k], rtol=1e-5)
        np.testing.assert_allclose(session.states()[STATE][0], states[k], rtol=1e-5)
    # What the outputs hand back are copies: the next step does not change them.
    kept = session.step(frames[0], 20.0)["pose"].copy()
    held = session.step(frames[1], 20.0)
    session.reset()
    np.testing.assert_allclose(session.step(frames[0], windows[0])["pose"][0], poses[0], rtol=1e-5)
    assert not np.array_equal(held["pose"], kept)
    np.testing.assert_array_equal(session.initial_states()[STATE], [INIT])


def test_the_explicit_state_view_reads_the_variables_back(toy_ir) -> None:
    view = ExplicitStateView(OpenVINOStatefulSession(toy_ir, threads=1))
    assert view.input_names() == ["lnes", "window_ms", state_input_name(STATE)]
    assert view.output_names_all() == ["pose", "extra", state_output_name(STATE)]
    frame = np.full(FRAME, 0.25, np.float32)
    state = view.init_state(1)
    np.testing.assert_array_equal(state[STATE], [INIT])
    for _ in range(2):  # the state it is given is ignored: the request's own carries on
        outputs, state = view.step(frame, {STATE: np.zeros((1, 3), np.float32)}, 20.0)
    poses, states = toy_reference(np.stack([frame, frame]), [20.0, 20.0])
    np.testing.assert_allclose(state[STATE][0], states[1], rtol=1e-5)
    np.testing.assert_allclose(outputs["pose"][0], poses[1], rtol=1e-5)
    fresh = view.init_state(1)  # resets the request
    np.testing.assert_allclose(view.step(frame, fresh, 20.0)[0]["pose"][0], poses[0], rtol=1e-5)
    with pytest.raises(InputError, match=r"^the IR is fixed to batch 1, asked for 2$"):
        view.init_state(2)


@pytest.mark.parametrize("lnes, window, message", [
    (np.zeros((1, 2, 2, 4), np.float32), 20.0, r"^LNES has shape \[1, 2, 2, 4\], expected \[1, 2, 2, 3\]$"),
    (np.zeros((2, 2, 2, 3), np.float32), 20.0, r"^LNES has shape \[2, 2, 2, 3\], expected \[1, 2, 2, 3\]$"),
    ([[0.0]], 20.0, r"^LNES has shape list, expected \[1, 2, 2, 3\]$"),
    (np.zeros(FRAME, np.float64), 20.0, r"^LNES has dtype float64, expected float32$"),
    (np.zeros(FRAME, np.float32), 0.0, r"^window_ms must be one positive value, got \[0\.0\]$"),
    (np.zeros(FRAME, np.float32), -5.0, r"^window_ms must be one positive value, got \[-5\.0\]$"),
    (np.zeros(FRAME, np.float32), [20.0, 20.0], r"^window_ms must be one positive value, got \[20\.0, 20\.0\]$"),
    (np.zeros(FRAME, np.float32), float("nan"), r"^window_ms must be one positive value, got \[nan\]$"),
])
def test_a_bad_step_is_refused_before_the_state_moves(toy_ir, lnes, window, message) -> None:
    session = OpenVINOStatefulSession(toy_ir, threads=1)
    frame = np.full(FRAME, 0.5, np.float32)
    session.step(frame, 20.0)
    with pytest.raises(InputError, match=message):
        session.step(lnes, window)
    poses, _ = toy_reference(np.stack([frame, frame]), [20.0, 20.0])
    np.testing.assert_allclose(session.step(frame, 20.0)["pose"][0], poses[1], rtol=1e-5)


def _ir(toy_onnx: Path, name: str, *, batch: int = 1, stateful: bool = True, metadata: bool = True) -> Path:
    """The toy as an IR made from the converter's own pieces, for IRs it refuses to make."""
    from e3dpsm.export.openvino_ir import ConversionInfo, attach_metadata, fix_batch, make_stateful, read_step_graph, save_ir

    model, meta, props = read_step_graph(toy_onnx)
    if stateful or batch != 1:
        fix_batch(model, meta, batch, states=not stateful)
    variables = make_stateful(model, meta, batch) if stateful else []
    if metadata:
        attach_metadata(model, props, ConversionInfo(source=toy_onnx.name, stateful=stateful, batch=batch,
                                                     precision="fp32", inputs=[], outputs=[], variables=variables))
    return save_ir(model, toy_onnx.with_name(name))[0]


def test_an_ir_that_is_not_a_one_stream_stateful_step_is_refused(toy_onnx, tmp_path) -> None:
    def refused(path: Path, error: type = InputError) -> str:
        with pytest.raises(error) as caught:
            OpenVINOStatefulSession(path)
        assert "\n" not in str(caught.value)
        return str(caught.value)

    explicit = _ir(toy_onnx, "explicit.xml", stateful=False)
    assert refused(explicit) == (f"{explicit}: variables [] do not match the metadata's states ['{STATE}']; is it a "
                                 "stateful IR (`e3dpsm convert openvino --stateful`)?")
    two = _ir(toy_onnx, "batch2.xml", batch=2)
    assert refused(two) == (f"{two}: a stateful IR of batch 2, whose variables OpenVINO's CPU plugin does not carry "
                            "from step to step; convert with batch 1 (`e3dpsm convert openvino --stateful`) and open "
                            "one session per stream")
    bare = _ir(toy_onnx, "bare.xml", metadata=False)
    assert refused(bare, MetadataError) == (f"{bare} carries no e3dpsm metadata in its rt_info; convert the step "
                                            "graph with `e3dpsm convert openvino`")
    onnx_file = tmp_path / "step.onnx"
    onnx_file.write_bytes(toy_onnx.read_bytes())
    assert refused(onnx_file) == (f"{onnx_file} is not an OpenVINO IR (.xml); convert the step graph first with "
                                  "`e3dpsm convert openvino --model STEP.onnx --out DIR --stateful`")


def test_an_ir_with_an_extra_input_or_a_dynamic_batch_is_refused(toy_onnx) -> None:
    """Made by hand from the stateful toy: one more parameter; the batch axis made dynamic."""
    import openvino as ov
    import openvino.opset13 as ops

    from e3dpsm.export.openvino_ir import save_ir

    core = ov.Core()
    stateful = _ir(toy_onnx, "base.xml")
    model = core.read_model(str(stateful))
    extra = ops.parameter([1], ov.Type.f32, name="extra_in")
    extra.output(0).set_names({"extra_in"})
    model.add_parameters([extra])
    with_extra = save_ir(model, toy_onnx.with_name("extra_input.xml"))[0]
    with pytest.raises(InputError, match=r"inputs \['extra_in', 'lnes', 'window_ms'\], expected exactly "
                                         r"\['lnes', 'window_ms'\]$"):
        OpenVINOStatefulSession(with_extra)
    dynamic = core.read_model(str(stateful))
    dynamic.reshape({"lnes": ov.PartialShape([-1, 2, 2, 3]), "window_ms": ov.PartialShape([-1])})
    with pytest.raises(InputError, match=r"the batch axis is dynamic; a stateful IR needs a fixed batch$"):
        OpenVINOStatefulSession(save_ir(dynamic, toy_onnx.with_name("dynamic.xml"))[0])


def test_the_rt_info_sections_read_as_strings(toy_ir) -> None:
    import openvino as ov

    model = ov.Core().read_model(str(toy_ir))
    conversion = read_rt_section(model, RT_CONVERSION)
    assert conversion["stateful"] == "true" and conversion["batch"] == "1" and conversion["source"] == '"toy.onnx"'
    assert read_rt_section(model, "no_such_section") == {}
    meta = metadata_from_ir(model, "toy IR")
    assert [s.name for s in meta.states] == [STATE] and meta.frame_input["name"] == "lnes"
    # The section names are the IR's file format (module docstring): an IR outlives the code that wrote it.
    assert model.has_rt_info(["e3dpsm"]) and model.has_rt_info(["e3dpsm_openvino"])
    assert model.get_rt_info(["e3dpsm_openvino", "stateful"]).astype(str) == "true"


def test_an_ir_without_metadata_is_named_ir_when_no_source_is_given(toy_onnx) -> None:
    import openvino as ov

    model = ov.Core().read_model(str(_ir(toy_onnx, "no_meta.xml", metadata=False)))
    with pytest.raises(MetadataError, match=r"^IR carries no e3dpsm metadata in its rt_info"):
        metadata_from_ir(model)


def test_the_session_exposes_its_compiled_model_and_takes_any_positive_window(toy_ir) -> None:
    session = OpenVINOStatefulSession(toy_ir, threads=1)
    assert {port.get_any_name() for port in session.compiled.outputs} >= {"pose"}
    frame = np.full(FRAME, 0.5, np.float32)
    poses, _ = toy_reference(frame[None], [0.5])
    np.testing.assert_allclose(session.step(frame, 0.5)["pose"][0], poses[0], rtol=1e-5)  # half a millisecond
    view = ExplicitStateView(session)
    assert view.meta is session.meta
    np.testing.assert_array_equal(view.init_state()[STATE], [INIT])  # batch 1 by default
