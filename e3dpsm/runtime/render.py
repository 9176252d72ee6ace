"""Poses you can watch: LNES frames with the predicted (and ground-truth) skeleton drawn on top.

Torch-free (numpy, Pillow; imageio + imageio-ffmpeg only for .mp4), so `e3dpsm run --render`
works on the same device as the runtime.

Picture of one window, at sensor resolution times `scale`:
- the LNES frame on the sensor grid (each sensor pixel shows the frame pixel its events went
  to): positive events (channel 1) red, negative (channel 0) blue, brighter = later in the
  window; both at a pixel mix;
- the predicted skeleton in gold and, where known, the ground truth in green, both projected
  through the fisheye camera (`OcamCamera.project`; joints outside its field of view are
  left out, with their bones);
- a label: window end time and frame number (it also keeps every GIF frame distinct, since
  Pillow merges identical consecutive frames and the frame count must equal the pose count).

The streaming side (ground truth and camera beside an event file, `PoseEstimate`s as they come,
`render_clip` for reports) is in `e3dpsm.runtime.render_stream`.

Every frame is a palette image with one fixed palette, so GIF colours are exact (no
per-frame quantisation) and the skeleton colours can be checked pixel by pixel.
Files are written under a temporary name and renamed when complete; a failure leaves nothing.
"""
from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Sequence

import numpy as np

from e3dpsm.camera import OcamCamera
from e3dpsm.errors import ConfigError, DataError, InputError, OutputExistsError
from e3dpsm.joints import PARENTS

if TYPE_CHECKING:  # pragma: no cover
    from PIL import Image

RENDER_SUFFIXES = (".gif", ".mp4")
MP4_HINT = "pip install imageio imageio-ffmpeg"

# Fixed palette: LEVELS x LEVELS event colours (positive level, negative level), then overlays.
LEVELS = 15
POSITIVE_RGB = np.array([255, 70, 40], dtype=np.float64)
NEGATIVE_RGB = np.array([40, 110, 255], dtype=np.float64)
PREDICTED_RGB = (255, 215, 0)
GROUND_TRUTH_RGB = (0, 230, 118)
TEXT_RGB = (255, 255, 255)
PREDICTED_INDEX = LEVELS * LEVELS
GROUND_TRUTH_INDEX = PREDICTED_INDEX + 1
TEXT_INDEX = PREDICTED_INDEX + 2


def _palette() -> list[int]:
    # Level 0 is "no event"; levels 1..LEVELS-1 span brightness 0.3..1, so even the earliest
    # event of a window stays visible.
    brightness = np.concatenate([[0.0], np.linspace(0.3, 1.0, LEVELS - 1)])
    pos, neg = np.meshgrid(brightness, brightness, indexing="ij")
    events = pos[..., None] * POSITIVE_RGB + neg[..., None] * NEGATIVE_RGB
    colours = np.clip(np.rint(events.reshape(-1, 3)), 0, 255).astype(int).tolist()
    colours += [list(PREDICTED_RGB), list(GROUND_TRUTH_RGB), list(TEXT_RGB)]
    colours += [[0, 0, 0]] * (256 - len(colours))
    return [c for rgb in colours for c in rgb]


PALETTE = _palette()


@dataclass(frozen=True)
class RenderSummary:
    path: Path
    frames: int  # frames in the file (== poses rendered)
    frames_with_ground_truth: int
    poses_seen: int  # poses offered; more than `frames` when max_frames cut the clip


# ---- drawing --------------------------------------------------------------------------------
def canvas_size(camera: OcamCamera, scale: float = 1.0) -> tuple[int, int]:
    """(width, height) of a rendered frame: the sensor times `scale`, rounded up to even
    (H.264 in yuv420p needs even sides)."""
    if not np.isfinite(scale) or scale <= 0:
        raise ConfigError(f"render scale must be positive, got {scale}")
    width, height = max(2, round(camera.width * scale)), max(2, round(camera.height * scale))
    return width + width % 2, height + height % 2


