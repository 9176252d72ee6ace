"""e3dpsm.runtime.iobinding on the toy step graph (tests/_toy_step_graph.py): the same numbers as
`StepSession`, states that stay bound between steps (two buffers a chain, lanes per chain),
what an overwritten or foreign state does, the stateful API, and where a provider keeps its
tensors."""
from __future__ import annotations

import types

import numpy as np
import onnx
import pytest

from _toy_step_graph import INIT, STATE, toy_lnes, toy_numpy_step, toy_step_graph
from e3dpsm.errors import InputError
from e3dpsm.runtime.iobinding import DeviceState, IOBindingStepSession, provider_device
from e3dpsm.runtime.session import StepSession


@pytest.fixture(scope="module")
def toy_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("iobinding_toy") / "step.onnx"
    onnx.save(toy_step_graph(), str(path))
    return path


def test_a_rollout_is_bitwise_the_numpy_sessions(toy_path) -> None:
    """Per-stream windows on odd steps, one window on even ones: the same poses and states as
    `StepSession`, bit for bit, and the recurrence numpy computes."""
    plain, bound = StepSession(toy_path, threads=1), IOBindingStepSession(toy_path, threads=1)
    a, b = plain.init_state(2), bound.init_state(2)
    expected = np.float64(INIT)[None].repeat(2, 0)
    for k in range(6):
        frame, windows = toy_lnes(2, seed=k), (np.array([20.0, 35.0]) if k % 2 else 27.5)
        out_a, a = plain.step(frame, a, windows)
        out_b, b = bound.step(frame, b, windows)
        assert isinstance(b, DeviceState) and set(out_b) == {"pose"}
        assert np.array_equal(out_a["pose"], out_b["pose"]) and np.array_equal(a[STATE], b[STATE])
        expected = toy_numpy_step(frame, expected, windows if k % 2 else [27.5, 27.5])
    np.testing.assert_allclose(b[STATE], expected, rtol=1e-5)


def test_a_device_state_reads_as_a_read_only_mapping_of_copies(toy_path) -> None:
    bound = IOBindingStepSession(toy_path, threads=1)
    _, state = bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    assert list(state) == [STATE] and len(state) == 1 and state.batch == 1 and state.valid
    first = state[STATE]
    first[:] = 99.0  # a copy: the bound buffer is untouched
    assert not np.array_equal(state[STATE], first)
    held = state.to_numpy()
    assert set(held) == {STATE} and np.array_equal(held[STATE], state[STATE])
    _, after = bound.step(toy_lnes(1, seed=1), state, 20.0)
    np.testing.assert_allclose(after[STATE], toy_numpy_step(toy_lnes(1, seed=1), held[STATE], [20.0]), rtol=1e-6)


def test_a_state_two_steps_old_is_overwritten_and_says_so(toy_path) -> None:
    bound = IOBindingStepSession(toy_path, threads=1)
    _, s1 = bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    kept = s1.to_numpy()
    _, s2 = bound.step(toy_lnes(1, 1), s1, 20.0)
    assert s1.valid and s2.valid  # states k and k + 1 are both readable
    _, s3 = bound.step(toy_lnes(1, 2), s2, 20.0)
    assert not s1.valid and s2.valid and s3.valid
    message = (r"^this state was overwritten by a later step from the state after it \(each chain of states reuses "
               r"two buffers\); keep state\.to_numpy\(\) to hold on to an older state$")
    with pytest.raises(InputError, match=message):
        s1[STATE]
    with pytest.raises(InputError, match=message):
        bound.step(toy_lnes(1), s1, 20.0)
    _, again = bound.step(toy_lnes(1, 1), kept, 20.0)  # the numpy copy still steps
    np.testing.assert_allclose(again[STATE], s2[STATE], rtol=0)


