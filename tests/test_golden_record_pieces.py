"""e3dpsm.golden.record on a prepared folder written here by hand (the layout in
e3dpsm/data/prepared.py's docstring) and a numpy stepper: which frames a rollout of N steps
takes (sequences in order, replayed from the start), what the record keeps of the reference's
outputs and states, and every field of its manifest, each against a value computed here."""
from __future__ import annotations

import hashlib
import json
import math

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper, numpy_helper

from e3dpsm.errors import DataError, InputError
from e3dpsm.golden.record import Reference, onnx_reference, prepared_rollout, record_golden, sha256_file
from e3dpsm.golden.store import load_golden
from e3dpsm.golden.tolerances import PROFILES
from e3dpsm.graph_metadata import GraphMetadata
from e3dpsm.state import StateSpec, state_input_name, state_output_name

H, W = 4, 6
J = 16
WINDOW_MS = 25.0


def _write_prepared(root, sequences: list[tuple[str, str, int]], hw: tuple[int, int] = (H, W)) -> None:
    """Sequence k's frame f holds the value 100 k + f everywhere; its pose the value 1000 k + f."""
    root.mkdir(parents=True)
    entries = []
    for k, (name, split, frames) in enumerate(sequences):
        (root / name).mkdir()
        value = (100 * k + np.arange(frames, dtype=np.float32))[:, None, None, None]
        np.save(root / name / "lnes.npy", np.broadcast_to(value, (frames, 2, *hw)).astype(np.float16))
        np.savez(root / name / "pose.npz",
                 j3d_mm=np.broadcast_to((1000 * k + np.arange(frames, dtype=np.float32))[:, None, None],
                                        (frames, J, 3)).astype(np.float32),
                 j2d_px=np.zeros((frames, J, 2), np.float32), visible=np.ones((frames, J), np.uint8),
                 action=np.zeros(frames, np.int16), t_us=np.arange(frames, dtype=np.int64) * 25_000)
        entries.append({"name": name, "split": split, "frames": frames})
    meta = {"format": "e3dpsm-prepared/1", "window_ms": 25.0, "window_us": 25_000, "height": hw[0], "width": hw[1],
            "sequences": entries}
    (root / "meta.json").write_text(json.dumps(meta))


def _frame_value(frame: np.ndarray) -> float:
    assert np.all(frame == frame.flat[0])
    return float(frame.flat[0])


def test_a_rollout_takes_the_sequences_in_order_and_replays_them(tmp_path) -> None:
    _write_prepared(tmp_path / "p", [("a", "train", 3), ("empty", "train", 0), ("b", "test", 2)])
    frames, segments, data = prepared_rollout(tmp_path / "p", 8)
    assert segments == [{"sequence": "a", "first_frame": 0, "steps": 3}, {"sequence": "b", "first_frame": 0, "steps": 2},
                        {"sequence": "a", "first_frame": 0, "steps": 3}]
    got = list(frames)
    assert [_frame_value(f) for f, _ in got] == [0, 1, 2, 200, 201, 0, 1, 2]  # `empty` (k = 1) has no frames
    assert [float(gt[0, 0]) for _, gt in got] == [0, 1, 2, 2000, 2001, 0, 1, 2]
    assert got[0][0].dtype == np.float16 and got[0][0].shape == (2, H, W)
    assert got[0][1].dtype == np.float32 and got[0][1].shape == (J, 3)
    assert (data.height, data.width) == (H, W)
    _, short, _ = prepared_rollout(tmp_path / "p", 2, split="test")
    assert short == [{"sequence": "b", "first_frame": 0, "steps": 2}]
    _, cut, _ = prepared_rollout(tmp_path / "p", 4)
    assert cut == [{"sequence": "a", "first_frame": 0, "steps": 3}, {"sequence": "b", "first_frame": 0, "steps": 1}]
    _, exact, _ = prepared_rollout(tmp_path / "p", 3)
    assert exact == [{"sequence": "a", "first_frame": 0, "steps": 3}]


def test_a_split_without_frames_is_refused(tmp_path) -> None:
    _write_prepared(tmp_path / "p", [("a", "train", 3), ("empty", "val", 0)])
    with pytest.raises(DataError, match=r"^\S+p holds no frames in split 'val'$"):
        prepared_rollout(tmp_path / "p", 5, split="val")


class SumStepper:
    """s' = s / 2 + mean(frame); pose[j] = s'[0] + j (mm, every axis)."""

    def __init__(self) -> None:
        self.steps = 0

    def init_state(self, batch: int = 1) -> dict[str, np.ndarray]:
        return {"s": np.full((batch, 3), 1.0, np.float32)}

    def step(self, lnes, state, window_ms):
        assert lnes.dtype == np.float32 and lnes.shape == (1, 2, H, W) and window_ms == WINDOW_MS
        assert state["s"].shape == (1, 3)  # one stream, as the graph's sessions check
        self.steps += 1
        new = (state["s"] / 2 + lnes.mean()).astype(np.float32)
        pose = (new[0, 0] + np.arange(J, dtype=np.float32))[None, :, None] * np.ones(3, np.float32)
        return {"pose": pose.astype(np.float32)}, {"s": new}


