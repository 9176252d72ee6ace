"""e3dpsm/golden/store_checks.py and tolerances.py field by field: a small, hand-built golden
record that passes, and each field or array of it broken on its own, with the one line the
user gets. (Records written by `golden record` and damaged at random: the fuzz tests.)"""
from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from e3dpsm.errors import DataError, InputError
from e3dpsm.golden import tolerances
from e3dpsm.golden.store_checks import check_arrays, check_manifest

PATH = Path("golden/manifest.json")
FIX = "record the golden again"
STEPS, FRAME, SNAPSHOTS = 3, [2, 2, 5], [0, 2]  # frames of 20 values: 3 mask bytes, 4 pad bits


def _manifest(steps: int = STEPS, frame: list[int] = FRAME) -> dict:
    return {"steps": steps, "frame_shape": list(frame), "outputs": ["pose", "pose_direct"], "joints": ["a", "b"],
            "states": [{"name": "s5", "shape": [1, 4]}, {"name": "scalar", "shape": [1]}],
            "source": {"variant": "tiny"}, "mpjpe_scale_mm": 1000.0,
            "tolerances": {"fp32": tolerances.PROFILES["fp32"].to_dict(), "int8": tolerances.PROFILES["int8"].to_dict()},
            "host_rollouts": [{"file": "host/step-onnxruntime.npz", "sha256": "ab", "runtime": "onnxruntime"}]}


def _arrays(steps: int = STEPS, frame: list[int] = FRAME, snapshots: list[int] = SNAPSHOTS) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    marked = rng.random((steps, math.prod(frame))) < 0.3
    arrays = {"lnes.mask": np.packbits(marked, axis=1), "lnes.nnz": marked.sum(axis=1).astype(np.int32),
              "lnes.values": rng.random(int(marked.sum())).astype(np.float32),
              "window_ms": np.full(steps, 20.0, np.float32), "snapshot_steps": np.array(snapshots, np.int64),
              "gt_mm": np.zeros((steps, 2, 3), np.float32)}
    for name in ("pose", "pose_direct"):
        arrays[f"out.{name}"] = np.zeros((steps, 2, 3), np.float32)
    for name, dims, samples in (("s5", (4,), 2), ("scalar", (), 0)):
        elements = math.prod(dims)
        arrays.update({f"state_absmax.{name}": np.ones(steps, np.float32),
                       f"state_index.{name}": np.arange(samples, dtype=np.int64) * (elements - 1),
                       f"state_sample.{name}": np.zeros((steps, samples), np.float32),
                       f"snapshot.{name}": np.zeros((len(snapshots), *dims), np.float32)})
    return arrays


def test_the_hand_built_record_passes() -> None:
    check_manifest(_manifest(), PATH)
    check_arrays(_manifest(), _arrays(), PATH)
    without_gt = _arrays()
    del without_gt["gt_mm"]
    check_arrays(_manifest(), without_gt, PATH)  # ground truth is optional
    relaxed = {**_manifest(), "mpjpe_scale_mm": None, "tolerances": {}, "host_rollouts": []}
    del relaxed["host_rollouts"], relaxed["tolerances"]
    check_manifest(relaxed, PATH)
    any_batch = _manifest()
    any_batch["states"][0]["shape"] = [0, 4]  # the batch dimension is the runtime's to choose
    check_manifest(any_batch, PATH)


def _set(field, value):
    def change(manifest):
        manifest[field] = value
    return change


def _state(index, **changes):
    def change(manifest):
        manifest["states"][index].update(changes)
    return change


