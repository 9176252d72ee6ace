"""runtime/render_stream.py on hand-written folders and a recording video writer: the ground
truth and camera found beside an event file (both layouts, and each way they are refused),
what `StreamRender` hands the writer for every pose, and `render_clip`'s reading (it stops once
the clip is full). Drawing itself is tests/test_render*.py's; a real graph's clip is
test_render.py's."""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from e3dpsm.camera import ee3d_default
from e3dpsm.errors import DataError, InputError
from e3dpsm.runtime import render_stream
from e3dpsm.runtime.render import frame_label
from e3dpsm.runtime.render_stream import StreamRender, camera_beside, ground_truth_beside, render_clip
from e3dpsm.runtime.stream import PoseEstimate

WINDOW_US = 20_000


def gt_folder(folder: Path, t_us: Any, j3d_m: Any) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    np.savez(folder / "gt.npz", t_us=np.asarray(t_us), j3d_m=np.asarray(j3d_m))
    return folder / "rec.npz"


def test_the_synthetic_layouts_ground_truth_is_read_in_millimetres(tmp_path) -> None:
    j3d = np.random.default_rng(0).normal(0, 0.5, (3, 16, 3))
    track = ground_truth_beside(gt_folder(tmp_path / "seq", [1_000, 2_000, 4_000], j3d))
    assert track.t_us.dtype == np.int64 and track.t_us.tolist() == [1_000, 2_000, 4_000]
    assert track.joints_mm.dtype == np.float32
    np.testing.assert_allclose(track.joints_mm, j3d * 1000.0, rtol=1e-6)
    assert ground_truth_beside(tmp_path / "empty" / "rec.npz") is None
    with pytest.raises(AttributeError):  # frozen: a track shared by every frame of a clip does not change
        track.t_us = np.zeros(3, np.int64)


def test_the_ee3d_layouts_ground_truth_is_read_for_its_events_file_only(tmp_path) -> None:
    from test_readers import write_ee3d_folder

    _, j3d, _ = write_ee3d_folder(tmp_path / "seq", np.random.default_rng(3))
    track = ground_truth_beside(tmp_path / "seq" / "events.h5")
    kept = [0, 1, 3]  # frame 2 has no events (write_ee3d_folder)
    np.testing.assert_allclose(track.joints_mm, j3d[kept] * np.array([1, -1, -1]) * 1000.0, rtol=1e-5)
    assert track.t_us.dtype == np.int64 and np.all(np.diff(track.t_us) > 0) and len(track.t_us) == 3
    assert ground_truth_beside(tmp_path / "seq" / "other.h5") is None  # not the folder's events file
    # gt.npz, where both are present, wins.
    gt_folder(tmp_path / "seq", [5, 6], np.zeros((2, 16, 3)))
    assert ground_truth_beside(tmp_path / "seq" / "events.h5").t_us.tolist() == [5, 6]


@pytest.mark.parametrize("t_us, j3d, message", [
    ([1, 2, 2], np.zeros((3, 16, 3)), "needs increasing t_us"),
    ([3, 2, 1], np.zeros((3, 16, 3)), "needs increasing t_us"),
    ([[1, 2, 3]], np.zeros((1, 16, 3)), "needs increasing t_us"),
    ([1, 2, 3], np.zeros((2, 16, 3)), "needs increasing t_us"),
])
def test_ground_truth_that_does_not_follow_the_layout_is_refused(tmp_path, t_us, j3d, message) -> None:
    events = gt_folder(tmp_path / "seq", t_us, j3d)
    with pytest.raises(DataError, match=rf"^{tmp_path / 'seq'}: ground truth needs increasing t_us \[F\] and "
                                        r"j3d_m \[F, J, 3\]$"):
        ground_truth_beside(events)


def test_a_damaged_or_incomplete_gt_file_is_one_error_naming_it(tmp_path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "gt.npz").write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(DataError, match=rf"^{tmp_path / 'a' / 'gt.npz'}: cannot read ground truth \(truncated or "
                                        r"corrupted\?\): "):
        ground_truth_beside(tmp_path / "a" / "rec.npz")  # a zipfile.BadZipFile escaped as a traceback before
    (tmp_path / "b").mkdir()
    np.savez(tmp_path / "b" / "gt.npz", t_us=np.arange(3))
    with pytest.raises(DataError, match=rf"^{tmp_path / 'b' / 'gt.npz'}: missing arrays \['j3d_m'\]"):
        ground_truth_beside(tmp_path / "b" / "rec.npz")