def test_chains_in_one_session_keep_their_own_lanes(toy_path) -> None:
    bound, plain = IOBindingStepSession(toy_path, threads=1), StepSession(toy_path, threads=1)
    other_start = {STATE: np.array([[3.0, 2.0, 1.0]], np.float32)}
    x, y = bound.init_state(1), other_start
    px, py = plain.init_state(1), other_start
    for k in range(4):  # interleaved: each chain's buffers are its own
        _, x = bound.step(toy_lnes(1, k), x, 20.0)
        _, y = bound.step(toy_lnes(1, 10 + k), y, 40.0)
        _, px = plain.step(toy_lnes(1, k), px, 20.0)
        _, py = plain.step(toy_lnes(1, 10 + k), py, 40.0)
    assert np.array_equal(x[STATE], px[STATE]) and np.array_equal(y[STATE], py[STATE])
    assert x._lane is not y._lane
    lane = y._lane
    del y  # no state of that chain is held any more: its lane is free for the next numpy input
    _, z = bound.step(toy_lnes(1), other_start, 20.0)
    assert z._lane is lane and x.valid
    _, wide = bound.step(toy_lnes(3), bound.init_state(3), 20.0)
    assert wide.batch == 3 and wide._lane is not lane  # lanes are per batch size


def test_a_failed_run_gives_its_fresh_lane_back(toy_path, monkeypatch) -> None:
    bound = IOBindingStepSession(toy_path, threads=1)

    def fail(binding):
        raise RuntimeError("provider failure")

    monkeypatch.setattr(bound.session, "run_with_iobinding", fail)
    with pytest.raises(RuntimeError, match="provider failure"):
        bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    (lane,) = bound._free[1]
    monkeypatch.undo()
    _, state = bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    assert state._lane is lane and bound._free[1] == []


def test_feeds_of_a_device_state_are_checked_like_numpy_ones(toy_path) -> None:
    bound, other = IOBindingStepSession(toy_path, threads=1), IOBindingStepSession(toy_path, threads=1)
    _, state = bound.step(toy_lnes(2), bound.init_state(2), 20.0)
    with pytest.raises(InputError, match=r"^a DeviceState can only be fed to the session that produced it$"):
        other.step(toy_lnes(2), state, 20.0)
    with pytest.raises(InputError, match=r"^state 'mem_a' has shape \[2, 3\], expected \[1, 3\]$"):
        bound.step(toy_lnes(1), state, 20.0)  # a batch of one against the state of two
    with pytest.raises(InputError, match=r"^LNES has shape \[2, 1, 2, 3\], expected \[B, 2, 2, 3\]$"):
        bound.step(np.zeros((2, 1, 2, 3), np.float32), state, 20.0)
    with pytest.raises(InputError, match=r"^LNES has dtype float64, expected float32$"):
        bound.step(toy_lnes(2).astype(np.float64), state, 20.0)
    with pytest.raises(InputError, match=r"^window_ms must hold one positive value or 2, got \[20\.0, 0\.0\]$"):
        bound.step(toy_lnes(2), state, np.array([20.0, 0.0]))
    feeds = bound.feeds(toy_lnes(2), state, 25.0)
    assert feeds["window_ms"].tolist() == [25.0, 25.0] and feeds["window_ms"].dtype == np.float32
    per_row = bound.feeds(toy_lnes(2), state, [0.5, 30.0])
    assert per_row["window_ms"].tolist() == [0.5, 30.0]
    with pytest.raises(NotImplementedError, match="^IOBindingStepSession steps through run_feeds / step only$"):
        bound.run_raw(feeds)


def test_the_stateful_api_holds_the_chain(toy_path) -> None:
    bound = IOBindingStepSession(toy_path, threads=1)
    assert np.array_equal(bound.states()[STATE], np.float32(INIT)[None])
    expected = np.float64(INIT)[None]
    for k in range(3):
        out = bound.advance(toy_lnes(1, k), 20.0)
        expected = toy_numpy_step(toy_lnes(1, k), expected, [20.0])
        np.testing.assert_allclose(out["pose"], 2 * expected, rtol=1e-5)
    np.testing.assert_allclose(bound.states()[STATE], expected, rtol=1e-5)
    bound.reset(2)
    assert bound.states()[STATE].shape == (2, 3)
    out = bound.advance(toy_lnes(2), 20.0)
    assert out["pose"].shape == (2, 3) and bound.states()[STATE].shape == (2, 3)
    bound.reset()
    assert bound.states()[STATE].shape == (1, 3)


