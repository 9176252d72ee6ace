"""Rendering the streaming runtime's poses: the camera and ground truth found beside an event
file, `PoseEstimate`s drawn as they come (`e3dpsm run --render`), and `render_clip` for reports.

Ground truth is matched to each window END (`PoseEstimate.t_us`, where the model's pose
refers): the nearest ground-truth pose within half a window, else none (that frame shows
the prediction only). Torch-free, like the rest of the runtime.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from e3dpsm.camera import OcamCamera, ee3d_default
from e3dpsm.errors import DataError, InputError
from e3dpsm.runtime.render import PoseVideoWriter, RenderSummary, frame_label

if TYPE_CHECKING:  # pragma: no cover
    from e3dpsm.runtime.stream import PoseEstimate


# ---- ground truth and camera beside an event file ------------------------------------------------
@dataclass(frozen=True)
class GroundTruthTrack:
    """Ground-truth joints (mm, camera frame) at increasing times; `at` matches a window end."""

    t_us: np.ndarray  # int64 [F]
    joints_mm: np.ndarray  # float32 [F, J, 3]

    def at(self, t_us: int, window_us: int) -> np.ndarray | None:
        """The pose nearest to `t_us` if within half a window of it (ties: the earlier), else None."""
        i = int(np.searchsorted(self.t_us, t_us))
        best = min((j for j in (i - 1, i) if 0 <= j < self.t_us.size),
                   key=lambda j: abs(int(self.t_us[j]) - t_us), default=None)
        if best is None or 2 * abs(int(self.t_us[best]) - t_us) > window_us:
            return None
        return self.joints_mm[best]


def ground_truth_beside(events_path: str | os.PathLike) -> GroundTruthTrack | None:
    """Ground truth of the sequence folder holding `events_path`: the synthetic layout's
    gt.npz, or the EE3D pickle when the file is that folder's events.h5; None without either."""
    from e3dpsm.data.layout import EE3D_GT_FILE, EVENTS_FILE, GT_FILE

    events = Path(events_path)
    folder = events.parent
    if (folder / GT_FILE).is_file():
        from e3dpsm.data.formats.npz import load_arrays

        gt = load_arrays(folder / GT_FILE, ("t_us", "j3d_m"), what="ground truth")  # bounded, as every .npz read
        t_us, j3d_m = np.asarray(gt["t_us"], np.int64), np.asarray(gt["j3d_m"], np.float64)
    elif (folder / EE3D_GT_FILE).is_file() and events.name == EVENTS_FILE:
        from e3dpsm.data.ee3d import read_ee3d_sequence

        seq = read_ee3d_sequence(folder)
        t_us, j3d_m = seq.t_us.astype(np.int64), seq.j3d_m.astype(np.float64)
    else:
        return None
    if t_us.ndim != 1 or j3d_m.shape[:1] != t_us.shape or np.any(np.diff(t_us) <= 0):
        raise DataError(f"{folder}: ground truth needs increasing t_us [F] and j3d_m [F, J, 3]")
    return GroundTruthTrack(t_us, (j3d_m * 1000.0).astype(np.float32))


def camera_beside(events_path: str | os.PathLike) -> OcamCamera:
    """camera.json of the sequence folder (synthetic layout), else the EE3D calibration."""
    from e3dpsm.data.layout import CAMERA_FILE

    path = Path(events_path).parent / CAMERA_FILE
    if not path.is_file():
        return ee3d_default()
    try:
        return OcamCamera.from_json(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise DataError(f"{path}: cannot read the camera calibration: {exc}") from exc


# ---- the streaming runtime's poses -------------------------------------------------------------
class StreamRender:
    """Renders `PoseEstimate`s (made with `keep_frames=True`) of one event file as they come,
    with the camera and ground truth found beside that file."""

    def __init__(self, path: str | os.PathLike, events_path: str | os.PathLike, window_us: int,
                 sensor_hw: tuple[int, int], *, max_frames: int | None = None, scale: float = 1.0,
                 force: bool = True) -> None:
        self.camera = camera_beside(events_path)
        if (self.camera.height, self.camera.width) != tuple(sensor_hw):
            raise DataError(
                f"{events_path}: sensor {sensor_hw[1]} x {sensor_hw[0]} but the camera calibration is "
                f"{self.camera.width} x {self.camera.height}; put a matching camera.json beside the events"
            )
        self.ground_truth = ground_truth_beside(events_path)
        self.window_us = int(window_us)
        self.video = PoseVideoWriter(path, self.camera, fps=1e6 / self.window_us, scale=scale,
                                     max_frames=max_frames, force=force)

    def __enter__(self) -> "StreamRender":
        self.video.__enter__()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.video.__exit__(*exc)

    def add(self, estimate: PoseEstimate) -> bool:
        if estimate.lnes is None:
            raise InputError("PoseEstimate carries no LNES frame; create the estimator with keep_frames=True")
        gt = None if self.ground_truth is None else self.ground_truth.at(estimate.t_us, self.window_us)
        index = self.video.poses_seen
        return self.video.add(estimate.lnes, estimate.pose, gt, label=frame_label(index, estimate.t_us, gt is not None))


def render_clip(
    model: str | os.PathLike, events: str | os.PathLike, out_path: str | os.PathLike, *,
    max_frames: int = 50, window_ms: float | None = None, scale: float = 0.5, threads: int | None = 1,
    chunk_events: int = 100_000,
) -> RenderSummary:
    """A short clip of the first `max_frames` poses of `model` over `events` (ground truth
    drawn when found beside the events): for reports. Stops reading once the clip is full."""
    from e3dpsm.data.readers import read_events
    from e3dpsm.runtime.stream import StreamingPoseEstimator

    stream = read_events(events)
    estimator = StreamingPoseEstimator(model, window_ms=window_ms, sensor_hw=stream.sensor_hw,
                                       threads=threads, keep_frames=True)
    with StreamRender(out_path, events, estimator.window_us, stream.sensor_hw, max_frames=max_frames,
                      scale=scale) as render:
        for lo in range(0, len(stream), chunk_events):
            sl = slice(lo, lo + chunk_events)
            estimates = estimator.push(stream.x[sl], stream.y[sl], stream.t_us[sl], stream.p[sl])
            if not all(render.add(e) for e in estimates):
                break
        else:
            for estimate in estimator.finish():
                render.add(estimate)
    return render.video.summary()
