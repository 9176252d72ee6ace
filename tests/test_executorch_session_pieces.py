"""The ExecuTorch step session (runtime/executorch_session.py) on the toy `.pte` of
tests/_toy_pte.py (ExecuTorch's own API, not the project's converter): the numbers it steps
against numpy, the threads and kernels it sets up, the release check, and each way a file is
refused, in one line naming it. The converted tiny runs in test_edge_artifacts.py."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("executorch", reason="executorch (pip extra executorch) is not installed")

from _golden_fakes import FRAME, STATE  # noqa: E402
from _toy_pte import TAPS, toy_pose, toy_pte, toy_taps  # noqa: E402
from e3dpsm.errors import DataError  # noqa: E402
from e3dpsm.graph_metadata import MetadataError  # noqa: E402
from e3dpsm.runtime import executorch_session  # noqa: E402
from e3dpsm.runtime.executorch_session import (OTHER_RELEASE_ENV, ExecuTorchStepSession,  # noqa: E402
                                               executorch_version, load_program, native_log_silenced,
                                               program_metadata, same_release)


@pytest.fixture(scope="module")
def toy(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("toy") / "step.pte"
    path.write_bytes(toy_pte())
    return path


def test_a_step_gives_the_toys_pose_and_carries_its_state(toy) -> None:
    session = ExecuTorchStepSession(toy, threads=1)
    assert session.runtime == "executorch" and session.path == toy and [s.name for s in session.meta.states] == [STATE]
    assert session.artifact["format"] == "executorch"
    rng = np.random.default_rng(0)
    state = session.init_state(1)
    for window in (20.0, 33.0):
        lnes = rng.uniform(0, 1, (1, *FRAME)).astype(np.float32)
        outputs, new_state = session.step(lnes, state, window)
        assert list(outputs) == ["pose"] and outputs["pose"].dtype == np.float32
        np.testing.assert_allclose(outputs["pose"], toy_pose(lnes, window), rtol=0, atol=1e-6)
        np.testing.assert_array_equal(new_state[STATE], state[STATE] + np.float32(window))
        state = new_state


def test_a_batch_is_stepped_row_by_row(toy) -> None:
    session = ExecuTorchStepSession(toy)
    rng = np.random.default_rng(1)
    lnes = rng.uniform(0, 1, (3, *FRAME)).astype(np.float32)
    state = {STATE: rng.normal(0, 5, (3, 6)).astype(np.float32)}
    windows = np.array([10.0, 20.0, 40.0], np.float32)
    outputs, new_state = session.run_feeds(session.feeds(lnes, state, windows))
    np.testing.assert_allclose(outputs["pose"], toy_pose(lnes, windows[:, None, None, None]), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(new_state[STATE], state[STATE] + windows[:, None])


def test_threads_reset_xnnpacks_pool_and_int8_programs_load_the_quantized_kernels(toy, tmp_path,
                                                                                 monkeypatch) -> None:
    from executorch.extension.pybindings import portable_lib

    reset = []
    monkeypatch.setattr(portable_lib, "_unsafe_reset_threadpool", reset.append)
    ExecuTorchStepSession(toy)
    ExecuTorchStepSession(toy, threads=0)
    assert reset == []  # no count asked: the runtime's own pool
    ExecuTorchStepSession(toy, threads=3)
    assert reset == [3] and type(reset[0]) is int

    int8 = tmp_path / "int8.pte"
    int8.write_bytes(toy_pte(precision="int8"))
    monkeypatch.delitem(sys.modules, "executorch.kernels.quantized", raising=False)
    ExecuTorchStepSession(toy)
    assert "executorch.kernels.quantized" not in sys.modules  # an fp32 program does not need them
    ExecuTorchStepSession(int8)
    assert "executorch.kernels.quantized" in sys.modules


@pytest.mark.parametrize("a, b, same", [("1.5.1", "1.5.0", True), ("1.5", "1.5.9", True), ("1.5.1", "1.4.1", False),
                                        ("2.5.1", "1.5.1", False), ("1.5.1", "1.50.1", False)])
def test_a_release_is_its_major_and_minor(a, b, same) -> None:
    assert same_release(a, b) is same and same_release(b, a) is same


def test_the_version_is_the_installed_distributions() -> None:
    import importlib.metadata

    assert executorch_version() == importlib.metadata.version("executorch")


def test_the_native_log_goes_nowhere_while_loading_and_comes_back_after(capfd) -> None:
    fds = len(os.listdir("/proc/self/fd")) if os.path.isdir("/proc/self/fd") else None
    print("before", file=sys.stderr)
    with native_log_silenced():
        os.write(2, b"from C\n")
        print("from Python", file=sys.stderr)
    os.write(2, b"after\n")
    assert capfd.readouterr().err == "before\nafter\n"
    if fds is not None:
        assert len(os.listdir("/proc/self/fd")) == fds  # the saved descriptor is closed again
    with pytest.raises(KeyError), native_log_silenced():
        raise KeyError("restored on an error too")
    os.write(2, b"again\n")
    assert capfd.readouterr().err == "again\n"


@pytest.mark.parametrize("content, message", [
    (None, "model {path} does not exist"),
    (b"\x00\x00\x00\x00ZZ99" + b"\x00" * 64,
     "ExecuTorch {version} cannot load {path} (file identifier b'ZZ99'): written by another ExecuTorch version or "
     "not a .pte; convert it again with this one"),
    (b"ab", "ExecuTorch {version} cannot load {path} (file identifier b''): written by another ExecuTorch version "
            "or not a .pte; convert it again with this one"),
])
def test_a_file_that_is_not_a_program_is_one_line_naming_it(tmp_path, capfd, content, message) -> None:
    path = tmp_path / "model.pte"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(DataError) as refused:
        ExecuTorchStepSession(path)
    assert str(refused.value) == message.format(path=path, version=executorch_version())
    assert capfd.readouterr().err == ""  # the runtime's own complaint silenced: the CLI's line is the one


def test_a_program_without_the_state_layout(tmp_path) -> None:
    path = tmp_path / "bare.pte"
    path.write_bytes(toy_pte(with_metadata=False))
    with pytest.raises(MetadataError) as refused:
        ExecuTorchStepSession(path)
    assert str(refused.value) == (f"{path} carries no e3dpsm state layout (no e3dpsm_metadata method); write it with "
                                  "`e3dpsm convert executorch`")


@pytest.mark.parametrize("env, runs", [(None, False), ("0", False), ("yes", False), ("1", True)])
def test_a_program_of_another_release_runs_only_when_asked(tmp_path, monkeypatch, env, runs) -> None:
    path = tmp_path / "other.pte"
    path.write_bytes(toy_pte(version="0.9.9"))
    if env is None:
        monkeypatch.delenv(OTHER_RELEASE_ENV, raising=False)
    else:
        monkeypatch.setenv(OTHER_RELEASE_ENV, env)
    program = load_program(path)
    if runs:
        meta, artifact = program_metadata(path, program)
        assert artifact["versions"]["executorch"] == "0.9.9" and [s.name for s in meta.states] == [STATE]
        return
    with pytest.raises(DataError) as refused:
        program_metadata(path, program)
    assert str(refused.value) == (f"{path} was written by ExecuTorch 0.9.9, this runtime is {executorch_version()}; "
                                  "convert it again here, or run it with executorch==0.9.9")


def test_a_patch_release_of_this_one_is_the_same_release(tmp_path, monkeypatch) -> None:
    major, minor = executorch_version().split(".")[:2]
    path = tmp_path / "patch.pte"
    path.write_bytes(toy_pte(version=f"{major}.{minor}.99"))
    monkeypatch.delenv(OTHER_RELEASE_ENV, raising=False)
    assert program_metadata(path, load_program(path))[1]["versions"]["executorch"] == f"{major}.{minor}.99"
    assert executorch_session.FORMAT == "executorch" and executorch_session.PTE_IDENTIFIER_AT == slice(4, 8)


def test_a_missing_extra_is_its_own_error_not_an_unreadable_program(toy, monkeypatch) -> None:
    from e3dpsm.errors import ConfigError

    monkeypatch.setitem(sys.modules, "executorch", None)
    with pytest.raises(ConfigError) as error:
        ExecuTorchStepSession(toy)
    assert str(error.value) == 'executorch is not installed (to run .pte programs): pip install -e ".[executorch]"'


def test_the_documented_escape_hatch_and_the_programs_lifetime(toy) -> None:
    docs = (Path(__file__).resolve().parents[1] / "docs" / "edge.md").read_text(encoding="utf-8")
    assert OTHER_RELEASE_ENV == "E3DPSM_EXECUTORCH_OTHER_RELEASE" and f"{OTHER_RELEASE_ENV}=1" in docs
    session = ExecuTorchStepSession(toy)
    assert "forward" in session.program.method_names  # the program outlives no method of its session


def test_what_a_step_returns_past_its_outputs_is_kept_and_outlives_the_next_step(toy, tmp_path) -> None:
    """A step program returns its outputs alone; a taps program's codes past them are the
    session's extra_outputs after each step, numpy's codes, which the next step leaves alone."""
    session = ExecuTorchStepSession(toy)
    assert session.extra_outputs == ()  # before any step too
    session.step(np.ones((1, *FRAME), np.float32), session.init_state(1), 20.0)
    assert session.extra_outputs == ()
    path = tmp_path / "step_taps.pte"
    path.write_bytes(toy_pte(precision="int8", taps=True))
    session = ExecuTorchStepSession(path)
    rng = np.random.default_rng(3)
    state, kept = session.init_state(1), []
    for window in (20.0, 90.0):
        lnes = rng.uniform(-40, 40, (1, *FRAME)).astype(np.float32)
        _, new_state = session.step(lnes, state, window)
        expected = toy_taps(lnes, new_state[STATE])
        assert len(session.extra_outputs) == len(TAPS)
        for got, want in zip(session.extra_outputs, expected):
            assert got.dtype == np.int8
            np.testing.assert_array_equal(got, want)
        kept.append((session.extra_outputs, expected))
        state = new_state
    for got, want in zip(*kept[0]):  # the first step's codes, after the second step ran
        np.testing.assert_array_equal(got, want)


def test_a_session_steps_through_the_method_it_is_given(toy) -> None:
    session = ExecuTorchStepSession(toy)
    forward = session._method

    class Shifted:  # the same program's forward, its pose moved: the session must step through it
        def execute(self, inputs):
            pose, state = forward.execute(inputs)
            return [pose + 1, state]

    session.use_method(Shifted())
    lnes = np.zeros((1, *FRAME), np.float32)
    outputs, _ = session.step(lnes, session.init_state(1), 5.0)
    np.testing.assert_allclose(outputs["pose"], toy_pose(lnes, 5.0) + 1, rtol=0, atol=1e-6)
    with pytest.raises(TypeError, match="^object has no execute\\(inputs\\): not an ExecuTorch method$"):
        session.use_method(object())

    class Short:
        def execute(self, inputs):
            return forward.execute(inputs)[:1]

    session.use_method(Short())
    with pytest.raises(DataError, match=f"^{toy} returned 1 values, fewer than its 2 outputs$"):
        session.step(lnes, session.init_state(1), 5.0)