def test_the_camera_beside_the_events_or_the_ee3d_calibration(tmp_path) -> None:
    assert camera_beside(tmp_path / "rec.npz") == ee3d_default()
    mine = replace(ee3d_default(), xc=300.5, width=320, height=240)
    (tmp_path / "camera.json").write_text(json.dumps(mine.to_json()))
    assert camera_beside(tmp_path / "rec.npz") == mine
    (tmp_path / "camera.json").write_text('{"pol": [1, 2]}')
    with pytest.raises(DataError, match=rf"^{tmp_path / 'camera.json'}: cannot read the camera calibration: "):
        camera_beside(tmp_path / "rec.npz")
    (tmp_path / "camera.json").write_text("{not json")
    with pytest.raises(DataError, match="cannot read the camera calibration"):
        camera_beside(tmp_path / "rec.npz")


# -- StreamRender and render_clip with a recording writer ----------------------------------------------
class Writer:
    """Stands for PoseVideoWriter: records how it was made and what it was handed."""

    made: list["Writer"] = []

    def __init__(self, path, camera, *, fps, scale, max_frames, force) -> None:
        self.args = {"path": path, "camera": camera, "fps": fps, "scale": scale, "max_frames": max_frames,
                     "force": force}
        self.frames: list[tuple] = []
        self.entered = self.exited = 0
        Writer.made.append(self)

    @property
    def poses_seen(self) -> int:
        return len(self.frames)

    def add(self, lnes, pose, gt, *, label) -> bool:
        self.frames.append((lnes, pose, gt, label))
        return self.args["max_frames"] is None or len(self.frames) < self.args["max_frames"]

    def __enter__(self):
        self.entered += 1
        return self

    def __exit__(self, *exc) -> None:
        self.exited += 1

    def summary(self) -> str:
        return f"{len(self.frames)} frames"


@pytest.fixture
def writer(monkeypatch):
    Writer.made = []
    monkeypatch.setattr(render_stream, "PoseVideoWriter", Writer)
    return Writer


def pose(t_us: int, value: float, lnes: bool = True) -> PoseEstimate:
    return PoseEstimate(t_us=t_us, t_start_us=t_us - WINDOW_US, events=3,
                        outputs={"pose": np.full((16, 3), value, np.float32)},
                        lnes=np.full((2, 4, 4), value, np.float32) if lnes else None)


def test_a_stream_render_hands_each_pose_its_frame_ground_truth_and_label(tmp_path, writer) -> None:
    events = gt_folder(tmp_path / "seq", [20_000, 60_000], np.ones((2, 16, 3)))
    camera = replace(ee3d_default(), width=8, height=6)
    (tmp_path / "seq" / "camera.json").write_text(json.dumps(camera.to_json()))
    with StreamRender(tmp_path / "out.gif", events, WINDOW_US, (6, 8), max_frames=5, scale=0.5, force=False) as render:
        video = writer.made[0]
        assert video.entered == 1 and video.args == {"path": tmp_path / "out.gif", "camera": camera, "fps": 50.0,
                                                     "scale": 0.5, "max_frames": 5, "force": False}
        assert render.add(pose(20_000, 1.0)) and render.add(pose(40_000, 2.0))
        with pytest.raises(InputError, match="^PoseEstimate carries no LNES frame; create the estimator with "
                                             "keep_frames=True$"):
            render.add(pose(60_000, 3.0, lnes=False))
    assert video.exited == 1
    (lnes0, pose0, gt0, label0), (_, _, gt1, label1) = video.frames
    assert lnes0[0, 0, 0] == 1.0 and pose0[0, 0] == 1.0
    np.testing.assert_array_equal(gt0, np.full((16, 3), 1000.0))  # the ground truth at 20 ms, in mm
    assert gt1 is None  # 40 ms is 20 ms from either ground truth pose: more than half a window
    assert (label0, label1) == (frame_label(0, 20_000, True), frame_label(1, 40_000, False))