@pytest.mark.parametrize("change, message", [
    (_set("steps", 0), "'steps' is 0, expected a positive whole number"),
    (_set("steps", True), "'steps' is True, expected a positive whole number"),
    (_set("steps", "3"), "'steps' is '3', expected a positive whole number"),
    (lambda m: m.pop("steps"), "'steps' is None, expected a positive whole number"),
    (_set("frame_shape", []), "'frame_shape' is [], expected a list of positive whole numbers"),
    (_set("frame_shape", [2, 0, 5]), "'frame_shape' is [2, 0, 5], expected a list of positive whole numbers"),
    (_set("frame_shape", "2x2"), "'frame_shape' is '2x2', expected a list of positive whole numbers"),
    (_set("outputs", []), "'outputs' is [], expected a list of distinct names"),
    (_set("outputs", ["pose", "pose"]), "'outputs' is ['pose', 'pose'], expected a list of distinct names"),
    (_set("outputs", "pose"), "'outputs' is 'pose', expected a list of distinct names"),
    (_set("joints", ["a", 2]), "'joints' is ['a', 2], expected a list of distinct names"),
    (_set("joints", ["j" * 80, 1]), f"'joints' is {repr(['j' * 80, 1])[:60]}, expected a list of distinct names"),
    (_set("states", {}), "'states' is {}, expected a list of {name, shape: [batch, dims...]} with distinct names"),
    (_state(0, name=3), "'states' is"),
    (_state(0, shape=(1, 4)), "'states' is"),
    (_state(0, shape=[]), "'states' is"),
    (_state(0, shape=[1, 0]), "'states' is"),
    (_state(0, shape=[1, True]), "'states' is"),
    (_state(1, name="s5"), "'states' is"),
    (lambda m: m["states"].append(5), "'states' is"),
    (_set("source", "tiny"), "'source' is 'tiny', expected an object naming the variant"),
    (_set("mpjpe_scale_mm", 0), "'mpjpe_scale_mm' is 0, expected a positive number or null"),
    (_set("mpjpe_scale_mm", float("nan")), "'mpjpe_scale_mm' is nan, expected a positive number or null"),
    (_set("mpjpe_scale_mm", True), "'mpjpe_scale_mm' is True, expected a positive number or null"),
    (_set("tolerances", []), "'tolerances' must map profile names to objects"),
    (_set("tolerances", {"fp32": 1}), "'tolerances' must map profile names to objects"),
    (_set("tolerances", {"x": {"name": "x", "kind": "exact", "pose_atol_mm": 1, "wild": 2, "extra": {}}}), None),
    (_set("tolerances", {"x": {"kind": "exact"}}), "tolerance profile 'x': broken tolerance profile"),
    (_set("tolerances", {"x": {"name": "x", "kind": "loose"}}), "tolerance profile 'x' is broken"),
    (_set("tolerances", {"x": {"name": "x", "kind": "exact"}}), "tolerance profile 'x' is broken"),
    (_set("tolerances", {"x": {"name": "x", "kind": "budget", "state_rtol": -0.1}}), "tolerance profile 'x' is broken"),
    (_set("tolerances", {"x": {"name": "x", "kind": "budget", "max_growth": float("inf")}}),
     "tolerance profile 'x' is broken"),
    (_set("tolerances", {"x": {"name": "x", "kind": "exact", "pose_atol_mm": "0.01"}}),
     "tolerance profile 'x' is broken"),
    (_set("host_rollouts", {}), "'host_rollouts' must list {file: host/NAME.npz, sha256, runtime} objects"),
    (_set("host_rollouts", [{"file": "../x.npz", "sha256": "ab", "runtime": "r"}]), "'host_rollouts' must list"),
    (_set("host_rollouts", [{"file": "host/x.npz", "runtime": "r"}]), "'host_rollouts' must list"),
    (_set("host_rollouts", [{"file": "host/x.npz", "sha256": "ab", "runtime": 1}]), "'host_rollouts' must list"),
])
def test_each_broken_manifest_field_is_one_line_naming_it(change, message) -> None:
    manifest = _manifest()
    change(manifest)
    if message is None:  # unknown keys of a profile are ignored, as newer records may add some
        check_manifest(manifest, PATH)
        return
    with pytest.raises(DataError) as info:
        check_manifest(manifest, PATH)
    text = str(info.value)
    assert text.startswith(f"{PATH}: {message}") and text.endswith(f"; {FIX}") and "\n" not in text


