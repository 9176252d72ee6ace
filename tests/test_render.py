"""`e3dpsm run --render` and e3dpsm.runtime.render: frame counts, where the skeleton lands, the
ground-truth time alignment, the missing-encoder error and atomic output."""
from __future__ import annotations

import csv
import importlib.util
import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageSequence

from e3dpsm.camera import ee3d_default
from e3dpsm.cli import main
from e3dpsm.data.layout import write_synthetic_sequence
from e3dpsm.data.sequence import EventStream, Sequence
from e3dpsm.runtime.render import GROUND_TRUTH_RGB, PREDICTED_RGB, canvas_size, draw_frame, render_poses
from e3dpsm.runtime.render_stream import GroundTruthTrack, render_clip

from _runtime_helpers import exported_tiny

WINDOW_US = 20_000
WINDOWS = 12
T0_US = 5_000_000
GT_OFFSET_US = 3_000  # ground truth 3 ms after each window end: matched (within half a window)
GT_GAP = (5, 6)  # ground truth k sits at the end of window k - 1 (+3 ms); none for k = 5, 6
HAS_MP4 = all(importlib.util.find_spec(m) is not None for m in ("imageio", "imageio_ffmpeg"))


def gt_pose_mm(k: int) -> np.ndarray:
    """A 4 x 4 grid of joints 1 m in front of the lens, swinging sideways from pose to pose."""
    xs, ys = np.meshgrid([-450.0, -150.0, 150.0, 450.0], [-300.0, 0.0, 300.0, 600.0])
    joints = np.stack([xs.ravel(), ys.ravel(), np.full(16, 1000.0)], axis=-1)
    joints[:, 0] += 150.0 * np.sin(1.3 * k)
    return joints


@pytest.fixture(scope="module")
def graph(tmp_path_factory) -> Path:
    return exported_tiny(str(tmp_path_factory.getbasetemp()))[1]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> dict:
    """A synthetic-layout sequence folder: random events over 12 windows, ground truth at
    window end + 3 ms except around windows 5 and 6."""
    rng = np.random.default_rng(7)
    n = WINDOWS * 300
    # First and last event fix the grid: exactly WINDOWS complete windows from T0_US.
    inner = rng.integers(0, WINDOWS * WINDOW_US, n - 2)
    t = np.sort(np.concatenate([[0], inner, [WINDOWS * WINDOW_US - 1]])) + T0_US
    events = EventStream(rng.integers(0, 640, n), rng.integers(0, 480, n), t.astype(np.int64),
                         rng.integers(0, 2, n).astype(np.uint8))
    ks = [k for k in range(1, WINDOWS + 2) if k not in GT_GAP]
    j3d_mm = np.stack([gt_pose_mm(k) for k in ks])
    camera = ee3d_default()
    seq = Sequence(
        name="seq", events=events, j3d_m=(j3d_mm / 1000).astype(np.float32),
        j2d_px=camera.project(j3d_mm).astype(np.float32), visible=np.ones((len(ks), 16), np.uint8),
        t_us=np.array([T0_US + k * WINDOW_US + GT_OFFSET_US for k in ks], np.int64),
        action=np.zeros(len(ks), np.int16), action_names=("walk",),
    )
    folder = write_synthetic_sequence(tmp_path_factory.mktemp("render") / "seq", seq, camera.to_json())
    return {"events": folder / "events.h5", "gt_t_us": seq.t_us, "gt_mm": j3d_mm}


def gif_frames(path: Path) -> list[np.ndarray]:
    with Image.open(path) as image:  # the iterator re-seeks one image: copy each frame out
        return [np.asarray(frame.convert("RGB")) for frame in ImageSequence.Iterator(image)]


def colour_mask(frame: np.ndarray, rgb: tuple[int, int, int]) -> np.ndarray:
    return np.all(frame == np.array(rgb, np.uint8), axis=-1)


def csv_times(path: Path) -> list[int]:
    with open(path, newline="") as fh:
        return [int(row["t_us"]) for row in csv.DictReader(fh)]


def expected_gt(t_us: int, gt_t_us: np.ndarray, gt_mm: np.ndarray) -> np.ndarray | None:
    """Brute-force reference: the nearest ground truth within half a window, else None."""
    gaps = [abs(int(g) - t_us) for g in gt_t_us]
    best = int(np.argmin(gaps))
    return gt_mm[best] if 2 * gaps[best] <= WINDOW_US else None