def test_a_stream_render_refuses_a_camera_of_another_size(tmp_path, writer) -> None:
    with pytest.raises(DataError, match=rf"^{tmp_path / 'rec.npz'}: sensor 346 x 260 but the camera calibration is "
                                        r"640 x 480; put a matching camera\.json beside the events$"):
        StreamRender(tmp_path / "out.gif", tmp_path / "rec.npz", WINDOW_US, (260, 346))
    assert writer.made == []
    StreamRender(tmp_path / "out.gif", tmp_path / "rec.npz", WINDOW_US, (480, 640))
    assert writer.made[0].args["fps"] == 50.0 and writer.made[0].args["force"] is True  # the defaults
    assert writer.made[0].args["scale"] == 1.0 and writer.made[0].args["max_frames"] is None


class Estimator:
    """Stands for StreamingPoseEstimator: each push returns the next scripted poses."""

    made: list["Estimator"] = []

    def __init__(self, model, *, window_ms, sensor_hw, threads, keep_frames, pushes, finish) -> None:
        self.args = {"model": model, "window_ms": window_ms, "sensor_hw": sensor_hw, "threads": threads,
                     "keep_frames": keep_frames}
        self.window_us, self.pushes, self.finished, self.rest = WINDOW_US, [], 0, finish
        self.script = pushes
        Estimator.made.append(self)

    def push(self, x, y, t, p) -> list[PoseEstimate]:
        self.pushes.append(t.tolist())
        return self.script.pop(0) if self.script else []

    def finish(self) -> list[PoseEstimate]:
        self.finished += 1
        return self.rest


def clip(tmp_path: Path, monkeypatch, pushes: list, finish: list, **kwargs) -> tuple[str, Estimator, Writer]:
    import e3dpsm.runtime.stream as stream_module

    events = tmp_path / "rec.npz"
    n = 10
    np.savez(events, x=np.zeros(n, np.int16), y=np.zeros(n, np.int16), t=np.arange(n, dtype=np.int64) * 1000,
             p=np.ones(n, np.int8), sensor_hw=np.array([480, 640]))
    Estimator.made = []
    monkeypatch.setattr(stream_module, "StreamingPoseEstimator",
                        lambda model, **kw: Estimator(model, pushes=pushes, finish=finish, **kw))
    summary = render_clip("m.onnx", events, tmp_path / "clip.gif", **kwargs)
    return summary, Estimator.made[0], Writer.made[0]


def test_a_clip_reads_in_chunks_and_closes_the_stream_when_not_full(tmp_path, monkeypatch, writer) -> None:
    summary, estimator, video = clip(tmp_path, monkeypatch, [[pose(20_000, 1.0)], []], [pose(40_000, 2.0)],
                                     chunk_events=4, max_frames=10)
    assert estimator.args == {"model": "m.onnx", "window_ms": None, "sensor_hw": (480, 640), "threads": 1,
                              "keep_frames": True}
    assert estimator.pushes == [[0, 1000, 2000, 3000], [4000, 5000, 6000, 7000], [8000, 9000]]
    assert estimator.finished == 1 and summary == "2 frames" and video.entered == video.exited == 1
    assert video.args["scale"] == 0.5 and video.args["max_frames"] == 10 and video.args["fps"] == 50.0


def test_a_full_clip_stops_reading(tmp_path, monkeypatch, writer) -> None:
    """Three poses fill a clip of 2: the rest of the recording is not read, nor the end closed."""
    summary, estimator, video = clip(tmp_path, monkeypatch, [[pose(20_000, 1.0), pose(40_000, 2.0),
                                                              pose(60_000, 3.0)]], [pose(80_000, 4.0)],
                                     chunk_events=4, max_frames=2, window_ms=20.0, scale=1.0, threads=2)
    assert estimator.pushes == [[0, 1000, 2000, 3000]] and estimator.finished == 0
    assert len(video.frames) == 2 and summary == "2 frames"  # all() stops at the first pose the clip refuses
    assert estimator.args["window_ms"] == 20.0 and estimator.args["threads"] == 2 and video.args["scale"] == 1.0


def test_a_clip_takes_fifty_frames_at_half_scale_by_default(tmp_path, monkeypatch, writer) -> None:
    _, estimator, video = clip(tmp_path, monkeypatch, [], [])
    assert (video.args["max_frames"], video.args["scale"]) == (50, 0.5)
    assert estimator.pushes == [list(range(0, 10_000, 1000))]  # 100,000 events a chunk