def _reference(path=None, shape=(2, H, W)) -> Reference:
    return Reference(SumStepper(), "onnx", path, "toy", shape, ("pose",),
                     (StateSpec("s", (3,)).to_metadata(),), tuple(f"j{i}" for i in range(J)))


def test_the_record_keeps_the_rollout_and_says_where_it_came_from(tmp_path) -> None:
    _write_prepared(tmp_path / "p", [("a", "train", 3), ("b", "test", 2)])
    source = tmp_path / "step.onnx"
    source.write_bytes(b"a graph" * 1000)
    reference = _reference(source)
    manifest = record_golden(reference, tmp_path / "p", tmp_path / "golden", steps=7, window_ms=WINDOW_MS,
                             header={"tool": "test", "window_ms": -1.0})
    assert reference.stepper.steps == 7
    values = [0, 1, 2, 100, 101, 0, 1]
    truth = [0, 1, 2, 1000, 1001, 0, 1]
    state, poses = 1.0, []
    for value in values:  # the stepper's recurrence in plain floats
        state = state / 2 + value
        poses.append(state + np.arange(J))
    pose = np.array(poses)[:, :, None] * np.ones(3)
    gt = np.array(truth, float)[:, None, None] * np.ones((J, 3))
    expected_mpjpe = float(np.mean(np.linalg.norm(pose - gt, axis=-1)))
    assert manifest["tool"] == "test" and manifest["window_ms"] == WINDOW_MS  # the header, then the record's own
    assert manifest["source"] == {"kind": "onnx", "variant": "toy", "file": "step.onnx",
                                  "sha256": hashlib.sha256(source.read_bytes()).hexdigest()}
    assert manifest["data"] == {"path": str(tmp_path / "p"), "split": "all", "prepared_window_ms": 25.0,
                                "segments": [{"sequence": "a", "first_frame": 0, "steps": 3},
                                             {"sequence": "b", "first_frame": 0, "steps": 2},
                                             {"sequence": "a", "first_frame": 0, "steps": 2}]}
    assert manifest["states"] == [StateSpec("s", (3,)).to_metadata()] and manifest["joints"] == [f"j{i}" for i in range(J)]
    assert manifest["tolerances"] == {name: p.to_dict() for name, p in PROFILES.items()} and manifest["tolerances"]
    assert manifest["mpjpe_scale_mm"] == pytest.approx(expected_mpjpe, rel=1e-6)
    assert 0 <= manifest["record_seconds"] < 60 and manifest["record_seconds"] == round(manifest["record_seconds"], 2)
    assert manifest["steps"] == 7 and manifest["snapshot_steps"] == [0, 1, 2, 5, 6]
    golden = load_golden(tmp_path / "golden")
    assert golden.manifest == manifest
    assert [_frame_value(golden.frame(s)) for s in range(7)] == values
    assert [golden.window_ms(s) for s in range(7)] == [WINDOW_MS] * 7
    np.testing.assert_allclose(golden.output("pose").reshape(7, J, 3), pose.astype(np.float32), rtol=1e-6)
    np.testing.assert_allclose(golden.gt_mm, gt, rtol=0)


def test_every_state_is_kept_when_asked_and_a_record_without_a_file_names_none(tmp_path) -> None:
    _write_prepared(tmp_path / "p", [("a", "train", 4)])
    manifest = record_golden(_reference(), tmp_path / "p", tmp_path / "golden", steps=4, window_ms=WINDOW_MS,
                             all_states=True, split="train")
    assert manifest["snapshot_steps"] == [0, 1, 2, 3] and manifest["data"]["split"] == "train"
    assert manifest["source"] == {"kind": "onnx", "variant": "toy"}
    with pytest.raises(Exception):  # the folder exists: kept unless forced
        record_golden(_reference(), tmp_path / "p", tmp_path / "golden", steps=4, window_ms=WINDOW_MS)
    again = record_golden(_reference(), tmp_path / "p", tmp_path / "golden", steps=2, window_ms=WINDOW_MS, force=True)
    assert again["steps"] == 2 and again["snapshot_steps"] == [0, 1]


def test_references_are_values() -> None:
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        _reference().kind = "checkpoint"


def test_frames_of_another_size_are_refused_before_any_step(tmp_path) -> None:
    _write_prepared(tmp_path / "p", [("a", "train", 2)], hw=(4, 8))
    reference = _reference()
    with pytest.raises(DataError, match=r"^\S+p holds 4 x 8 frames, the toy model takes 4 x 6; prepare the data for it$"):
        record_golden(reference, tmp_path / "p", tmp_path / "golden", steps=2, window_ms=WINDOW_MS)
    assert reference.stepper.steps == 0 and not (tmp_path / "golden").exists()