def test_cli_gif_has_one_frame_per_pose_and_aligned_ground_truth(graph, sequence, tmp_path, capsys):
    out, gif = tmp_path / "poses.csv", tmp_path / "poses.gif"
    code = main(["run", "--model", str(graph), "--events", str(sequence["events"]), "--out", str(out),
                 "--render", str(gif), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    times = csv_times(out)
    frames = gif_frames(gif)
    report = json.loads((tmp_path / "poses.report.json").read_text())
    assert len(frames) == len(times) == report["windows"] == WINDOWS
    assert frames[0].shape == (480, 640, 3)
    camera = ee3d_default()
    with_gt = 0
    for t_us, frame in zip(times, frames):
        gt = expected_gt(t_us, sequence["gt_t_us"], sequence["gt_mm"])
        is_gt = colour_mask(frame, GROUND_TRUTH_RGB)
        if gt is None:
            assert not is_gt.any(), f"window ending {t_us}: ground truth drawn where none is within half a window"
            continue
        with_gt += 1
        u, v = np.rint(camera.project(gt)).astype(int).T  # canvas = sensor grid at scale 1
        # The prediction is drawn on top and may hide a few joints; most must show.
        assert is_gt[v, u].sum() >= 12, f"window ending {t_us}: ground truth not at its projected joints"
    assert with_gt == WINDOWS - len(GT_GAP)
    printed = capsys.readouterr().out.splitlines()
    assert printed[-1] == f"render: {WINDOWS} frames, {with_gt} with ground truth -> {gif}"


@pytest.mark.parametrize("scale", [1.0, 0.5])
def test_joint_is_drawn_at_its_fisheye_projection(tmp_path, scale):
    """One joint per frame (the rest NaN, so not drawn): the gold disc must be centred on the
    camera projection of the 3D point, and nothing gold may sit at the x/y-swapped pixel."""
    camera = ee3d_default()
    points = np.array([[-400.0, -250.0, 900.0], [500.0, 100.0, 700.0], [120.0, 420.0, 800.0],
                       [-300.0, 350.0, 600.0], [0.0, 0.0, 1000.0]])
    poses = np.full((len(points), 16, 3), np.nan)
    poses[np.arange(len(points)), np.arange(len(points)) + 3] = points
    blank = np.zeros((len(points), 2, 192, 256), np.float32)
    summary = render_poses(blank, poses, camera, tmp_path / "one_joint.gif", scale=scale)
    frames = gif_frames(tmp_path / "one_joint.gif")
    assert summary.frames == len(frames) == len(points)
    assert frames[0].shape[:2] == canvas_size(camera, scale)[::-1]

    uv = camera.project(points)
    # Independent of `project` (invpol + Newton step): lifting the pixel with `pol` must give
    # the joint's own ray.
    rays = camera.backproject(uv)
    np.testing.assert_allclose(rays, points / np.linalg.norm(points, axis=1, keepdims=True), atol=1e-6)
    expected = (uv + 0.5) * scale - 0.5
    for (x, y), frame in zip(expected, frames):
        rows, cols = np.nonzero(colour_mask(frame, PREDICTED_RGB))
        assert rows.size > 0, "joint not drawn"
        np.testing.assert_allclose([cols.mean(), rows.mean()], [x, y], atol=0.5 + 1e-6)  # disc on the nearest pixel
        assert abs(x - y) > 10  # the swap below is a different place
        swapped_row, swapped_col = int(round(x)), int(round(y))
        if swapped_row < frame.shape[0]:
            assert not colour_mask(frame, PREDICTED_RGB)[swapped_row, swapped_col]


def test_identical_windows_still_give_one_frame_each(tmp_path):
    """Pillow merges identical consecutive GIF frames; the per-frame label must prevent that."""
    pose = np.tile(gt_pose_mm(0), (4, 1, 1))
    summary = render_poses(np.zeros((4, 2, 192, 256), np.float32), pose, ee3d_default(), tmp_path / "same.gif")
    assert summary.frames == len(gif_frames(tmp_path / "same.gif")) == 4


def test_lnes_polarity_colours_and_placement():
    """Positive events (channel 1) red, negative (channel 0) blue, brighter = later; a frame
    pixel is drawn on the sensor pixels whose events it holds: frame column 100 of 256 holds
    sensor columns 250-252 of 640 (floor(x * 256 / 640) = 100), frame row 50 of 192 sensor rows
    125-127 of 480."""
    lnes = np.zeros((2, 192, 256), np.float32)
    lnes[1, 50, 100] = 1.0
    lnes[0, 120, 30] = 1.0
    lnes[0, 120, 200] = 0.1
    image = np.asarray(draw_frame(lnes, ee3d_default()).convert("RGB")).astype(int)
    red = image[125:128, 250:253].reshape(-1, 3)
    assert np.all(red[:, 0] > 200) and np.all(red[:, 2] < 100)
    assert image[124:129, 249:254].any(axis=-1).sum() == 9  # exactly that 3 x 3 block
    blue, dim_blue = image[301, 76], image[301, 501]
    assert blue[2] > 200 and blue[0] < 100
    assert 0 < dim_blue[2] < blue[2]
    # Round trip through the LNES encoder itself: every event lands on its own sensor pixel.
    from e3dpsm.events import events_to_lnes

    rng = np.random.default_rng(5)
    x, y, p = rng.integers(0, 640, 40), rng.integers(0, 480, 40), np.arange(40) % 2
    encoded = events_to_lnes(x, y, np.full(40, 5), p.astype(np.uint8), 0, 10)
    drawn = np.asarray(draw_frame(encoded, ee3d_default()).convert("RGB")).astype(int)[y, x]
    assert np.all(np.where(p == 1, drawn[:, 0] > drawn[:, 2], drawn[:, 2] > drawn[:, 0]))


def test_ground_truth_matching_is_nearest_within_half_a_window():
    rng = np.random.default_rng(3)
    gt_t = np.cumsum(rng.integers(1, 30_000, 40)).astype(np.int64)
    track = GroundTruthTrack(gt_t, np.arange(40, dtype=np.float32)[:, None, None] * np.ones((1, 16, 3), np.float32))
    queries = np.concatenate([rng.integers(-20_000, gt_t[-1] + 20_000, 300),
                              gt_t + WINDOW_US // 2, gt_t - WINDOW_US // 2, gt_t + WINDOW_US // 2 + 1])
    for t in queries.tolist():
        gaps = np.abs(gt_t - t)
        want = int(np.argmin(gaps)) if 2 * gaps.min() <= WINDOW_US else None  # argmin: the earlier on a tie
        got = track.at(t, WINDOW_US)
        assert (None if got is None else int(got[0, 0])) == want, t


def test_mp4_without_encoder_is_one_clear_error_before_the_stream(monkeypatch, tmp_path, capsys):
    for module in ("imageio", "imageio.v2", "imageio_ffmpeg"):
        monkeypatch.setitem(sys.modules, module, None)  # import fails as if not installed
    # Neither the graph nor the events exist: the encoder check must come first.
    code = main(["run", "--model", str(tmp_path / "missing.onnx"), "--events", str(tmp_path / "missing.h5"),
                 "--out", str(tmp_path / "poses.csv"), "--render", str(tmp_path / "poses.mp4")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "pip install imageio imageio-ffmpeg" in err and ".gif" in err
    assert list(tmp_path.iterdir()) == []


def test_render_needs_a_single_event_file(tmp_path, capsys):
    code = main(["run", "--model", str(tmp_path / "m.onnx"), "--events", str(tmp_path / "a.h5"), str(tmp_path / "b.h5"),
                 "--out", str(tmp_path / "out"), "--render", str(tmp_path / "poses.gif")])
    assert code == 2 and "single --events file" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_failed_run_writes_no_render_and_cap_keeps_the_first_frames(graph, sequence, tmp_path, capsys):
    # A window longer than the stream: no pose, an error, and nothing left behind.
    code = main(["run", "--model", str(graph), "--events", str(sequence["events"]), "--out", str(tmp_path / "a.csv"),
                 "--render", str(tmp_path / "a.gif"), "--window-ms", "1000", "--no-progress"])
    assert code == 2 and "no complete" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []

    code = main(["run", "--model", str(graph), "--events", str(sequence["events"]), "--out", str(tmp_path / "b.csv"),
                 "--render", str(tmp_path / "b.gif"), "--render-max-frames", "4", "--no-progress"])
    assert code == 0
    assert len(gif_frames(tmp_path / "b.gif")) == 4 and len(csv_times(tmp_path / "b.csv")) == WINDOWS
    printed = capsys.readouterr().out.splitlines()
    with_gt = int(re.search(r", (\d+) with ground truth", printed[-1]).group(1))
    assert printed[-1] == (f"render: 4 frames (the first 4 of {WINDOWS} poses), {with_gt} with ground truth "
                           f"-> {tmp_path / 'b.gif'}") and 0 < with_gt <= 4


def test_render_clip_for_reports(graph, sequence, tmp_path):
    summary = render_clip(graph, sequence["events"], tmp_path / "clip.gif", max_frames=5, scale=0.5)
    frames = gif_frames(tmp_path / "clip.gif")
    assert summary.frames == len(frames) == 5
    assert frames[0].shape == (240, 320, 3)
    # Windows 0-4 end where ground truth 1-5 sits (+3 ms); 5 is in the gap.
    assert summary.frames_with_ground_truth == 4


@pytest.mark.skipif(not HAS_MP4, reason="needs imageio and imageio-ffmpeg")
def test_cli_mp4_has_one_frame_per_pose(graph, sequence, tmp_path, capsys):
    import imageio.v2 as imageio

    out, mp4 = tmp_path / "poses.csv", tmp_path / "poses.mp4"
    code = main(["run", "--model", str(graph), "--events", str(sequence["events"]), "--out", str(out),
                 "--render", str(mp4), "--no-progress"])
    assert code == 0, capsys.readouterr().err
    with imageio.get_reader(mp4, format="FFMPEG") as reader:
        shapes = [frame.shape for frame in reader]
    assert len(shapes) == len(csv_times(out)) == WINDOWS and shapes[0] == (480, 640, 3)
