"""Synthetic layout round trip, `prepare` and the prepared-cache reader."""
from __future__ import annotations

import json

import numpy as np
import pytest

from e3dpsm.cli import main
from e3dpsm.data.layout import (
    detect_layout, list_sequences, load_sequences, read_synthetic_sequence, write_dataset_index,
    write_synthetic_sequence,
)
from e3dpsm.data.prepare import prepare_dataset
from e3dpsm.data.prepared import PreparedData
from e3dpsm.data.sequence import EventStream, Sequence
from e3dpsm.errors import ConfigError, DataError, OutputExistsError
from e3dpsm.events import events_to_lnes
from e3dpsm.joints import ACTIONS

POSE_PERIOD_US = 20_000
FIRST_POSE_US = 50_000
SPLITS = {"train": ["walk_01", "box_02"], "val": ["kick_03"], "test": ["jump_04"]}


def make_sequence(name: str, seed: int, poses: int = 12, events: int = 3000) -> Sequence:
    rng = np.random.default_rng(seed)
    t_pose = FIRST_POSE_US + POSE_PERIOD_US * np.arange(poses, dtype=np.int64)
    t_events = np.sort(rng.integers(FIRST_POSE_US - 30_000, t_pose[-1] + 10_000, events))
    # a crowded corner so that pixels repeat within windows
    x = np.where(rng.random(events) < 0.3, rng.integers(0, 4, events), rng.integers(0, 640, events))
    return Sequence(
        name=name,
        events=EventStream(x=x.astype(np.int32), y=rng.integers(0, 480, events).astype(np.int32),
                           t_us=t_events.astype(np.int64), p=rng.integers(0, 2, events).astype(np.uint8)),
        j3d_m=rng.normal(0, 0.5, (poses, 16, 3)).astype(np.float32),
        j2d_px=rng.uniform(0, 480, (poses, 16, 2)).astype(np.float32),
        visible=rng.integers(0, 2, (poses, 16)).astype(np.uint8),
        t_us=t_pose,
        action=rng.integers(0, len(ACTIONS), poses).astype(np.int16),
        action_names=ACTIONS,
    )


@pytest.fixture(scope="session")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("synthetic")
    sequences = {}
    for seed, name in enumerate(n for names in SPLITS.values() for n in names):
        sequences[name] = make_sequence(name, seed)
        write_synthetic_sequence(root / name, sequences[name], {"model": "test-fisheye"})
    write_dataset_index(root, SPLITS, {"seed": 0})
    return root, sequences


