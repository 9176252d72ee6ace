"""quantize/holdout.py on a numpy stepper: held-out frames and their head, the streams carried
over each sequence, the runtime a graph is opened on, the fidelity figure, the worst runtime."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from e3dpsm.budget import BudgetCheck, MetricChange, TaskBudget, check_budget
from e3dpsm.quantize import holdout
from e3dpsm.quantize.holdout import HeldOut, Judgement, check_stepper, distance_pct, held_out, stepper_outputs


class Accumulator:
    """A causal stepper: its state is the running sum of each frame's mean input, and every
    joint's every coordinate of `pose` is that sum plus `offset` (`pose_direct` one less)."""

    def __init__(self, offset: float = 0.0, model=None, threads=None):
        self.offset, self.model, self.threads = offset, model, threads
        self.inits, self.windows = [], []

    def init_state(self, batch: int = 1):
        self.inits.append(batch)
        return {"h": np.zeros((batch,), np.float32)}

    def step(self, lnes, state, window_ms):
        self.windows.append(window_ms)
        h = state["h"] + lnes.reshape(len(lnes), -1).mean(axis=1)
        pose = np.broadcast_to((h + self.offset)[:, None, None], (len(lnes), 16, 3)).astype(np.float32)
        return {"pose": pose, "pose_direct": pose - 1.0}, {"h": h}


def by_hand(lnes: np.ndarray, offset: float = 0.0) -> np.ndarray:
    """Accumulator's poses over a whole sequence, state carried: a cumulative sum, no stepping."""
    running = np.cumsum(lnes.reshape(len(lnes), -1).mean(axis=1)) + offset
    return np.broadcast_to(running[:, None, None], (len(lnes), 16, 3)).astype(np.float32)


def frames(n: int, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 2.0, (n, 2, 4, 4))


def constant_poses(n: int, xyz) -> np.ndarray:
    return np.broadcast_to(np.asarray(xyz, np.float32), (n, 16, 3)).copy()


def two_sequences() -> HeldOut:
    """Ground truth at the origin; fp32 off by 2 mm (10 frames) and by 4 mm (30 frames)."""
    gt = (constant_poses(10, (0, 0, 0)), constant_poses(30, (0, 0, 0)))
    fp32 = ({"pose": constant_poses(10, (0, 0, 2))}, {"pose": constant_poses(30, (0, 4, 0))})
    return HeldOut("split", (frames(10, 0), frames(30, 1)), gt, fp32, 20.0)


def noisy() -> HeldOut:
    """Poses spread 50 mm around the origin, fp32's 20 mm off them: every metric has a positive fp32 value."""
    rng = np.random.default_rng(3)
    gt = tuple(rng.normal(0.0, 50.0, (n, 16, 3)).astype(np.float32) for n in (40, 60))
    fp32 = tuple({"pose": g + rng.normal(0.0, 20.0, g.shape).astype(np.float32)} for g in gt)
    return HeldOut("split", (frames(40, 4), frames(60, 5)), gt, fp32, 10.0)


def test_frames_and_fp32_mpjpe_weigh_every_frame_of_every_sequence():
    """40 frames; fp32's MPJPE over all of them (2 mm x 10, 4 mm x 30) is 3.5 mm, not the 3 mm
    mean of the two sequences' means."""
    held = two_sequences()
    assert held.frames == 40
    assert held.fp32_mpjpe == pytest.approx((2 * 10 + 4 * 30) / 40)


def test_head_keeps_the_first_frames_of_everything_and_names_them():
    """head(3): the first 3 frames of each sequence's input, ground truth and fp32 outputs (each
    frame of fp32 made distinct), named `name[:3]`, at the same window; one frame is a head too."""
    held = two_sequences()
    held = HeldOut(held.name, held.lnes, held.gt,
                   tuple({"pose": o["pose"] + np.arange(len(o["pose"]))[:, None, None]} for o in held.fp32),
                   held.window_ms)
    head = held.head(3)
    assert head.name == "split[:3]" and head.window_ms == 20.0 and head.frames == 6
    for full, part in [(held.lnes, head.lnes), (held.gt, head.gt), ([o["pose"] for o in held.fp32],
                                                                    [o["pose"] for o in head.fp32])]:
        assert len(part) == 2 and all(np.array_equal(p, f[:3]) for p, f in zip(part, full))
    assert held.head(1).frames == 2  # one frame of each: the smallest head there is


@pytest.mark.parametrize("count", [0, -1])
def test_a_head_of_no_frames_is_refused(count):
    """No frames, or fewer: a ValueError saying so, with the count asked."""
    with pytest.raises(ValueError, match=f"^frames must be positive, got {count}$"):
        two_sequences().head(count)


