"""The golden record's layout on disk (e3dpsm/golden/store.py): the snapshot series and state
samples, what the writer keeps of each step (checked against explicit loops over the steps),
the frames decoded back exactly, the manifest it writes, and each refusal of the writer and the
loader compared whole."""
from __future__ import annotations

import json

import numpy as np
import pytest

from e3dpsm.errors import DataError
from e3dpsm.golden.store import (ARRAYS_FILE, MANIFEST_FILE, STATE_SAMPLES, GoldenRecord, GoldenWriter,
                                 load_golden, sample_indices, snapshot_steps)

FRAME = (2, 3, 5)
BIG = (10, 9)  # 90 elements: over twice STATE_SAMPLES, sampled
SMALL = (4,)  # kept whole
MANIFEST = {"source": {"kind": "onnx"}, "window_ms": 20.0, "mpjpe_scale_mm": 1.0, "joints": ["a", "b", "c", "d"],
            "states": [{"name": "big", "shape": [1, *BIG]}, {"name": "small", "shape": [1, *SMALL]}]}


@pytest.mark.parametrize("steps, chosen", [
    (1, [0]), (2, [0, 1]), (3, [0, 1, 2]), (7, [0, 1, 2, 5, 6]), (10, [0, 1, 2, 5, 9]), (11, [0, 1, 2, 5, 10]),
    (60, [0, 1, 2, 5, 10, 20, 50, 59]), (1000, [0, 1, 2, 5, 10, 20, 50, 100, 200, 500, 999]),
])
def test_snapshots_are_the_1_2_5_series_and_the_last_step(steps, chosen) -> None:
    assert snapshot_steps(steps) == chosen
    assert snapshot_steps(steps, every_step=True) == list(range(steps))


def test_state_samples() -> None:
    # docs/golden-and-diagnose.md: "all of them for states of up to 64 numbers"; the manifest
    # records the sample size of larger ones (state_samples)
    assert STATE_SAMPLES == 32
    np.testing.assert_array_equal(sample_indices("s", 64), np.arange(64))
    picked = sample_indices("s", 65)
    assert picked.dtype == np.int64 and len(picked) == 32 and len(set(picked.tolist())) == 32
    assert np.all(np.diff(picked) > 0) and picked.min() >= 0 and picked.max() < 65
    np.testing.assert_array_equal(picked, sample_indices("s", 65))  # the same for the same name, every time
    assert not np.array_equal(picked, sample_indices("t", 65))
    assert len(sample_indices("s", 1000, count=5)) == 5 and len(sample_indices("s", 10, count=5)) == 10


def _step_data(steps: int, seed: int = 0, gt: bool = True):
    rng = np.random.default_rng(seed)
    for k in range(steps):
        frame = np.where(rng.random(FRAME) < 0.3, rng.random(FRAME), 0.0).astype(np.float16)
        outputs = {"pose": rng.normal(size=(1, 4, 3)).astype(np.float32) * 100,
                   "aux": rng.normal(size=(1, 4, 3)).astype(np.float32)}
        state = {"big": rng.normal(size=(1, *BIG)).astype(np.float32) * (k + 1),
                 "small": -np.abs(rng.normal(size=(1, *SMALL))).astype(np.float32) * 3}
        yield frame, 20.0 + k, (rng.normal(size=(4, 3)) if gt else None), outputs, state


def _writer(steps: int = 12, **kwargs) -> tuple[GoldenWriter, list]:
    writer = GoldenWriter(FRAME, ["pose", "aux"], {"big": BIG, "small": SMALL}, steps, **kwargs)
    data = list(_step_data(steps))
    for step in data:
        writer.add(*step)
    return writer, data


