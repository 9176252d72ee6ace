"""e3dpsm.runtime.render's pieces against what the docs promise and what a loop computes: the
fixed palette (gold prediction, green ground truth, white label; red positive and blue negative
events from 0.3 to full brightness), the canvas size, the LNES levels, the sensor-grid
lookup, the drawing order and the writer's bookkeeping and refusals."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageSequence

from e3dpsm.camera import ee3d_default
from e3dpsm.errors import ConfigError, DataError, InputError, OutputExistsError
from e3dpsm.joints import PARENTS
from e3dpsm.runtime import render
from e3dpsm.runtime.render import (PALETTE, PoseVideoWriter, canvas_size, check_render_path, draw_frame,
                                   frame_label, lnes_levels, project_to_canvas, render_poses)

GOLD, GREEN, WHITE = (255, 215, 0), (0, 230, 118), (255, 255, 255)  # docs/runtimes.md: gold and green
RED_FULL, BLUE_FULL = (255, 70, 40), (40, 110, 255)


def _rgb(index: int) -> tuple[int, ...]:
    return tuple(PALETTE[3 * index: 3 * index + 3])


def test_the_palette_holds_the_documented_colours() -> None:
    levels = render.LEVELS
    assert levels == 15 and len(PALETTE) == 256 * 3
    assert (render.PREDICTED_INDEX, render.GROUND_TRUTH_INDEX, render.TEXT_INDEX) == (225, 226, 227)
    assert (_rgb(225), _rgb(226), _rgb(227)) == (GOLD, GREEN, WHITE)
    assert _rgb(0) == (0, 0, 0)  # no event: black
    assert all(_rgb(i) == (0, 0, 0) for i in range(228, 256))
    for pos in range(levels):
        for neg in range(levels):
            bright = [0.0 if k == 0 else 0.3 + 0.7 * (k - 1) / (levels - 2) for k in (pos, neg)]
            mixed = np.array([bright[0] * r + bright[1] * b for r, b in zip(RED_FULL, BLUE_FULL)])
            assert _rgb(pos * levels + neg) == tuple(np.clip(np.rint(mixed), 0, 255).astype(int).tolist()), (pos, neg)
    assert _rgb((levels - 1) * levels) == RED_FULL and _rgb(levels - 1) == BLUE_FULL
    assert _rgb(levels) == tuple(round(0.3 * c) for c in RED_FULL)  # the earliest event stays visible


@pytest.mark.parametrize("scale, expected", [(1.0, (640, 480)), (0.5, (320, 240)), (0.1, (64, 48)),
                                             (0.0041, (4, 2)), (0.001, (2, 2)), (1.0 / 3.0, (214, 160)),
                                             (0.00625, (4, 4))])  # 3 rows: up to 4
def test_canvas_size_is_the_sensor_scaled_rounded_up_to_even(scale, expected) -> None:
    assert canvas_size(ee3d_default(), scale) == expected
    assert canvas_size(ee3d_default()) == (640, 480)  # the sensor's own size unless scaled


@pytest.mark.parametrize("scale", [0.0, -1.0, math.nan, math.inf])
def test_canvas_size_refuses_a_scale_that_is_not_positive(scale) -> None:
    with pytest.raises(ConfigError, match=f"^render scale must be positive, got {scale}$"):
        canvas_size(ee3d_default(), scale)


def test_projection_to_the_canvas_scales_pixel_centres_and_masks_what_cannot_be_drawn() -> None:
    camera = ee3d_default()
    points = np.array([[0.0, 0.0, 1000.0], [300.0, -200.0, 800.0], [np.nan, 0.0, 1.0], [0.0, 0.0, -1000.0],
                       [100.0, 50.0, np.inf]])
    uv = camera.project(points[:2])
    xy, ok = project_to_canvas(points, camera, 1.0)
    np.testing.assert_allclose(xy[:2], uv, atol=1e-9)
    assert ok.tolist() == [True, True, False, False, False]  # NaN, behind the lens, infinite
    assert np.array_equal(project_to_canvas(points, camera)[0], xy)  # scale 1 unless asked
    half, _ = project_to_canvas(points, camera, 0.5)
    np.testing.assert_allclose(half[:2], (uv + 0.5) * 0.5 - 0.5, atol=1e-9)
    odd, _ = project_to_canvas(points[:2], camera, 1.0 / 3.0)  # 213.33 columns round to 213, 160 rows
    np.testing.assert_allclose(odd[:, 0], (uv[:, 0] + 0.5) * 213 / 640 - 0.5, atol=1e-9)
    np.testing.assert_allclose(odd[:, 1], (uv[:, 1] + 0.5) * 160 / 480 - 0.5, atol=1e-9)


def test_lnes_levels_against_a_loop() -> None:
    rng = np.random.default_rng(3)
    lnes = rng.uniform(-0.2, 1.2, (2, 5, 7)).astype(np.float32)
    lnes[0, 0, 0], lnes[1, 0, 1], lnes[0, 1, 1] = np.nan, 1.0, 1e-9
    lnes[:, 4, :] = 0.0
    got = lnes_levels(lnes)
    assert got.dtype == np.uint8 and got.shape == (5, 7)
    for r in range(5):
        for c in range(7):
            levels = []
            for ch in (1, 0):
                v = float(lnes[ch, r, c])
                v = 0.0 if not math.isfinite(v) else min(max(v, 0.0), 1.0)
                levels.append(0 if v <= 0 else 1 + min(int(v * 14), 13))
            assert got[r, c] == levels[0] * 15 + levels[1], (r, c)
    assert got[0, 1] >= 14 * 15 and got[1, 1] % 15 == 1  # full positive: the top level; a trace of negative: level 1


@pytest.mark.parametrize("shape", [(3, 4, 4), (2, 4), (1, 2, 4, 4)])
def test_lnes_levels_refuses_other_shapes(shape) -> None:
    with pytest.raises(InputError, match=r"^expected an LNES frame of shape \[2, H, W\], got "):
        lnes_levels(np.zeros(shape, np.float32))


def test_each_canvas_pixel_shows_the_frame_pixel_its_sensor_pixel_fed() -> None:
    camera = ee3d_default()
    levels = np.arange(12 * 16, dtype=np.uint8).reshape(12, 16)
    for scale in (1.0, 0.25):
        got = render._on_sensor_grid(levels, camera, scale)
        height, width = round(480 * scale), round(640 * scale)
        assert got.shape == (height, width)
        for row in range(0, height, 7):
            for col in range(0, width, 11):
                sensor_row = min(int((row + 0.5) * 480 / height), 479)
                sensor_col = min(int((col + 0.5) * 640 / width), 639)
                assert got[row, col] == levels[sensor_row * 12 // 480, sensor_col * 16 // 640], (scale, row, col)
    full = np.random.default_rng(0).integers(0, 225, (480, 640)).astype(np.uint8)  # a frame at sensor resolution
    assert np.array_equal(render._on_sensor_grid(full, camera, 1.0), full)  # the last row and column included


def _one_bone_pose(camera, shift_x: float = 0.0) -> np.ndarray:
    """Every joint at one point 1 m ahead (one disc, no visible bone), shifted sideways."""
    return np.tile([shift_x, 0.0, 1000.0], (len(PARENTS), 1))


def test_prediction_is_drawn_over_ground_truth_and_the_label_over_both() -> None:
    camera = ee3d_default()
    blank = np.zeros((2, 12, 16), np.float32)
    at_centre = np.rint(camera.project(np.array([0.0, 0.0, 1000.0]))).astype(int)
    both = np.asarray(draw_frame(blank, camera, _one_bone_pose(camera), _one_bone_pose(camera)).convert("RGB"))
    assert tuple(both[at_centre[1], at_centre[0]]) == GOLD  # prediction on top
    gt_only = np.asarray(draw_frame(blank, camera, None, _one_bone_pose(camera)).convert("RGB"))
    assert tuple(gt_only[at_centre[1], at_centre[0]]) == GREEN
    disc = np.all(gt_only == GREEN, axis=-1)
    assert disc.sum() == np.all(both == GOLD, axis=-1).sum() > 20  # radius 3 at scale 1: the same disc
    rows, cols = np.nonzero(disc)
    assert rows.max() - rows.min() == cols.max() - cols.min() == 6
    labelled = np.asarray(draw_frame(blank, camera, label="t = 1.000 s").convert("RGB"))
    text = np.all(labelled == WHITE, axis=-1)
    assert text.any() and not text[40:].any()  # white text in the top-left corner only
    assert np.nonzero(text)[1].min() >= 4
    assert not np.asarray(draw_frame(blank, camera).convert("RGB")).any()  # nothing at all: black


def test_a_bone_joins_two_visible_joints_and_goes_with_either() -> None:
    camera = ee3d_default()
    blank = np.zeros((2, 12, 16), np.float32)
    child = next(c for c, p in enumerate(PARENTS) if c != p)
    pose = np.full((len(PARENTS), 3), np.nan)
    pose[child] = [-300.0, 0.0, 1000.0]
    pose[PARENTS[child]] = [300.0, 0.0, 1000.0]
    (x0, y0), (x1, y1) = np.rint(camera.project(pose[[child, PARENTS[child]]])).astype(int)
    gold = lambda p: np.all(np.asarray(draw_frame(blank, camera, p).convert("RGB")) == GOLD, axis=-1)  # noqa: E731
    mid = ((x0 + x1) // 2, (y0 + y1) // 2)
    drawn = gold(pose)
    assert drawn[y0, x0] and drawn[y1, x1] and drawn[mid[1], mid[0]]
    widths = drawn[:, mid[0]].sum()
    assert 2 <= widths <= 3  # a 2-pixel line
    alone = pose.copy()
    alone[PARENTS[child]] = np.nan
    drawn = gold(alone)
    assert drawn[y0, x0] and not drawn[mid[1], mid[0]]  # the disc stays, the bone goes
    scaled = np.all(np.asarray(draw_frame(blank, camera, pose, scale=2.0).convert("RGB")) == GOLD, axis=-1)
    assert 4 <= scaled[:, 2 * mid[0]].sum() <= 5  # line width and radius follow the scale


def test_joints_of_another_shape_are_refused() -> None:
    with pytest.raises(InputError, match=r"^expected joints of shape \(16, 3\) in mm, got \(15, 3\)$"):
        draw_frame(np.zeros((2, 12, 16), np.float32), ee3d_default(), np.zeros((15, 3)))
    with pytest.raises(InputError, match=r"got \(16, 2\)$"):
        draw_frame(np.zeros((2, 12, 16), np.float32), ee3d_default(), None, np.zeros((16, 2)))


def test_render_paths_are_checked_before_any_work(tmp_path) -> None:
    assert check_render_path(tmp_path / "a.gif") == "gif" and check_render_path(tmp_path / "A.GIF") == "gif"
    with pytest.raises(ConfigError, match=r"^--render-max-frames must be positive, got 0$"):
        check_render_path(tmp_path / "a.gif", max_frames=0)
    assert check_render_path(tmp_path / "a.gif", max_frames=1) == "gif"
    with pytest.raises(ConfigError, match=r"expected a \.mp4 or \.gif path, got '\.png'$"):
        check_render_path(tmp_path / "a.png")
    with pytest.raises(ConfigError, match=r"got 'no suffix'$"):
        check_render_path(tmp_path / "poses")
    (tmp_path / "dir.gif").mkdir()
    with pytest.raises(DataError, match=r"dir\.gif is a folder; expected a \.mp4 or \.gif file path$"):
        check_render_path(tmp_path / "dir.gif")
    (tmp_path / "old.gif").write_bytes(b"x")
    with pytest.raises(OutputExistsError, match=r"old\.gif exists; pass --force to replace it$"):
        check_render_path(tmp_path / "old.gif")
    assert check_render_path(tmp_path / "old.gif", force=True) == "gif"


def test_an_mp4_without_its_encoder_names_the_install(monkeypatch, tmp_path) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(ConfigError, match=r"run `pip install imageio imageio-ffmpeg`, or pass a \.gif path$"):
        check_render_path(tmp_path / "a.mp4")


def _gif(path: Path) -> tuple[list[np.ndarray], dict]:
    with Image.open(path) as image:
        info = dict(image.info)
        return [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(image)], info


def test_the_writer_counts_caps_and_times_its_frames(tmp_path) -> None:
    camera = ee3d_default()
    blank = np.zeros((2, 12, 16), np.float32)
    pose = _one_bone_pose(camera)
    with PoseVideoWriter(tmp_path / "capped.gif", camera, fps=40.0, scale=0.25, max_frames=2) as video:
        added = [video.add(blank, pose, pose if k % 2 else None, label=f"#{k}") for k in range(4)]
    assert added == [True, True, False, False]
    summary = video.summary()
    assert (summary.path, summary.frames, summary.frames_with_ground_truth, summary.poses_seen) == (
        tmp_path / "capped.gif", 2, 1, 4)
    frames, info = _gif(tmp_path / "capped.gif")
    assert len(frames) == 2 and frames[0].shape == (120, 160, 3)
    assert info["duration"] == 20 and info["loop"] == 0  # 25 ms to the nearest GIF hundredth, looping forever
    assert sorted(p.name for p in tmp_path.iterdir()) == ["capped.gif"]


@pytest.mark.parametrize("fps", [0.0, -5.0, math.nan])
def test_the_writer_refuses_a_frame_rate_that_is_not_positive(tmp_path, fps) -> None:
    with pytest.raises(ConfigError, match=f"^render fps must be positive, got {fps}$"):
        PoseVideoWriter(tmp_path / "a.gif", ee3d_default(), fps=fps)
    with pytest.raises(ConfigError, match="^render scale must be positive"):
        PoseVideoWriter(tmp_path / "a.gif", ee3d_default(), fps=10.0, scale=0.0)


def test_nothing_is_written_without_frames_or_after_a_failure(tmp_path) -> None:
    camera = ee3d_default()
    with pytest.raises(InputError, match=r"^no frames to render into .*empty\.gif$"):
        with PoseVideoWriter(tmp_path / "empty.gif", camera, fps=10.0):
            pass
    with pytest.raises(RuntimeError, match="boom"):
        with PoseVideoWriter(tmp_path / "failed.gif", camera, fps=10.0) as video:
            video.add(np.zeros((2, 12, 16), np.float32), None)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_render_poses_checks_its_counts_and_labels_each_frame(tmp_path) -> None:
    camera = ee3d_default()
    frames = np.zeros((3, 2, 12, 16), np.float32)
    poses = np.stack([_one_bone_pose(camera, 100.0 * k) for k in range(3)])
    with pytest.raises(InputError, match="^3 poses, 2 ground-truth entries, 3 timestamps$"):
        render_poses(frames, poses, camera, tmp_path / "a.gif", gt_mm=[None, None], t_us=[1, 2, 3])
    with pytest.raises(InputError, match="^2 LNES frames for 3 poses$"):
        render_poses(frames[:2], poses, camera, tmp_path / "a.gif")
    summary = render_poses(frames, poses, camera, tmp_path / "a.gif", gt_mm=[None, poses[1], None],
                           t_us=[20_000, 40_000, 60_000], fps=20.0, scale=0.5)
    assert (summary.frames, summary.frames_with_ground_truth, summary.poses_seen) == (3, 1, 3)
    got, info = _gif(tmp_path / "a.gif")
    assert len(got) == 3 and got[0].shape == (240, 320, 3) and info["duration"] == 50
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif"]


@pytest.mark.parametrize("fps, delay", [(50.0, 20), (40.0, 20), (30.0, 30), (25.0, 40), (4.0, 250), (100.0, 20),
                                        (1000.0, 20), (0.5, 2000)])
def test_gif_delays_are_whole_hundredths_browsers_play(fps, delay) -> None:
    assert render.gif_delay_ms(fps) == delay


def test_frame_labels() -> None:
    assert frame_label(0, None, False) == "#0  pred (gold)"
    assert frame_label(7, 1_234_567, True) == "t = 1.235 s  #7  pred (gold)  gt (green)"
    assert frame_label(3, 20_000, False) == "t = 0.020 s  #3  pred (gold)"


def test_a_canvas_wider_than_the_events_is_black_where_they_end() -> None:
    """At scale 1/3 the events cover 213 columns of a 214-column canvas (rounded up to even)."""
    camera = ee3d_default()
    image = np.asarray(draw_frame(np.ones((2, 12, 16), np.float32), camera, scale=1.0 / 3.0))
    assert image.shape == (160, 214)
    assert (image[:, 213] == 0).all() and (image[:, :213] == 14 * 15 + 14).all()


@pytest.mark.parametrize("scale, radius, line", [(0.25, 2, 1), (1.0, 3, 2), (2.0, 6, 4)])
def test_discs_and_lines_scale_with_a_floor(scale, radius, line) -> None:
    """A joint's disc spans 2 r + 1 pixels (r = 3 x scale, at least 2); a bone is 2 x scale
    pixels wide (at least 1), measured across a horizontal bone."""
    camera = ee3d_default()
    blank = np.zeros((2, 12, 16), np.float32)
    pose = np.full((len(PARENTS), 3), np.nan)
    pose[0] = [0.0, 0.0, 1000.0]
    one = np.asarray(draw_frame(blank, camera, pose, scale=scale)) == render.PREDICTED_INDEX
    rows, cols = np.nonzero(one)
    assert rows.max() - rows.min() == cols.max() - cols.min() == 2 * radius
    child = next(c for c, p in enumerate(PARENTS) if c != p)
    bone = np.full((len(PARENTS), 3), np.nan)
    bone[child], bone[PARENTS[child]] = [-400.0, 0.0, 1000.0], [400.0, 0.0, 1000.0]
    drawn = np.asarray(draw_frame(blank, camera, bone, scale=scale)) == render.PREDICTED_INDEX
    (x0, y0), (x1, y1) = project_to_canvas(bone[[child, PARENTS[child]]], camera, scale)[0]
    assert y0 == y1  # two points mirrored across the lens axis: a horizontal bone
    assert drawn[:, int(round((x0 + x1) / 2))].sum() == line


def test_the_label_is_pillows_text_at_4_2_on_a_black_box() -> None:
    from PIL import Image, ImageDraw

    camera = ee3d_default()
    label = "t = 1.000 s  #7  pred (gold)"
    events = np.asarray(draw_frame(np.ones((2, 12, 16), np.float32), camera, label=label, scale=0.5))
    reference = Image.new("P", events.shape[::-1], 0)
    draw = ImageDraw.Draw(reference)
    box = draw.textbbox((4, 2), label)
    draw.text((4, 2), label, fill=render.TEXT_INDEX)
    text = np.asarray(reference) == render.TEXT_INDEX
    assert text.any() and np.array_equal(events == render.TEXT_INDEX, text)
    inside = np.zeros_like(text)
    inside[box[1]:box[3] + 1, box[0]:box[2] + 1] = True  # Pillow's rectangle includes its far corner
    assert (events[inside & ~text] == 0).all()  # the box is black around the text
    assert (events[~inside] == 14 * 15 + 14).all()  # and no larger: the events show around it


def test_render_summaries_are_values() -> None:
    import dataclasses

    summary = render.RenderSummary(Path("a.gif"), 1, 0, 1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        summary.frames = 2


def test_the_writer_keeps_the_fixed_palette_in_the_file(tmp_path) -> None:
    camera = ee3d_default()
    rng = np.random.default_rng(1)
    with PoseVideoWriter(tmp_path / "a.gif", camera, fps=50.0, scale=0.25) as video:
        for k in range(3):
            video.add((rng.random((2, 12, 16)) < 0.3).astype(np.float32) * rng.random((2, 12, 16)).astype(np.float32),
                      _one_bone_pose(camera, 50.0 * k), label=f"#{k}")
    with Image.open(tmp_path / "a.gif") as image:
        assert image.n_frames == 3 and image.getpalette()[:len(PALETTE)] == PALETTE  # as drawn: not reordered


def test_defaults_draw_at_sensor_size_and_replace_what_is_there(tmp_path) -> None:
    camera = ee3d_default()
    frames = np.zeros((2, 2, 12, 16), np.float32)
    poses = np.stack([_one_bone_pose(camera)] * 2)
    (tmp_path / "a.gif").write_bytes(b"old")
    summary = render_poses(frames, poses, camera, tmp_path / "a.gif")
    got, info = _gif(tmp_path / "a.gif")
    assert summary.frames == 2 and got[0].shape == (480, 640, 3) and info["duration"] == 20  # 50 Hz
    with PoseVideoWriter(tmp_path / "a.gif", camera, fps=10.0) as video:
        video.add(frames[0], None)
    got, _ = _gif(tmp_path / "a.gif")
    assert len(got) == 1 and got[0].shape == (480, 640, 3)


def test_each_frame_is_labelled_with_its_time_and_whether_ground_truth_is_drawn(tmp_path, monkeypatch) -> None:
    labels: list[str] = []
    original = PoseVideoWriter.add

    def spy(self, lnes, pose_mm, gt_mm=None, *, label=None):
        labels.append(label)
        return original(self, lnes, pose_mm, gt_mm, label=label)

    monkeypatch.setattr(PoseVideoWriter, "add", spy)
    camera = ee3d_default()
    poses = np.stack([_one_bone_pose(camera)] * 2)
    render_poses(np.zeros((2, 2, 12, 16), np.float32), poses, camera, tmp_path / "a.gif", gt_mm=[poses[0], None],
                 t_us=[20_000, 40_000], scale=0.25)
    assert labels == ["t = 0.020 s  #0  pred (gold)  gt (green)", "t = 0.040 s  #1  pred (gold)"]


class _FakeMp4:
    def __init__(self, path, **kwargs) -> None:
        self.path, self.kwargs, self.frames = Path(path), kwargs, []

    def append_data(self, frame) -> None:
        self.frames.append(frame)

    def close(self) -> None:
        self.path.write_bytes(b"mp4")


def test_an_mp4_is_h264_in_yuv420p_at_the_window_rate_fed_rgb_frames(tmp_path, monkeypatch) -> None:
    pytest.importorskip("imageio_ffmpeg")
    import imageio.v2 as imageio

    writers: list[_FakeMp4] = []
    monkeypatch.setattr(imageio, "get_writer", lambda path, **kw: writers.append(_FakeMp4(path, **kw)) or writers[-1])
    camera = ee3d_default()
    render_poses(np.zeros((2, 2, 12, 16), np.float32), np.stack([_one_bone_pose(camera)] * 2), camera,
                 tmp_path / "a.mp4", scale=0.25)
    (writer,) = writers
    assert writer.kwargs == {"format": "FFMPEG", "mode": "I", "fps": 50.0, "codec": "libx264", "pixelformat": "yuv420p",
                             "macro_block_size": 1, "quality": 7, "ffmpeg_log_level": "error",
                             "output_params": ["-preset", "veryfast"]}
    assert [f.shape for f in writer.frames] == [(120, 160, 3)] * 2 and writer.frames[0].dtype == np.uint8
    assert (tmp_path / "a.mp4").read_bytes() == b"mp4"


def test_an_mp4_error_names_the_flag_and_the_libraries(monkeypatch, tmp_path) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(ConfigError, match=r"^--render \S+a\.mp4: writing \.mp4 needs imageio and imageio-ffmpeg \("):
        check_render_path(tmp_path / "a.mp4")