def test_a_manifest_that_is_no_object_says_what_it_is() -> None:
    with pytest.raises(DataError) as info:
        check_manifest([1], PATH)
    assert str(info.value) == f"{PATH}: expected a JSON object, got list; {FIX}"


def test_zero_is_a_valid_state_tolerance() -> None:
    manifest = _manifest()
    manifest["tolerances"] = {"x": {"name": "x", "kind": "budget", "state_rtol": 0.0, "max_growth": 0}}
    check_manifest(manifest, PATH)


def _array(key, value):
    def change(arrays):
        arrays[key] = value
    return change


@pytest.mark.parametrize("change, message", [
    (_array("lnes.mask", np.zeros((STEPS, 4), np.uint8)), "array lnes.mask is uint8 [3, 4], the manifest implies [3, 3]"),
    (_array("lnes.nnz", np.zeros(STEPS, np.float32)), "array lnes.nnz is float32 [3], the manifest implies [3]"),
    (_array("window_ms", np.full(STEPS, 20, np.int32)), "array window_ms is int32 [3], the manifest implies [3]"),
    (_array("out.pose", np.zeros((STEPS, 3, 3), np.float32)), "array out.pose is float32 [3, 3, 3], the manifest "
                                                               "implies [3, 2, 3]"),
    (_array("gt_mm", np.zeros((STEPS, 2), np.float32)), "array gt_mm is float32 [3, 2], the manifest implies [3, 2, 3]"),
    (_array("snapshot_steps", np.zeros((2, 1), np.int64)), "array snapshot_steps is int64 [2, 1], the manifest "
                                                           "implies [2]"),
    (_array("state_absmax.s5", np.ones(STEPS + 1, np.float32)), "array state_absmax.s5 is float32 [4], the manifest "
                                                                "implies [3]"),
    (_array("state_sample.s5", np.zeros((STEPS, 3), np.float32)), "array state_sample.s5 is float32 [3, 3], the "
                                                                   "manifest implies [3, 2]"),
    (_array("snapshot.s5", np.zeros((2, 5), np.float32)), "array snapshot.s5 is float32 [2, 5], the manifest implies "
                                                          "[2, 4]"),
    (_array("window_ms", np.array([20.0, 0.0, 20.0], np.float32)), "window_ms holds values that are not positive "
                                                                    "numbers"),
    (_array("window_ms", np.array([20.0, np.nan, 20.0], np.float32)), "window_ms holds values that are not positive "
                                                                       "numbers"),
    (_array("snapshot_steps", np.array([2, 2])), "snapshot_steps [2, 2] are not increasing steps of 0..2"),
    (_array("snapshot_steps", np.array([-1, 2])), "snapshot_steps [-1, 2] are not increasing steps of 0..2"),
    (_array("snapshot_steps", np.array([0, 3])), "snapshot_steps [0, 3] are not increasing steps of 0..2"),
    (_array("state_index.s5", np.array([0, 4])), "state_index.s5 points outside its 4 elements"),
    (_array("state_index.s5", np.array([-1, 3])), "state_index.s5 points outside its 4 elements"),
    (_array("lnes.values", np.zeros((2, 3), np.float32)), "array lnes.values is float32 [2, 3], expected float values"),
    (_array("lnes.values", np.zeros(3, np.int32)), "array lnes.values is int32 [3], expected float values"),
])
def test_each_array_that_disagrees_with_the_manifest_is_one_line_naming_it(change, message) -> None:
    arrays = _arrays()
    change(arrays)
    with pytest.raises(DataError) as info:
        check_arrays(_manifest(), arrays, PATH)
    assert str(info.value) == f"{PATH}: {message}; {FIX}"