def test_stepper_outputs_carry_the_state_over_each_sequence_and_restart_it_on_the_next():
    """Every output of each sequence is the by-hand cumulative sum: the state is carried frame
    to frame within a sequence and starts afresh (batch 1) on each; the window is the held-out one."""
    held = two_sequences()
    stepper = Accumulator(offset=0.5)
    outputs = stepper_outputs(stepper, held)
    assert len(outputs) == 2 and stepper.inits == [1, 1] and stepper.windows == [20.0] * 40
    for out, x in zip(outputs, held.lnes):
        assert set(out) == {"pose", "pose_direct"}
        np.testing.assert_allclose(out["pose"], by_hand(x, 0.5), rtol=1e-5)
        np.testing.assert_allclose(out["pose_direct"], by_hand(x, 0.5) - 1.0, rtol=1e-5)


def test_check_stepper_is_the_budget_of_the_streamed_poses_against_fp32():
    """The check equals the budget of poses streamed by hand (the cumulative sums) against the
    held-out fp32 poses and ground truth, on the budget passed."""
    held = noisy()
    lnes, gt, fp32 = held.lnes, held.gt, held.fp32
    budget = TaskBudget(mpjpe_pct=3.0)
    got = check_stepper(Accumulator(offset=1.0), held, budget)
    expected = check_budget([by_hand(x, 1.0) for x in lnes], [o["pose"] for o in fp32], list(gt), budget)
    assert got.frames == 100 and got.sequences == 2 and got.budget == budget
    for mine, theirs in zip(got.metrics, expected.metrics):
        assert mine.name == theirs.name
        assert mine.change_pct == pytest.approx(theirs.change_pct, rel=1e-5, abs=1e-9)
        assert mine.limit_pct == theirs.limit_pct
    assert got.fidelity_mm == pytest.approx(expected.fidelity_mm, rel=1e-5)


def test_distance_pct_is_the_mean_distance_to_fp32_over_fp32s_mpjpe():
    """Poses 5 mm (a 3-4-5 triangle) from fp32's, whose MPJPE is 3.5 mm: 100 x 5 / 3.5 %."""
    held = two_sequences()
    outputs = [{"pose": o["pose"] + np.asarray([3.0, 4.0, 0.0], np.float32)} for o in held.fp32]
    assert distance_pct(outputs, held) == pytest.approx(100.0 * 5.0 / 3.5)


def test_held_out_takes_the_first_frames_or_all_and_runs_fp32_on_onnxruntime(monkeypatch):
    """`frames_per_sequence` frames of each sequence (0: every frame) as float32, with fp32's
    outputs streamed on an ONNX Runtime session of the fp32 graph opened with `threads`."""
    import e3dpsm.runtime

    opened = []
    monkeypatch.setattr(e3dpsm.runtime, "StepSession",
                        lambda model, threads: opened.append((model, threads)) or Accumulator(model=model))
    rng = np.random.default_rng(7)
    sequences = [type("Seq", (), {"lnes": frames(n, n), "j3d_mm": rng.normal(size=(n, 16, 3))})() for n in (6, 9)]
    some = held_out("fp32.onnx", sequences, 33.0, 4, "val", threads=3)
    assert opened == [("fp32.onnx", 3)] and some.name == "val" and some.window_ms == 33.0
    assert [len(x) for x in some.lnes] == [4, 4] and [len(g) for g in some.gt] == [4, 4]
    assert all(x.dtype == np.float32 and g.dtype == np.float32 for x, g in zip(some.lnes, some.gt))
    np.testing.assert_allclose(some.gt[1], sequences[1].j3d_mm[:4], rtol=1e-6)
    for out, s in zip(some.fp32, sequences):
        np.testing.assert_allclose(out["pose"], by_hand(np.asarray(s.lnes[:4], np.float32)), rtol=1e-5)
    every = held_out("fp32.onnx", sequences, 33.0, 0, "val")
    assert [len(x) for x in every.lnes] == [6, 9] and [len(o["pose"]) for o in every.fp32] == [6, 9]
    assert opened[-1] == ("fp32.onnx", None)
    assert [len(x) for x in held_out("fp32.onnx", sequences, 33.0, 1, "val").lnes] == [1, 1]