def test_the_writer_keeps_what_each_step_needs() -> None:
    writer, data = _writer()
    arrays = writer.arrays()
    snaps = snapshot_steps(12)
    assert writer.steps == 12 and writer.snapshots == snaps
    np.testing.assert_array_equal(arrays["snapshot_steps"], snaps)
    np.testing.assert_array_equal(arrays["window_ms"], [20.0 + k for k in range(12)])
    assert arrays["window_ms"].dtype == np.float32
    nnz = [int(np.count_nonzero(f)) for f, *_ in data]
    np.testing.assert_array_equal(arrays["lnes.nnz"], nnz)
    np.testing.assert_array_equal(arrays["lnes.values"], np.concatenate([f.reshape(-1)[f.reshape(-1) != 0]
                                                                          for f, *_ in data]))
    assert arrays["lnes.values"].dtype == np.float16 and arrays["lnes.mask"].shape == (12, (30 + 7) // 8)
    np.testing.assert_array_equal(arrays["gt_mm"], np.stack([g for _, _, g, _, _ in data]).astype(np.float32))
    for name in ("pose", "aux"):
        np.testing.assert_array_equal(arrays[f"out.{name}"], np.stack([o[name][0] for *_, o, _ in data]))
    index = sample_indices("big", 90)
    np.testing.assert_array_equal(arrays["state_index.big"], index)
    np.testing.assert_array_equal(arrays["state_index.small"], np.arange(4))
    for name, shape in (("big", BIG), ("small", SMALL)):
        states = [s[name][0] for *_, s in data]
        np.testing.assert_array_equal(arrays[f"state_absmax.{name}"], [np.abs(s).max() for s in states])
        picked = arrays[f"state_index.{name}"]
        np.testing.assert_array_equal(arrays[f"state_sample.{name}"], [s.reshape(-1)[picked] for s in states])
        np.testing.assert_array_equal(arrays[f"snapshot.{name}"], [states[k] for k in snaps])
        assert arrays[f"snapshot.{name}"].shape == (len(snaps), *shape)
    record = GoldenRecord({"steps": 12, "frame_shape": list(FRAME), "outputs": ["pose", "aux"],
                           "states": [{"name": "big"}, {"name": "small"}]}, arrays)
    for k, (frame, window, gt, outputs, state) in enumerate(data):
        np.testing.assert_array_equal(record.frame(k), frame.astype(np.float32)[None])
        assert record.window_ms(k) == window
    assert record.steps == 12 and record.frame_shape == FRAME and record.output_names == ["pose", "aux"]
    assert record.state_names == ["big", "small"] and record.gt_mm is arrays["gt_mm"]
    np.testing.assert_array_equal(record.snapshot_steps, snaps)
    assert record.output("aux") is arrays["out.aux"] and record.snapshot("big") is arrays["snapshot.big"]
    assert record.state_index("big") is arrays["state_index.big"] and record.state_sample("small") is arrays[
        "state_sample.small"] and record.state_absmax("big") is arrays["state_absmax.big"]


def test_every_step_kept_whole_when_asked() -> None:
    writer, data = _writer(5, all_states=True)
    np.testing.assert_array_equal(writer.arrays()["snapshot.big"], [s["big"][0] for *_, s in data])


def test_ground_truth_is_kept_only_when_every_step_has_it() -> None:
    writer = GoldenWriter(FRAME, ["pose", "aux"], {"big": BIG, "small": SMALL}, 3)
    for k, step in enumerate(_step_data(3)):
        writer.add(*(step[:2] + ((None if k == 1 else step[2]),) + step[3:]))
    assert "gt_mm" not in writer.arrays()
    assert GoldenRecord({"steps": 3}, {**writer.arrays()}).gt_mm is None


def test_an_empty_state_has_magnitude_zero() -> None:
    writer = GoldenWriter(FRAME, [], {"none": (0,)}, 1)
    frame = np.zeros(FRAME, np.float16)
    writer.add(frame, 20.0, None, {}, {"none": np.zeros((1, 0), np.float32)})
    arrays = writer.arrays()
    np.testing.assert_array_equal(arrays["state_absmax.none"], [0.0])
    assert arrays["lnes.nnz"].tolist() == [0] and arrays["lnes.values"].size == 0


@pytest.mark.parametrize("frame", [np.zeros(FRAME, np.float32), np.zeros((2, 3, 4), np.float16)])
def test_the_writer_takes_float16_frames_of_its_shape_only(frame) -> None:
    writer = GoldenWriter(FRAME, ["pose"], {}, 2)
    with pytest.raises(DataError) as refused:
        writer.add(frame, 20.0, None, {"pose": np.zeros((1, 4, 3))}, {})
    assert str(refused.value) == (f"golden frames must be float16 [2, 3, 5], got {frame.dtype} "
                                  f"{list(frame.shape)}")
    assert writer.steps == 0


def test_a_short_rollout_is_refused() -> None:
    writer = GoldenWriter(FRAME, ["pose", "aux"], {"big": BIG, "small": SMALL}, 12)
    for step in list(_step_data(12))[:11]:
        writer.add(*step)
    with pytest.raises(DataError) as refused:
        writer.arrays()
    assert str(refused.value) == "the rollout has 11 steps, 12 were planned"


def test_written_and_loaded_back(tmp_path) -> None:
    writer, data = _writer()
    manifest = dict(MANIFEST)
    written = writer.write(tmp_path / "golden", manifest)
    on_disk = json.loads((tmp_path / "golden" / MANIFEST_FILE).read_text())
    assert written == on_disk
    assert sorted(p.name for p in (tmp_path / "golden").iterdir()) == ["golden.json", "rollout.npz"]  # docs
    assert {k: written[k] for k in ("format", "steps", "frame_shape", "outputs", "snapshot_steps",
                                    "state_samples", "arrays")} == {
        "format": "e3dpsm-golden/1", "steps": 12, "frame_shape": list(FRAME), "outputs": ["pose", "aux"],
        "snapshot_steps": snapshot_steps(12), "state_samples": 32, "arrays": "rollout.npz"}
    assert written["bytes"] == {"arrays": (tmp_path / "golden" / ARRAYS_FILE).stat().st_size}
    assert written["source"] == {"kind": "onnx"}
    loaded = load_golden(tmp_path / "golden")
    assert loaded.folder == tmp_path / "golden" and loaded.manifest == written
    for name, array in writer.arrays().items():
        np.testing.assert_array_equal(loaded.arrays[name], array)
    np.testing.assert_array_equal(loaded.frame(3), data[3][0].astype(np.float32)[None])
    with pytest.raises(Exception):  # an existing folder is kept unless forced
        writer.write(tmp_path / "golden", manifest)
    again = writer.write(tmp_path / "golden", {**manifest, "source": {"kind": "again"}}, force=True)
    assert load_golden(tmp_path / "golden").manifest == again


def test_the_loader_names_what_is_wrong(tmp_path) -> None:
    writer, _ = _writer(3)
    manifest = dict(MANIFEST)
    folder = tmp_path / "golden"
    writer.write(folder, manifest)

    def refusal() -> str:
        with pytest.raises(DataError) as refused:
            load_golden(folder)
        return str(refused.value)

    (folder / ARRAYS_FILE).rename(tmp_path / "kept.npz")
    assert refusal() == (f"{folder} is not a golden record (needs golden.json and rollout.npz); "
                         "write one with `e3dpsm golden record`")
    (tmp_path / "kept.npz").rename(folder / ARRAYS_FILE)
    good = (folder / MANIFEST_FILE).read_text()
    (folder / MANIFEST_FILE).write_text("{not json")
    assert refusal() == (f"{folder / MANIFEST_FILE}: cannot read JSON (Expecting property name enclosed in double "
                         "quotes: line 1 column 2 (char 1))")
    (folder / MANIFEST_FILE).write_text("[1, 2]")
    assert refusal() == f"{folder / MANIFEST_FILE}: format 'list', this e3dpsm reads 'e3dpsm-golden/1'"
    (folder / MANIFEST_FILE).write_text(json.dumps({**json.loads(good), "format": "e3dpsm-golden/0"}))
    assert refusal() == f"{folder / MANIFEST_FILE}: format 'e3dpsm-golden/0', this e3dpsm reads 'e3dpsm-golden/1'"
    (folder / MANIFEST_FILE).write_text(json.dumps({**json.loads(good), "outputs": ["pose", "aux", "extra"]}))
    assert refusal() == f"{folder / ARRAYS_FILE} lacks out.extra; record the golden again"
    five = ["pose", "aux", "e1", "e2", "e3", "e4", "e5"]
    (folder / MANIFEST_FILE).write_text(json.dumps({**json.loads(good), "outputs": five}))
    assert refusal() == f"{folder / ARRAYS_FILE} lacks out.e1, out.e2, out.e3, out.e4; record the golden again"
    (folder / MANIFEST_FILE).write_text(good)
    arrays = (folder / ARRAYS_FILE).read_bytes()
    (folder / ARRAYS_FILE).write_bytes(b"not a zip archive")
    assert refusal().startswith(f"{folder / ARRAYS_FILE}: cannot read the arrays (truncated or corrupted?): ")
    (folder / ARRAYS_FILE).write_bytes(arrays)
    (folder / MANIFEST_FILE).write_text(good)
    assert load_golden(folder).steps == 3