def project_to_canvas(points_mm: np.ndarray, camera: OcamCamera, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame joints [J, 3] (mm) -> canvas pixels [J, 2] (x = column, y = row) and a
    mask of the joints that can be drawn (finite, inside the lens' field of view)."""
    points = np.asarray(points_mm, dtype=np.float64)
    finite = np.isfinite(points).all(axis=-1)
    safe = np.where(finite[..., None], points, 1.0)
    uv = camera.project(safe)
    # Sensor pixel centres sit at integers; a canvas pixel covers 1/scale sensor pixels.
    sx, sy = round(camera.width * scale) / camera.width, round(camera.height * scale) / camera.height
    xy = np.stack([(uv[..., 0] + 0.5) * sx - 0.5, (uv[..., 1] + 0.5) * sy - 0.5], axis=-1)
    return xy, finite & camera.in_fov(safe)


def lnes_levels(lnes: np.ndarray) -> np.ndarray:
    """LNES [2, H, W] in [0, 1] -> palette indices [H, W] (uint8)."""
    lnes = np.asarray(lnes, dtype=np.float32)
    if lnes.ndim != 3 or lnes.shape[0] != 2:
        raise InputError(f"expected an LNES frame of shape [2, H, W], got {lnes.shape}")
    values = np.nan_to_num(np.clip(lnes, 0.0, 1.0))
    levels = np.where(values > 0, 1 + np.minimum(values * (LEVELS - 1), LEVELS - 2).astype(np.int64), 0)
    return (levels[1] * LEVELS + levels[0]).astype(np.uint8)


def _on_sensor_grid(levels: np.ndarray, camera: OcamCamera, scale: float) -> np.ndarray:
    """Frame-resolution image -> canvas, each canvas pixel taking the frame pixel that its
    sensor pixel's events went to (`events_to_lnes`: frame index = floor(sensor * frame / sensor
    size)), so events are drawn where they happened."""
    frame_h, frame_w = levels.shape

    def lookup(canvas: int, sensor: int, frame: int) -> np.ndarray:
        sensor_px = np.minimum(((np.arange(canvas) + 0.5) * sensor / canvas).astype(np.intp), sensor - 1)
        return sensor_px * frame // sensor

    rows = lookup(round(camera.height * scale), camera.height, frame_h)
    cols = lookup(round(camera.width * scale), camera.width, frame_w)
    return levels[rows[:, None], cols[None, :]]


def draw_frame(
    lnes: np.ndarray, camera: OcamCamera, pose_mm: np.ndarray | None = None, gt_mm: np.ndarray | None = None,
    *, label: str | None = None, scale: float = 1.0,
) -> Image.Image:
    """One frame as a palette ("P") image of `canvas_size(camera, scale)`; see the module doc."""
    from PIL import Image, ImageDraw

    width, height = canvas_size(camera, scale)
    events = Image.fromarray(_on_sensor_grid(lnes_levels(lnes), camera, scale), mode="P")
    image = Image.new("P", (width, height), 0)
    image.putpalette(PALETTE)
    image.paste(events, (0, 0))
    draw = ImageDraw.Draw(image)
    radius, line = max(2, round(3 * scale)), max(1, round(2 * scale))
    for joints, colour in ((gt_mm, GROUND_TRUTH_INDEX), (pose_mm, PREDICTED_INDEX)):  # prediction on top
        if joints is None:
            continue
        if np.shape(joints) != (len(PARENTS), 3):
            raise InputError(f"expected joints of shape ({len(PARENTS)}, 3) in mm, got {np.shape(joints)}")
        xy, ok = project_to_canvas(joints, camera, scale)
        xy = np.rint(xy)  # Pillow truncates float corners; rounding centres each disc on its pixel
        for child, parent in enumerate(PARENTS):
            if child != parent and ok[child] and ok[parent]:
                draw.line([tuple(xy[child]), tuple(xy[parent])], fill=colour, width=line)
        for (x, y), visible in zip(xy.tolist(), ok.tolist()):
            if visible:
                draw.ellipse([x - radius, y - radius, x + radius, y + radius], fill=colour)
    if label:  # on a black box: readable over a skeleton drawn through the corner
        draw.rectangle(draw.textbbox((4, 2), label), fill=0)
        draw.text((4, 2), label, fill=TEXT_INDEX)
    return image


# ---- writing --------------------------------------------------------------------------------
def check_render_path(path: str | os.PathLike, *, force: bool = False, max_frames: int | None = None) -> str:
    """Validate an output path (and frame cap) before any work: returns "gif" or "mp4", or raises.

    An .mp4 needs imageio with its ffmpeg plugin; without them this is the one clear error.
    """
    if max_frames is not None and max_frames <= 0:
        raise ConfigError(f"--render-max-frames must be positive, got {max_frames}")
    out = Path(path)
    suffix = out.suffix.lower()
    if suffix not in RENDER_SUFFIXES:
        raise ConfigError(f"--render {out}: expected a .mp4 or .gif path, got {suffix or 'no suffix'!r}")
    if out.is_dir():
        raise DataError(f"--render {out} is a folder; expected a .mp4 or .gif file path")
    if out.exists() and not force:
        raise OutputExistsError(f"{out} exists; pass --force to replace it")
    if suffix == ".mp4":
        try:
            import imageio.v2  # noqa: F401
            import imageio_ffmpeg

            imageio_ffmpeg.get_ffmpeg_exe()
        except (ImportError, RuntimeError) as exc:
            raise ConfigError(
                f"--render {out}: writing .mp4 needs imageio and imageio-ffmpeg ({exc}); "
                f"run `{MP4_HINT}`, or pass a .gif path"
            ) from exc
    return suffix[1:]


class PoseVideoWriter:
    """Frames appended one at a time; the file appears under its name only when the `with`
    block ends without an exception (mp4 streams to ffmpeg; a GIF keeps its palette frames,
    h x w bytes each, until the end, as Pillow writes a GIF in one go).

        with PoseVideoWriter("poses.gif", camera, fps=50) as video:
            video.add(lnes, pose_mm, gt_mm, label="t = 0.020 s")
    """

    def __init__(self, path: str | os.PathLike, camera: OcamCamera, *, fps: float, scale: float = 1.0,
                 max_frames: int | None = None, force: bool = True) -> None:
        if not np.isfinite(fps) or fps <= 0:
            raise ConfigError(f"render fps must be positive, got {fps}")
        self.path = Path(path)
        self.kind = check_render_path(self.path, force=force, max_frames=max_frames)
        self.camera, self.fps, self.scale, self.max_frames = camera, float(fps), float(scale), max_frames
        canvas_size(camera, scale)  # validates the scale before any frame
        self.frames = 0
        self.frames_with_ground_truth = 0
        self.poses_seen = 0
        self._gif_frames: list[Any] = []
        self._mp4: Any = None
        self._stack = contextlib.ExitStack()
        self._tmp: Path | None = None

    def __enter__(self) -> "PoseVideoWriter":
        from e3dpsm.utils.io import atomic_path

        self._tmp = self._stack.enter_context(atomic_path(self.path, suffix=f".{self.kind}"))
        if self.kind == "mp4":
            import imageio.v2 as imageio

            self._mp4 = imageio.get_writer(
                self._tmp, format="FFMPEG", mode="I", fps=self.fps, codec="libx264", pixelformat="yuv420p",
                macro_block_size=1, quality=7, ffmpeg_log_level="error", output_params=["-preset", "veryfast"],
            )
        return self

    def add(self, lnes: np.ndarray, pose_mm: np.ndarray | None, gt_mm: np.ndarray | None = None,
            *, label: str | None = None) -> bool:
        """Draw and append one frame; False (nothing drawn) once `max_frames` frames are in."""
        self.poses_seen += 1
        if self.max_frames is not None and self.frames >= self.max_frames:
            return False
        frame = draw_frame(lnes, self.camera, pose_mm, gt_mm, label=label, scale=self.scale)
        if self._mp4 is not None:
            self._mp4.append_data(np.asarray(frame.convert("RGB")))
        else:
            self._gif_frames.append(frame)
        self.frames += 1
        self.frames_with_ground_truth += int(gt_mm is not None)
        return True

    def summary(self) -> RenderSummary:
        return RenderSummary(self.path, self.frames, self.frames_with_ground_truth, self.poses_seen)

    def __exit__(self, exc_type, exc, tb) -> None:
        try:
            if self._mp4 is not None:
                self._mp4.close()  # before the rename (or the removal on failure)
            if exc_type is None:
                self._finish()
        except BaseException as error:
            self._gif_frames = []
            self._stack.__exit__(type(error), error, error.__traceback__)  # removes the temporary file
            raise
        self._gif_frames = []
        self._stack.__exit__(exc_type, exc, tb)  # renames on success, removes on failure

    def _finish(self) -> None:
        if self.frames == 0:
            raise InputError(f"no frames to render into {self.path}")
        if self.kind == "gif":
            first, *rest = self._gif_frames
            first.save(self._tmp, format="GIF", save_all=True, append_images=rest,
                       duration=gif_delay_ms(self.fps), loop=0, optimize=False)


def gif_delay_ms(fps: float) -> int:
    """A GIF frame's delay: GIF counts in hundredths of a second (Pillow truncates milliseconds
    to them) and browsers play a delay under 2 hundredths at 10 Hz, so the nearest whole
    hundredth, at least 2 (a 50 Hz ceiling)."""
    return 10 * max(2, round(100.0 / fps))


def render_poses(
    frames: Iterable[np.ndarray], poses_mm: Iterable[np.ndarray], camera: OcamCamera, out_path: str | os.PathLike,
    *, gt_mm: Iterable[np.ndarray | None] | None = None, t_us: Sequence[int] | None = None, fps: float = 50.0,
    scale: float = 1.0, max_frames: int | None = None, force: bool = True,
) -> RenderSummary:
    """Write a .gif/.mp4 with one frame per pose: `frames` LNES [2, H, W], `poses_mm` [J, 3]
    in the camera frame (mm), `gt_mm` the same or None per frame, `t_us` window ends (labels)."""
    poses = list(poses_mm)
    gts = [None] * len(poses) if gt_mm is None else list(gt_mm)
    times = [None] * len(poses) if t_us is None else list(t_us)
    if not len(gts) == len(times) == len(poses):
        raise InputError(f"{len(poses)} poses, {len(gts)} ground-truth entries, {len(times)} timestamps")
    with PoseVideoWriter(out_path, camera, fps=fps, scale=scale, max_frames=max_frames, force=force) as video:
        for k, (frame, pose, gt, t) in enumerate(zip(frames, poses, gts, times)):
            video.add(frame, pose, gt, label=frame_label(k, t, gt is not None))
        if video.poses_seen != len(poses):
            raise InputError(f"{video.poses_seen} LNES frames for {len(poses)} poses")
    return video.summary()


def frame_label(index: int, t_us: int | None, with_gt: bool) -> str:
    time = f"t = {t_us / 1e6:.3f} s  " if t_us is not None else ""
    return f"{time}#{index}  pred (gold)" + ("  gt (green)" if with_gt else "")