def test_each_runtime_opens_its_own_session(monkeypatch):
    """ONNX Runtime: StepSession; OpenVINO: its session in f32; an edge runtime: the artifact's
    own stepper, only for an artifact of that runtime; anything else is refused."""
    import e3dpsm.runtime
    from e3dpsm.runtime import openvino_session, stepping

    calls = []
    monkeypatch.setattr(e3dpsm.runtime, "StepSession", lambda m, threads: calls.append(("ort", m, threads)) or "ort")
    monkeypatch.setattr(openvino_session, "OpenVINOStepSession",
                        lambda m, threads, precision: calls.append(("ov", m, threads, precision)) or "ov")
    monkeypatch.setattr(stepping, "open_stepper", lambda m, threads: calls.append(("edge", m, threads)) or "edge")
    assert holdout.open_stepper("a.onnx", "onnxruntime", 2) == "ort"
    assert holdout.open_stepper("a.onnx", "openvino", 3) == "ov"
    assert holdout.open_stepper("a.pte", "executorch", 4) == "edge"
    assert holdout.open_stepper("a.tflite", "litert", None) == "edge"
    assert calls == [("ort", "a.onnx", 2), ("ov", "a.onnx", 3, "f32"), ("edge", "a.pte", 4), ("edge", "a.tflite", None)]
    with pytest.raises(ValueError, match=r"^a\.tflite is not run by executorch; it is a litert artifact$"):
        holdout.open_stepper("a.tflite", "executorch", None)
    with pytest.raises(ValueError, match=r"^unknown runtime 'tensorrt'; choose onnxruntime, openvino or one of "
                                         r"\('executorch', 'litert'\)$"):
        holdout.open_stepper("a.onnx", "tensorrt", None)
    assert len(calls) == 4  # neither refusal opened anything


def test_graph_outputs_and_judge_open_the_graph_on_each_runtime_asked(monkeypatch):
    """graph_outputs streams the graph opened on ONNX Runtime unless told otherwise; judge
    checks it once per runtime, with `threads`, each against the same held-out fp32."""
    opened = []

    def fake_open(model, runtime, threads):
        opened.append((model, runtime, threads))
        return Accumulator(offset=2.0 if runtime == "openvino" else 0.0)

    monkeypatch.setattr(holdout, "open_stepper", fake_open)
    held = noisy()
    outputs = holdout.graph_outputs("g.onnx", held)
    assert opened == [("g.onnx", "onnxruntime", None)]
    np.testing.assert_allclose(outputs[1]["pose"], by_hand(held.lnes[1]), rtol=1e-5)
    holdout.graph_outputs("g.onnx", held, "openvino", 5)
    assert opened[-1] == ("g.onnx", "openvino", 5)
    opened.clear()
    judged = holdout.judge("g.onnx", held, TaskBudget(), ("onnxruntime", "openvino"), threads=2)
    assert opened == [("g.onnx", "onnxruntime", 2), ("g.onnx", "openvino", 2)]
    assert list(judged.by_runtime) == ["onnxruntime", "openvino"]
    by_runtime = {r: check_budget([by_hand(x, 2.0 if r == "openvino" else 0.0) for x in held.lnes],
                                  [o["pose"] for o in held.fp32], list(held.gt)) for r in ("onnxruntime", "openvino")}
    for runtime, check in judged.by_runtime.items():
        assert check.fidelity_mm == pytest.approx(by_runtime[runtime].fidelity_mm, rel=1e-5)


def _check(upper_pct: float, fidelity_mm: float = 1.0) -> BudgetCheck:
    metric = MetricChange("mpjpe", 100.0, 100.0 + upper_pct, upper_pct, upper_pct, upper_pct, 0.0, 1.0)
    return BudgetCheck((metric,), 10, 1, fidelity_mm, TaskBudget())


def test_the_judgement_is_the_worst_runtime_and_within_only_where_every_runtime_is():
    """The worst runtime is the one furthest over its limit; within needs all; the fidelity
    is the worst runtime's distance (of fp32's 100 mm MPJPE here); the dict keeps each runtime."""
    judged = Judgement({"onnxruntime": _check(0.4, fidelity_mm=3.0), "openvino": _check(1.3, fidelity_mm=2.0)})
    assert judged.worst is judged.by_runtime["openvino"] and judged.worst_share == pytest.approx(1.3)
    assert judged.fidelity_pct == pytest.approx(3.0)  # onnxruntime's: 100 x 3 / 100, the larger
    assert not judged.within
    assert judged.to_dict() == {"within": False, "by_runtime": {"onnxruntime": _check(0.4, 3.0).to_dict(),
                                                                "openvino": _check(1.3, 2.0).to_dict()}}
    both = Judgement({"onnxruntime": _check(1.0), "openvino": _check(0.2)})
    assert both.within and both.to_dict()["within"] is True  # inclusive, both
    assert both.worst is both.by_runtime["onnxruntime"]


def test_held_out_frames_and_judgements_cannot_be_changed_once_made():
    """One HeldOut serves every trial of the search and the final check, and a Judgement is
    reported as made: assigning to either is refused."""
    held = two_sequences()
    with pytest.raises(dataclasses.FrozenInstanceError):
        held.lnes = held.lnes[:1]
    judged = Judgement({"onnxruntime": _check(0.4)})
    with pytest.raises(dataclasses.FrozenInstanceError):
        judged.by_runtime = {}