def test_a_snapshot_at_the_first_and_last_steps_and_no_snapshot_at_all_pass() -> None:
    check_arrays(_manifest(), _arrays(), PATH)  # steps 0 and 2 of 0..2
    none = _arrays()
    none["snapshot_steps"] = np.zeros(0, np.int64)
    for name, dims in (("s5", (4,)), ("scalar", ())):
        none[f"snapshot.{name}"] = np.zeros((0, *dims), np.float32)
    check_arrays(_manifest(), none, PATH)


def test_frame_masks_must_agree_with_their_counts_and_the_stored_values() -> None:
    """Each packed mask row marks as many values as lnes.nnz says (popcount, checked against
    numpy's unpackbits), its pad bits stay clear, and the counts add up to the values stored."""
    arrays = _arrays()
    marked = np.unpackbits(arrays["lnes.mask"], axis=1)[:, :math.prod(FRAME)].sum(axis=1)
    assert marked.tolist() == arrays["lnes.nnz"].tolist()
    miscounted = copy.deepcopy(arrays)
    miscounted["lnes.nnz"][1] += 1
    with pytest.raises(DataError) as info:
        check_arrays(_manifest(), miscounted, PATH)
    assert str(info.value) == (f"{PATH}: frame 1's mask marks {marked[1]} values, lnes.nnz says {marked[1] + 1}; "
                               f"{FIX}")
    padded = copy.deepcopy(arrays)
    padded["lnes.mask"][2, -1] |= 0b0001  # a pad bit: the 21st value of a 20-value frame
    padded["lnes.nnz"][2] += 1
    with pytest.raises(DataError, match="frame 2's mask marks"):
        check_arrays(_manifest(), padded, PATH)
    last = copy.deepcopy(arrays)
    last["lnes.mask"][2, -1] |= 0b10000  # the 20th value itself is no pad bit
    if last["lnes.mask"][2, -1] != arrays["lnes.mask"][2, -1]:
        last["lnes.nnz"][2] += 1
        last["lnes.values"] = np.zeros(int(last["lnes.nnz"].sum()), np.float32)
        check_arrays(_manifest(), last, PATH)
    short = copy.deepcopy(arrays)
    short["lnes.values"] = short["lnes.values"][:-1]
    with pytest.raises(DataError) as info:
        check_arrays(_manifest(), short, PATH)
    total = int(arrays["lnes.nnz"].sum())
    assert str(info.value) == f"{PATH}: lnes.nnz adds up to {total} values, {total - 1} are stored; {FIX}"


def test_a_frame_of_whole_bytes_has_no_pad_bits() -> None:
    """72 values: 9 mask bytes (ceil(72 / 8)), none of them padding."""
    manifest, arrays = _manifest(frame=[2, 6, 6]), _arrays(frame=[2, 6, 6])
    marked = np.ones((STEPS, 72), bool)
    arrays.update({"lnes.mask": np.packbits(marked, axis=1), "lnes.nnz": np.full(STEPS, 72, np.int32),
                   "lnes.values": np.ones(72 * STEPS, np.float32)})
    assert arrays["lnes.mask"].shape == (STEPS, 9)
    check_arrays(manifest, arrays, PATH)


def test_the_smallest_valid_numbers_pass() -> None:
    """One step of a one-value frame, a state of one element, a 0.5 ms window and an mpjpe
    scale under 1 mm are all valid."""
    manifest = {**_manifest(steps=1, frame=[1, 1, 1]), "mpjpe_scale_mm": 0.5}
    manifest["states"] = [{"name": "s5", "shape": [1, 1]}, {"name": "scalar", "shape": [1]}]
    arrays = _arrays(steps=1, frame=[1, 1, 1], snapshots=[0])
    arrays.update({"window_ms": np.array([0.5], np.float32), "snapshot.s5": np.zeros((1, 1), np.float32),
                   "state_index.s5": np.array([0]), "state_sample.s5": np.zeros((1, 1), np.float32)})
    check_manifest(manifest, PATH)
    check_arrays(manifest, arrays, PATH)