def _fake(providers, options=None):
    return types.SimpleNamespace(get_providers=lambda: providers, get_provider_options=lambda: options or {})


@pytest.mark.parametrize("providers, options, expected", [
    (["CPUExecutionProvider"], None, ("cpu", 0)),
    ([], None, ("cpu", 0)),
    (["CUDAExecutionProvider", "CPUExecutionProvider"], {"CUDAExecutionProvider": {"device_id": "1"}}, ("cuda", 1)),
    (["CUDAExecutionProvider"], {"CUDAExecutionProvider": {"device_id": ""}}, ("cuda", 0)),
    (["CUDAExecutionProvider"], {}, ("cuda", 0)),
    (["TensorrtExecutionProvider"], {"TensorrtExecutionProvider": {"device_id": "2"}}, ("cuda", 2)),
    (["ROCMExecutionProvider"], None, ("cuda", 0)),
    (["DmlExecutionProvider"], {"DmlExecutionProvider": {"device_id": "3"}}, ("dml", 3)),
    (["OpenVINOExecutionProvider"], {"OpenVINOExecutionProvider": {"device_id": "5"}}, ("cpu", 0)),
])
def test_where_each_provider_keeps_its_tensors(providers, options, expected) -> None:
    assert provider_device(_fake(providers, options)) == expected


def test_a_cpu_session_binds_on_the_host(toy_path) -> None:
    bound = IOBindingStepSession(toy_path, threads=1)
    assert (bound.device, bound.device_id) == ("cpu", 0)
    with pytest.raises(Exception):  # spinning left to ONNX Runtime unless asked, as StepSession
        bound.session.get_session_options().get_session_config_entry("session.intra_op.allow_spinning")


def test_a_lane_stays_taken_while_any_state_of_it_is_held(toy_path) -> None:
    """States k and k + 1 share a lane: dropping k leaves it taken (k + 1 still reads it), so
    a new chain from numpy states gets a lane of its own and k + 1 is untouched."""
    bound = IOBindingStepSession(toy_path, threads=1)
    _, s1 = bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    _, s2 = bound.step(toy_lnes(1, 1), s1, 20.0)
    kept = s2.to_numpy()
    lane = s2._lane
    del s1
    _, other = bound.step(toy_lnes(1, 2), {STATE: np.full((1, 3), 7.0, np.float32)}, 20.0)
    assert other._lane is not lane and s2.valid and np.array_equal(s2[STATE], kept[STATE])
    del s2
    _, again = bound.step(toy_lnes(1, 2), bound.init_state(1), 20.0)
    assert again._lane is lane  # free once no state refers to it


def test_the_every_step_case_skips_the_full_check(toy_path, monkeypatch) -> None:
    """Feeding a DeviceState back with a well-formed frame and window (one window, one per
    stream, however short) goes straight to the bound run; anything off goes through
    build_feeds, which names it."""
    import e3dpsm.runtime.iobinding as module

    bound = IOBindingStepSession(toy_path, threads=1)
    _, one = bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    _, two = bound.step(toy_lnes(2), bound.init_state(2), 20.0)
    checked: list[int] = []
    real = module.build_feeds
    monkeypatch.setattr(module, "build_feeds", lambda *a: checked.append(1) or real(*a))
    for state, window in ((one, 20.0), (one, [0.5]), (two, 20.0), (two, [0.5, 40.0]), (two, np.array([[7.5]]))):
        feeds = bound.feeds(toy_lnes(state.batch), state, window)
        assert feeds["window_ms"].shape == (state.batch,)
    assert checked == []
    with pytest.raises(InputError, match=r"^window_ms must hold one positive value or 2, got \[20\.0, 30\.0, 40\.0\]$"):
        bound.feeds(toy_lnes(2), two, [20.0, 30.0, 40.0])
    assert checked == [1]


def test_poses_returned_earlier_keep_their_values(toy_path) -> None:
    bound = IOBindingStepSession(toy_path, threads=1)
    first, state = bound.step(toy_lnes(1), bound.init_state(1), 20.0)
    copy = first["pose"].copy()
    for k in range(4):
        _, state = bound.step(toy_lnes(1, 10 + k), state, 20.0)
    assert np.array_equal(first["pose"], copy)