def test_progress_goes_through_tqdm_only_when_asked(tmp_path, monkeypatch) -> None:
    import sys
    import types

    calls: list[dict] = []
    monkeypatch.setitem(sys.modules, "tqdm", types.SimpleNamespace(tqdm=lambda it, **kw: calls.append(kw) or it))
    _write_prepared(tmp_path / "p", [("a", "train", 2)])
    record_golden(_reference(), tmp_path / "p", tmp_path / "quiet", steps=2, window_ms=WINDOW_MS)
    assert calls == []
    record_golden(_reference(), tmp_path / "p", tmp_path / "shown", steps=2, window_ms=WINDOW_MS, progress=True)
    assert calls == [{"total": 2, "desc": "golden record", "unit": "step", "leave": False, "disable": None}]


def test_sha256_of_a_file_read_in_chunks(tmp_path) -> None:
    data = np.random.default_rng(0).bytes(3000)
    (tmp_path / "f").write_bytes(data)
    assert sha256_file(tmp_path / "f") == hashlib.sha256(data).hexdigest()
    assert sha256_file(tmp_path / "f", chunk=7) == hashlib.sha256(data).hexdigest()  # many reads, the last short
    (tmp_path / "empty").write_bytes(b"")
    assert sha256_file(tmp_path / "empty") == hashlib.sha256(b"").hexdigest()


def _toy_graph(path, quantization: dict | None = None) -> None:
    """s' = s + mean(lnes); pose = s' (metadata as the export writes it)."""
    inits = [numpy_helper.from_array(np.array([-1, 1], np.int64), "column")]
    nodes = [helper.make_node("ReduceMean", ["lnes"], ["mean"], axes=[1, 2, 3], keepdims=0),
             helper.make_node("Reshape", ["mean", "column"], ["mean_col"]),
             helper.make_node("Add", [state_input_name("s"), "mean_col"], [state_output_name("s")]),
             helper.make_node("Mul", ["window_ms", "window_ms"], ["unused"]),
             helper.make_node("Identity", [state_output_name("s")], ["pose"])]
    value = lambda name, *shape: helper.make_tensor_value_info(name, TensorProto.FLOAT, ["B", *shape])  # noqa: E731
    graph = helper.make_graph(nodes, "toy", [value("lnes", 2, H, W), value("window_ms"), value(state_input_name("s"), 3)],
                              [value("pose", 3), value(state_output_name("s"), 3)], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    GraphMetadata(states=(StateSpec("s", (3,)),),
                  inputs={"frame": {"name": "lnes", "shape": ["B", 2, H, W]}, "window": {"name": "window_ms", "shape": ["B"]}},
                  outputs=[{"name": "pose"}], config={"variant": "toy"}, joints=["a", "b"],
                  quantization=quantization).write_to(model)
    onnx.save(model, str(path))


def test_an_fp32_graph_is_a_reference_and_a_quantised_one_is_not(tmp_path) -> None:
    _toy_graph(tmp_path / "step.onnx")
    reference = onnx_reference(tmp_path / "step.onnx", threads=1)
    assert (reference.kind, reference.path, reference.variant) == ("onnx", tmp_path / "step.onnx", "toy")
    assert (reference.frame_shape, reference.output_names, reference.joints) == ((2, H, W), ("pose",), ("a", "b"))
    assert reference.states == (StateSpec("s", (3,)).to_metadata(),)
    outputs, state = reference.stepper.step(np.ones((1, 2, H, W), np.float32), reference.stepper.init_state(1), 20.0)
    assert np.allclose(state["s"], 1.0) and np.allclose(outputs["pose"], 1.0)
    _toy_graph(tmp_path / "int8.onnx", quantization={"mode": "int8"})
    with pytest.raises(InputError, match=r"^\S+int8\.onnx is a int8 graph; record the golden from the fp32 graph or "
                                         r"the checkpoint, then check compressed graphs against it$"):
        onnx_reference(tmp_path / "int8.onnx")


def test_a_checkpoints_model_is_a_reference_with_the_models_layout() -> None:
    from _model_helpers import randomised_tiny

    from e3dpsm.golden.record import torch_reference
    from e3dpsm.joints import JOINT_NAMES
    from e3dpsm.models import OUTPUT_NAMES

    model = randomised_tiny(0)
    reference = torch_reference(model, "checkpoint", "ck.pt")
    assert (reference.kind, reference.path, reference.variant) == ("checkpoint", __import__("pathlib").Path("ck.pt"),
                                                                   "tiny")
    assert reference.frame_shape == (2, 64, 96) and reference.output_names == tuple(OUTPUT_NAMES)
    assert reference.joints == tuple(JOINT_NAMES) and len(reference.joints) == 16
    assert reference.states == tuple(s.to_metadata() for s in model.state_spec())
    assert torch_reference(model, "variant", None).path is None
    assert not math.isnan(reference.stepper.init_state(1)[reference.states[0]["name"]].sum())
