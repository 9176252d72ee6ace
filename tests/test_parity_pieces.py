"""export/parity.py's pieces without an export: the per-tensor difference against an explicit
loop, the verdict at its limits, the report's lines and dict, and `run_parity` driven with a
runner that is the PyTorch step plus differences chosen per step (names, shapes, dtypes and
values checked in that order)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from e3dpsm.export.parity import (DtypeMismatchError, NameMismatchError, ParityReport, ShapeMismatchError,
                                  TensorDiff, Tolerances, ValueMismatchError, assert_parity, run_parity)
from e3dpsm.export.spec import step_io_spec
from e3dpsm.export.torch_stepper import TorchStepper
from e3dpsm.graph_metadata import GraphMetadata


def _loop(steps: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, float]:
    """The documented figures, element by element."""
    max_abs, peak, max_rel, scale = 0.0, -1, 0.0, 0.0
    low, high = {}, {}
    for step, (got, ref) in enumerate(steps):
        here_abs, here_scale = 0.0, 0.0
        for i, (g, r) in enumerate(zip(got.ravel().tolist(), ref.ravel().tolist())):
            here_abs = max(here_abs, abs(g - r))
            here_scale = max(here_scale, abs(r))
            low[i], high[i] = min(low.get(i, r), r), max(high.get(i, r), r)
        if here_abs > max_abs or peak < 0:
            max_abs, peak = here_abs, step
        max_rel = max(max_rel, here_abs / max(here_scale, 1e-6))
        scale = max(scale, here_scale)
    return {"max_abs": max_abs, "peak_step": peak, "max_rel": max_rel, "reference_scale": scale,
            "reference_spread": max(high[i] - low[i] for i in high)}


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_tensor_difference_matches_an_explicit_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    steps = []
    for _ in range(6):
        ref = rng.normal(size=(2, 3)).astype(np.float32) * rng.uniform(0.1, 100)
        steps.append((ref + rng.normal(size=ref.shape).astype(np.float32) * 1e-3, ref))
    diff = TensorDiff("t", "state", limit=1e-4, limit_kind="rel")
    for step, (got, ref) in enumerate(steps):
        diff.update(step, got, ref)
    expected = _loop(steps)
    for key, value in expected.items():
        assert getattr(diff, key) == pytest.approx(value, rel=1e-6), key


def test_the_first_step_of_the_largest_difference_is_its_peak() -> None:
    diff = TensorDiff("pose", "output", limit=0.01)
    ref = np.ones(3, np.float32)
    for step, delta in enumerate([0.0, 0.5, 0.5, 0.2]):
        diff.update(step, ref + np.float32(delta), ref)
    assert (diff.peak_step, diff.max_abs) == (1, 0.5)
    still = TensorDiff("pose", "output", limit=0.01)
    for step in range(3):
        still.update(step, ref, ref)
    assert (still.peak_step, still.max_abs, still.reference_spread) == (0, 0.0, 0.0)  # a stuck reference shows


def test_a_near_zero_reference_divides_by_a_floor_not_by_zero() -> None:
    diff = TensorDiff("s", "state", limit=1e-4, limit_kind="rel")
    diff.update(0, np.full(2, 1e-9, np.float32), np.zeros(2, np.float32))
    assert diff.max_rel == pytest.approx(1e-9 / 1e-6)


def test_an_empty_tensor_changes_nothing_and_a_nan_fails() -> None:
    diff = TensorDiff("s", "state", limit=1e-4, limit_kind="rel")
    diff.update(0, np.zeros(0, np.float32), np.zeros(0, np.float32))
    assert (diff.peak_step, diff.max_abs, diff.passed) == (-1, 0.0, True)
    diff.update(1, np.array([np.nan], np.float32), np.array([1.0], np.float32))
    assert diff.max_abs == math.inf and not diff.passed


@pytest.mark.parametrize("kind, limit, value, passed", [
    ("abs", 0.01, 0.01, True),            # at the limit: passes
    ("abs", 0.01, 0.0100001, False),      # just over: fails
    ("rel", 1e-4, 1e-4, True),
    ("rel", 1e-4, 1.0001e-4, False),
])
def test_the_verdict_bites_at_the_limit(kind, limit, value, passed) -> None:
    """abs limits read max_abs, rel limits max_rel (the other figure is set far off the limit)."""
    far = 1e3
    diff = TensorDiff("x", "output", max_abs=value if kind == "abs" else far,
                      max_rel=value if kind == "rel" else far, limit=limit, limit_kind=kind)
    assert diff.passed is passed


def test_lines_and_the_report_dict() -> None:
    ok = TensorDiff("pose", "output", max_abs=1.5e-4, max_rel=2e-6, peak_step=7, limit=0.01)
    bad = TensorDiff("s5_0", "state", max_abs=0.5, max_rel=0.02, peak_step=12, limit=1e-4, limit_kind="rel")
    assert ok.line() == ("output pose                   max|diff|  1.500e-04 mm rel  2.00e-06 at step     7  "
                         "(limit abs 1e-02)  ok")
    assert bad.line() == ("state  s5_0                   max|diff|  5.000e-01    rel  2.00e-02 at step    12  "
                          "(limit rel 1e-04)  FAIL")
    report = ParityReport(20, 33.0, "onnxruntime", {"pose_atol_mm": 0.01, "state_rtol": 1e-4}, [ok, bad])
    assert not report.passed and report.lines() == [ok.line(), bad.line()]
    as_dict = report.to_dict()
    assert (as_dict["steps"], as_dict["window_ms"], as_dict["runtime"], as_dict["passed"]) == (20, 33.0, "onnxruntime", False)
    assert [t["passed"] for t in as_dict["tensors"]] == [True, False]
    assert not any(key.startswith("_") for t in as_dict["tensors"] for key in t)
    assert as_dict["tensors"][1]["max_rel"] == 0.02 and as_dict["tensors"][1]["name"] == "s5_0"
    with pytest.raises(ValueMismatchError, match=r"^parity failed at 33 ms for s5_0: state  s5_0 .* FAIL$"):
        assert_parity(report)
    assert_parity(ParityReport(20, 33.0, "onnxruntime", {}, [ok]))


class OffsetRunner:
    """The PyTorch step of the same model, with `pose_mm[step]` added to the pose output and the
    first state scaled by 1 + `state_rel[step]` (on what it hands back: its own rollout
    carries the change)."""

    def __init__(self, model, pose_mm, state_rel) -> None:
        self.inner = TorchStepper(model)
        self.pose_mm, self.state_rel = list(pose_mm), list(state_rel)
        spec = step_io_spec(model)
        self._inputs, self._outputs = list(spec.input_names), list(spec.output_names)
        self.meta = GraphMetadata(states=tuple(model.state_spec()), inputs={}, outputs=[],
                                  config={}, joints=[])
        self.first_state = model.state_spec()[0].name
        self.step_index = 0
        self.cast: dict[str, type] = {}
        self.reshape: dict[str, tuple[int, ...]] = {}

    def input_names(self) -> list[str]:
        return self._inputs

    def output_names_all(self) -> list[str]:
        return self._outputs

    def init_state(self, batch: int = 1):
        return self.inner.init_state(batch)

    def step(self, lnes, state, window_ms):
        out, new = self.inner.step(lnes, state, window_ms)
        k = self.step_index
        self.step_index += 1
        out = dict(out, pose=out["pose"] + np.float32(self.pose_mm[k]))
        new = dict(new)
        new[self.first_state] = new[self.first_state] * np.float32(1.0 + self.state_rel[k])
        for name, dtype in self.cast.items():
            out[name] = out[name].astype(dtype)
        for name, shape in self.reshape.items():
            out[name] = out[name].reshape(shape)
        return out, new


@pytest.fixture(scope="module")
def tiny():
    """The tiny as created (poses in millimetres, not the randomised one's 1e7), seeded."""
    import torch

    import e3dpsm

    torch.manual_seed(5)
    return e3dpsm.create_model("tiny", height=64, width=96).eval()


def _frames(model, steps: int) -> list[np.ndarray]:
    rng = np.random.default_rng(1)
    cfg = model.config
    return [(rng.random((2, cfg.height, cfg.width)) < 0.05).astype(np.float32) for _ in range(steps)]


def test_parity_reports_the_differences_it_was_given(tiny) -> None:
    """A pose 0.02 mm off at step 2 only (along every coordinate: max |diff| 0.02), states exact:
    the pose fails at step 2, every other tensor is within its limit; the states of the runner
    carried its own rollout (exact here), so nothing else moves."""
    runner = OffsetRunner(tiny, [0, 0, 0.02, 0], [0, 0, 0, 0])
    report = run_parity(tiny, runner, _frames(tiny, 4), 20.0)
    by_name = {d.name: d for d in report.diffs}
    assert report.steps == 4 and not report.passed
    assert by_name["pose"].peak_step == 2 and by_name["pose"].max_abs == pytest.approx(0.02, rel=1e-2)
    assert [d.name for d in report.diffs if not d.passed] == ["pose"]
    assert set(by_name) == {"pose", "pose_direct", "pose_delta", *(s.name for s in tiny.state_spec())}
    assert by_name["pose_direct"].max_abs == 0.0
    assert report.tolerances == {"pose_atol_mm": 0.01, "state_rtol": 1e-4} and report.runtime == "onnxruntime"
    assert report.to_dict()["tolerances"] == report.tolerances
    assert {d.name: (d.kind, d.limit_kind) for d in report.diffs} == {
        **{n: ("output", "abs") for n in ("pose", "pose_direct", "pose_delta")},
        **{s.name: ("state", "rel") for s in tiny.state_spec()}}


def test_a_state_off_by_more_than_its_relative_limit_fails_and_tolerances_are_read(tiny) -> None:
    first = tiny.state_spec()[0].name
    runner = OffsetRunner(tiny, [0, 0, 0], [0, 1e-3, 0])
    report = run_parity(tiny, runner, _frames(tiny, 3), 20.0, tolerances=Tolerances(state_rtol=1e-2))
    assert report.passed  # 1e-3 relative within 1e-2
    runner = OffsetRunner(tiny, [0, 0, 0], [0, 1e-3, 0])
    report = run_parity(tiny, runner, _frames(tiny, 3), 20.0)
    failed = [d.name for d in report.diffs if not d.passed]
    assert first in failed and "pose" not in failed


def test_checks_run_in_order_names_shapes_dtypes(tiny) -> None:
    runner = OffsetRunner(tiny, [0], [0])
    runner._outputs = [*runner._outputs, "extra"]
    with pytest.raises(NameMismatchError, match=r"^graph outputs \[.*'extra'.*\] differ from the model's \[.*\]$"):
        run_parity(tiny, runner, _frames(tiny, 1), 20.0)
    runner = OffsetRunner(tiny, [0], [0])
    runner._inputs = runner._inputs[1:]
    with pytest.raises(NameMismatchError, match=r"^graph inputs \[.*\] differ from the model's \['fusion_cov_in', "):
        run_parity(tiny, runner, _frames(tiny, 1), 20.0)
    import dataclasses

    runner = OffsetRunner(tiny, [0], [0])  # same names, a state of another shape in the graph's metadata
    states = list(runner.meta.states)
    states[0] = dataclasses.replace(states[0], shape=(*states[0].shape[:-1], states[0].shape[-1] + 1))
    runner.meta = dataclasses.replace(runner.meta, states=tuple(states))
    with pytest.raises(NameMismatchError, match=r"^the graph's state metadata differs from the model's "
                                                r"state_spec\(\); re-export the graph$"):
        run_parity(tiny, runner, _frames(tiny, 1), 20.0)
    runner = OffsetRunner(tiny, [0], [0])
    runner.reshape["pose"] = (16, 3)
    with pytest.raises(ShapeMismatchError, match=r"^pose: graph gives shape \[16, 3\], PyTorch \[1, 16, 3\]$"):
        run_parity(tiny, runner, _frames(tiny, 1), 20.0)
    runner = OffsetRunner(tiny, [0], [0])
    runner.cast["pose"] = np.float64
    with pytest.raises(DtypeMismatchError, match="^pose: graph gives dtype float64, PyTorch float32$"):
        run_parity(tiny, runner, _frames(tiny, 1), 20.0)


def test_fresh_differences_and_reports_start_from_nothing() -> None:
    """A difference that saw no step: scale and spread 0 (not 1: a scale below 1 must show), and
    a default limit of 0, so that nothing but equality passes; a report of no tensors is empty.
    Tolerances are frozen: run_parity's default instance is shared by every call."""
    import dataclasses

    fresh = TensorDiff("x", "output")
    assert (fresh.reference_scale, fresh.reference_spread, fresh.limit, fresh.passed) == (0.0, 0.0, 0.0, True)
    fresh.update(0, np.full(2, 0.25, np.float32), np.full(2, 0.5, np.float32))
    assert fresh.reference_scale == 0.5 and not fresh.passed
    assert ParityReport(0, 20.0, "onnxruntime", {}).to_dict()["tensors"] == []
    with pytest.raises(dataclasses.FrozenInstanceError):
        Tolerances().pose_atol_mm = 1.0


def test_differences_compare_and_print_without_their_arrays() -> None:
    """The running minimum and maximum behind the spread are private: two differences of the same
    figures are equal, and the repr shows the figures, not arrays."""
    a, b = TensorDiff("s", "state", limit=1e-4, limit_kind="rel"), TensorDiff("s", "state", limit=1e-4, limit_kind="rel")
    a.update(0, np.ones(3, np.float32), np.ones(3, np.float32))
    b.update(0, np.ones(3, np.float32), np.full(3, 1.0, np.float32))
    assert a == b and "_ref" not in repr(a) and "array" not in repr(a)



def test_every_failing_tensor_is_named(tiny) -> None:
    runner = OffsetRunner(tiny, [0.5], [0.5])  # one step: the scaled state moves nothing else yet
    report = run_parity(tiny, runner, _frames(tiny, 1), 20.0)
    first = tiny.state_spec()[0].name
    with pytest.raises(ValueMismatchError, match=rf"^parity failed at 20 ms for pose, {first}: output pose "):
        assert_parity(report)


def test_progress_is_shown_only_when_asked(tiny, monkeypatch) -> None:
    """A progress bar named after the runtime and window, over the frames, gone when done."""
    import tqdm

    shown = []

    def bar(iterable, **kwargs):
        shown.append(kwargs)
        return iterable

    monkeypatch.setattr(tqdm, "tqdm", bar)
    frames = _frames(tiny, 2)
    assert run_parity(tiny, OffsetRunner(tiny, [0, 0], [0, 0]), frames, 20.0).steps == 2 and shown == []
    report = run_parity(tiny, OffsetRunner(tiny, [0, 0], [0, 0]), frames, 12.5, runtime="openvino", progress=True)
    assert report.steps == 2 and report.passed
    assert shown == [{"desc": "parity openvino 12.5 ms", "unit": "step", "leave": False, "disable": None}]