def test_snapshot_steps_are_checked_at_their_last_and_shown_eight_at_most() -> None:
    manifest = _manifest(steps=12)
    late = _arrays(steps=12, snapshots=[0, 5, 12])
    with pytest.raises(DataError) as info:
        check_arrays(manifest, late, PATH)
    assert str(info.value) == f"{PATH}: snapshot_steps [0, 5, 12] are not increasing steps of 0..11; {FIX}"
    many = _arrays(steps=12, snapshots=[0, 1, 2, 3, 4, 5, 6, 7, 9, 8])
    with pytest.raises(DataError) as info:
        check_arrays(manifest, many, PATH)
    assert str(info.value) == f"{PATH}: snapshot_steps [0, 1, 2, 3, 4, 5, 6, 7] are not increasing steps of 0..11; {FIX}"


# ---- tolerances.py ---------------------------------------------------------------------------------------
def test_the_profiles_are_the_documented_numbers() -> None:
    """docs/golden.md and the module doc: fp32 0.01 mm and 1e-4 of a state's magnitude; fp16 5%
    relative RMS, int8 and bf16 50%, growth at most 4x for all three compressed ones, judged
    above a floor of a tenth of the state bound."""
    profiles = tolerances.PROFILES
    assert profiles["fp32"] == tolerances.ToleranceProfile("fp32", "exact", pose_atol_mm=0.01, state_rtol=1e-4)
    assert profiles["fp16"] == tolerances.ToleranceProfile("fp16", "budget", state_rtol=0.05, max_growth=4.0,
                                                           growth_floor=0.005)
    assert profiles["int8"] == tolerances.ToleranceProfile("int8", "budget", state_rtol=0.5, max_growth=4.0,
                                                           growth_floor=0.05)
    assert profiles["bf16"] == tolerances.ToleranceProfile("bf16", "budget", state_rtol=0.5, max_growth=4.0,
                                                           growth_floor=0.05)
    assert tolerances.ToleranceProfile("x", "exact").state_rtol == 1e-4
    assert tolerances.ToleranceProfile("x", "exact").pose_atol_mm is None
    assert tolerances.ToleranceProfile("x", "exact").max_growth is None
    assert tolerances.ToleranceProfile("x", "budget").growth_floor is None  # a golden recorded before the floor
    with pytest.raises(dataclasses.FrozenInstanceError):
        profiles["fp32"].state_rtol = 1.0


def test_a_profile_round_trips_without_its_unset_numbers() -> None:
    assert tolerances.PROFILES["fp32"].to_dict() == {"name": "fp32", "kind": "exact", "pose_atol_mm": 0.01,
                                                     "state_rtol": 1e-4}
    for profile in tolerances.PROFILES.values():
        assert tolerances.ToleranceProfile.from_dict(profile.to_dict()) == profile
    assert tolerances.ToleranceProfile.from_dict({"name": "n", "kind": "budget", "newer_field": 1}) == \
        tolerances.ToleranceProfile("n", "budget")
    with pytest.raises(InputError, match=r"broken tolerance profile \{'kind': 'exact'\}: "):
        tolerances.ToleranceProfile.from_dict({"kind": "exact"})


@pytest.mark.parametrize("quantization, profile", [
    (None, "fp32"), ({}, "fp32"), ({"mode": "int8"}, "int8"), ({"mode": "int8-dynamic"}, "int8"),
    ({"mode": "fp16"}, "fp16"), ({"mode": "int8", "format": "tflite", "budget": {}}, "int8"),
])
def test_a_graphs_quantisation_mode_picks_its_profile(quantization, profile) -> None:
    assert tolerances.profile_for_quantization(quantization) == profile


@pytest.mark.parametrize("quantization, shown", [({"mode": "int4"}, "'int4'"), ({"format": "onnx"}, "''")])
def test_a_mode_without_a_profile_says_to_pass_one(quantization, shown) -> None:
    with pytest.raises(InputError) as info:
        tolerances.profile_for_quantization(quantization)
    assert str(info.value) == f"the graph's quantisation mode {shown} has no golden profile; pass --profile"