@pytest.fixture(scope="session")
def prepared_20ms(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("prepared") / "p20"
    report = prepare_dataset(dataset[0], out, 20, progress=False)
    return out, report


def test_synthetic_sequence_round_trip(dataset):
    root, sequences = dataset
    written = sequences["kick_03"]
    back = read_synthetic_sequence(root / "kick_03")
    for name in ("j3d_m", "j2d_px", "visible", "t_us", "action"):
        np.testing.assert_array_equal(getattr(back, name), getattr(written, name))
    np.testing.assert_array_equal(back.events.t_us, written.events.t_us)
    assert back.action_names == ACTIONS and back.meta["camera"] == {"model": "test-fisheye"}
    assert detect_layout(root) == "synthetic"
    assert list_sequences(root) == [(n, s) for s, names in SPLITS.items() for n in names]
    assert [(seq.name, split) for seq, split in load_sequences(root, "train")] == [
        ("walk_01", "train"), ("box_02", "train")]


def test_prepare_writes_meta_and_shapes(prepared_20ms, dataset):
    out, report = prepared_20ms
    meta = json.loads((out / "meta.json").read_text())
    assert meta["format"] == "e3dpsm-prepared/1" and meta["source"] == "synthetic"
    assert (meta["window_ms"], meta["height"], meta["width"], meta["sensor_hw"]) == (20.0, 192, 256, [480, 640])
    assert meta["action_names"] == list(ACTIONS) and len(meta["joints"]) == 16
    assert "versions" in meta and "machine" in meta
    assert [(s["name"], s["split"], s["frames"]) for s in meta["sequences"]] == [
        (n, split, 12) for split, names in SPLITS.items() for n in names]
    data = PreparedData.open(out)
    seq = data.split("val")[0]
    assert seq.lnes.shape == (12, 2, 192, 256) and seq.lnes.dtype == np.float16
    assert not seq.lnes.flags.writeable
    assert seq.j3d_mm.shape == (12, 16, 3) and seq.visible.dtype == np.uint8
    assert report["frames"] == 48 and report["sequences"][0]["ground_truth"] == "copied"
    counts = report["events_per_window"]
    assert 0 < counts["median"] <= counts["p90"] <= counts["max"]


def test_prepared_lnes_and_ground_truth_match_the_sequence(prepared_20ms, dataset):
    out, _ = prepared_20ms
    source = dataset[1]["box_02"]
    seq = next(s for s in PreparedData.open(out).sequences if s.name == "box_02")
    np.testing.assert_array_equal(seq.t_us, source.t_us)  # poses every 20 ms: ends on the poses
    ev = source.events
    for f in (0, 5, 11):
        expected = events_to_lnes(ev.x, ev.y, ev.t_us, ev.p, int(source.t_us[f]) - 20_000, 20_000)
        np.testing.assert_array_equal(seq.lnes[f], expected.astype(np.float16))
    assert np.count_nonzero(seq.lnes[0]) > 0
    np.testing.assert_allclose(seq.j3d_mm, source.j3d_m * 1000.0, rtol=1e-6)
    np.testing.assert_allclose(seq.j2d_px, source.j2d_px * 0.4, rtol=1e-6)
    np.testing.assert_array_equal(seq.visible, source.visible)
    np.testing.assert_array_equal(seq.action, source.action)


def test_prepare_resamples_ground_truth_to_50ms_window_ends(dataset, tmp_path):
    root, sequences = dataset
    prepare_dataset(root, tmp_path / "p50", 50, height=96, width=128, progress=False)
    data = PreparedData.open(tmp_path / "p50")
    seq, source = data.sequences[0], sequences["walk_01"]
    ends = FIRST_POSE_US + 50_000 * np.arange(5)  # last end 250 ms <= last pose 270 ms
    np.testing.assert_array_equal(seq.t_us, ends)
    assert seq.lnes.shape == (5, 2, 96, 128)
    for j, c in ((0, 0), (7, 2), (15, 1)):
        expected = np.interp(ends, source.t_us, source.j3d_m[:, j, c].astype(np.float64)) * 1000
        np.testing.assert_allclose(seq.j3d_mm[:, j, c], expected, rtol=1e-5, atol=1e-3)
    # end 100 ms falls between poses at 90 and 110 ms: tie -> later pose; 150 ms lies on a pose
    np.testing.assert_array_equal(seq.visible[1], source.visible[3])
    np.testing.assert_array_equal(seq.action[2], source.action[5])
    np.testing.assert_allclose(seq.j2d_px[2], source.j2d_px[5] * 0.2, rtol=1e-6)
    with pytest.raises(DataError, match="prepared with 50 ms windows, but the model/graph expects 20 ms; "
                                        "re-run prepare with --window-ms 20"):
        data.check_compatible(window_ms=20)
    with pytest.raises(DataError, match="--height 192 --width 256"):
        data.check_compatible(height=192, width=256)
    data.check_compatible(window_ms=50, height=96, width=128)


def test_existing_output_is_refused_unless_forced(prepared_20ms, dataset):
    out, _ = prepared_20ms
    before = (out / "meta.json").read_text()
    with pytest.raises(OutputExistsError, match="--force"):
        prepare_dataset(dataset[0], out, 20, progress=False)
    assert (out / "meta.json").read_text() == before


def test_cli_reports_one_line_errors(prepared_20ms, dataset, capsys, tmp_path):
    out, _ = prepared_20ms
    assert main(["prepare", "--data", str(dataset[0]), "--out", str(out), "--no-progress"]) == 2
    assert "e3dpsm prepare: error: output folder" in capsys.readouterr().err
    assert main(["prepare", "--data", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_failure_leaves_no_partial_output(dataset, tmp_path):
    root = tmp_path / "data"
    for name, seq in dataset[1].items():
        write_synthetic_sequence(root / name, seq, {})
    write_dataset_index(root, SPLITS, {"seed": 0})
    events = root / "jump_04" / "events.h5"  # the last sequence: the others were already written
    events.write_bytes(events.read_bytes()[:2000])
    out = tmp_path / "out"
    with pytest.raises(DataError, match="jump_04"):
        prepare_dataset(root, out, 20, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]  # no out, no temporary folder


def test_workers_prepare_the_same_frames_and_poses(prepared_20ms, dataset, tmp_path):
    """--workers prepares one sequence per process; each file is what one process writes."""
    serial, serial_report = prepared_20ms
    out = tmp_path / "parallel"
    report = prepare_dataset(dataset[0], out, 20, progress=False, workers=3)
    assert report["workers"] == 3 and report["sequences"] == serial_report["sequences"]
    for entry in report["sequences"]:  # each entry describes its own sequence, whatever order the workers end in
        seq = dataset[1][entry["name"]]  # windows [t_pose[0] - T, t_pose[-1]) at T = 20 ms, counted here
        inside = (seq.events.t_us >= seq.t_us[0] - 20_000) & (seq.events.t_us < seq.t_us[-1])
        assert entry["events_in_windows"] == np.count_nonzero(inside), entry["name"]
        assert entry["frames"] == len(np.load(out / entry["name"] / "lnes.npy", mmap_mode="r")), entry["name"]
    names = sorted(p.name for p in serial.iterdir() if p.is_dir())
    assert names == sorted(p.name for p in out.iterdir() if p.is_dir()) and len(names) >= 3
    for name in names:
        for file in sorted((serial / name).iterdir()):
            assert (out / name / file.name).read_bytes() == file.read_bytes(), f"{name}/{file.name}"
    assert json.loads((out / "meta.json").read_text())["sequences"] == \
        json.loads((serial / "meta.json").read_text())["sequences"]


def test_a_worker_that_fails_leaves_no_partial_output(dataset, tmp_path):
    root = tmp_path / "data"
    for name, seq in dataset[1].items():
        write_synthetic_sequence(root / name, seq, {})
    write_dataset_index(root, SPLITS, {"seed": 0})
    events = root / "jump_04" / "events.h5"
    events.write_bytes(events.read_bytes()[:2000])
    with pytest.raises(DataError, match="jump_04"):
        prepare_dataset(root, tmp_path / "out", 20, progress=False, workers=2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data"]
    with pytest.raises(ConfigError, match="--workers must be at least 1"):
        prepare_dataset(root, tmp_path / "out", 20, progress=False, workers=0)


def test_opening_a_folder_that_is_not_prepared(tmp_path, prepared_20ms):
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match=r"is not a prepared folder \(is empty\): run `e3dpsm prepare"):
        PreparedData.open(tmp_path / "empty")
    with pytest.raises(DataError, match="does not exist"):
        PreparedData.open(tmp_path / "missing")
    broken = tmp_path / "broken"
    broken.mkdir()
    meta = json.loads((prepared_20ms[0] / "meta.json").read_text())
    (broken / "meta.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="lnes.npy is missing"):
        PreparedData.open(broken)
    (broken / "meta.json").write_text(json.dumps({**meta, "format": "something/2"}))
    with pytest.raises(DataError, match="format 'something/2'"):
        PreparedData.open(broken)


def test_prepare_reads_the_ee3d_layout_and_interpolates_its_pose_clock(tmp_path):
    try:  # tests/ is on sys.path as a rootdir, or is a package
        from test_readers import write_ee3d_folder
    except ImportError:
        from tests.test_readers import write_ee3d_folder

    root = tmp_path / "ee3d"
    root.mkdir()
    _, j3d, _ = write_ee3d_folder(root / "seq_a", np.random.default_rng(3))
    (root / "test.txt").write_text("seq_a\n")
    assert detect_layout(root) == "ee3d"
    report = prepare_dataset(root, tmp_path / "out", 20, progress=False)
    assert report["source"] == "ee3d" and report["sequences"][0]["ground_truth"] == "resampled"
    seq = PreparedData.open(tmp_path / "out").split("test")[0]
    # poses (kept frames 0, 1, 3) at 24501, 39501, 59501 us; 20 ms ends from the first pose
    np.testing.assert_array_equal(seq.t_us, [24_501, 44_501])
    rotated = j3d * np.array([1, -1, -1]) * 1000
    np.testing.assert_allclose(seq.j3d_mm[0], rotated[0], rtol=1e-5)
    np.testing.assert_allclose(seq.j3d_mm[1], 0.75 * rotated[1] + 0.25 * rotated[3], rtol=1e-5, atol=1e-3)
    assert (seq.action == -1).all()


def test_prepare_reads_camera_recordings_in_place_of_events_h5(dataset, prepared_20ms, tmp_path):
    """A sequence folder with events.raw (Prophesee EVT 2.0) instead of events.h5 prepares the
    same LNES frames and poses; two event files in one folder are refused."""
    import shutil

    from _camera_formats import encode_evt2

    root = tmp_path / "camera"
    shutil.copytree(dataset[0], root)
    for name, seq in dataset[1].items():
        (root / name / "events.h5").unlink()
        (root / name / "events.raw").write_bytes(encode_evt2(seq.events, ["evt 2.0", "geometry 640x480"]))
    prepare_dataset(root, tmp_path / "prep", 20, progress=False)
    want = {s.name: s for s in PreparedData.open(prepared_20ms[0]).sequences}
    got = {s.name: s for s in PreparedData.open(tmp_path / "prep").sequences}
    assert sorted(got) == sorted(dataset[1])
    for name, seq in got.items():
        np.testing.assert_array_equal(seq.lnes, want[name].lnes)
        np.testing.assert_array_equal(seq.j3d_mm, want[name].j3d_mm)
        assert seq.lnes.any()
    shutil.copy(dataset[0] / "walk_01" / "events.h5", root / "walk_01")
    with pytest.raises(DataError, match=r"walk_01: holds events.h5, events.raw; keep one event file"):
        read_synthetic_sequence(root / "walk_01")


def test_a_damaged_archive_in_a_sequence_or_a_prepared_folder_is_one_error(dataset, prepared_20ms, tmp_path):
    """A zip that is not one (a zipfile.BadZipFile escaped both readers before): one DataError
    naming the file. The bytes start as a zip does, so numpy hands them to zipfile."""
    import shutil

    from e3dpsm.data.layout import GT_FILE
    from e3dpsm.data.prepared import POSE_FILE

    root, _ = dataset
    sequence = tmp_path / "walk_01"
    shutil.copytree(root / "walk_01", sequence)
    (sequence / GT_FILE).write_bytes(b"PK\x03\x04" + b"\x00" * 60)
    with pytest.raises(DataError, match=rf"^{sequence / GT_FILE}: cannot read ground truth \(truncated or corrupted\?\)"):
        read_synthetic_sequence(sequence)
    prepared = tmp_path / "prepared"
    shutil.copytree(prepared_20ms[0], prepared)
    name = json.loads((prepared / "meta.json").read_text())["sequences"][0]["name"]
    (prepared / name / POSE_FILE).write_bytes(b"PK\x03\x04" + b"\x00" * 60)
    with pytest.raises(DataError, match=rf"^{prepared / name / POSE_FILE}: cannot read \(.*\); re-run `e3dpsm prepare`$"):
        PreparedData.open(prepared).split("train")
