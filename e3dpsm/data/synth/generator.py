"""One synthetic egocentric sequence: motion -> renders -> events + ground truth.

Rendering happens at `render_hz` (a multiple of the pose rate, so pose frames coincide
with renders) on a grid of `render_scale` times the sensor resolution; each render pixel
stands for a block of sensor pixels and its events land on a uniformly drawn pixel of the
block. At the default 0.5 one render pixel is 2 x 2 sensor pixels, still finer than the
0.4-scaled 256 x 192 frames the model sees.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from e3dpsm.camera import OcamCamera, ee3d_default
from e3dpsm.data.sequence import EventStream, Sequence
from e3dpsm.data.synth.event_sim import EventParams, EventSimulator, noise_events
from e3dpsm.data.synth.motion import Trajectory, capsules_cam, make_trajectory
from e3dpsm.data.synth.render import Renderer, closest_on_segment, intersect_capsule
from e3dpsm.errors import ConfigError
from e3dpsm.joints import ACTIONS

OCCLUSION_MARGIN_M = 0.02  # a surface this close in front of a joint does not hide it


@dataclass(frozen=True)
class SynthConfig:
    seed: int = 0
    seconds: float = 10.0
    pose_hz: int = 50
    render_hz: int = 250
    render_scale: float = 0.5
    segment_s: float = 5.0
    events: EventParams = field(default_factory=EventParams)

    def validate(self) -> None:
        if not self.seconds > 0:
            raise ConfigError(f"seconds must be positive, got {self.seconds}")
        if self.pose_hz <= 0 or self.render_hz <= 0 or self.render_hz % self.pose_hz:
            raise ConfigError(f"render rate {self.render_hz} Hz must be a positive multiple of "
                              f"the pose rate {self.pose_hz} Hz")
        if self.render_scale not in (1.0, 0.5, 0.25):
            raise ConfigError(f"render scale must be 1, 0.5 or 0.25, got {self.render_scale}")
        if round(self.seconds * self.pose_hz) < 1:
            raise ConfigError(f"{self.seconds} s at {self.pose_hz} Hz gives no pose frame")

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


@dataclass
class SequenceExtras:
    """Per-event and per-frame facts kept for statistics and previews, not written."""

    is_body: np.ndarray   # [N] bool, event pixel showed the body before or after the change
    is_noise: np.ndarray  # [N] bool
    in_image: np.ndarray  # [F, 16] bool
    occluded: np.ndarray  # [F, 16] bool, in the image but behind another body part


def action_order(seed: int) -> np.ndarray:
    """The dataset-wide cycle of actions (same for every sequence of one seed)."""
    return np.random.default_rng([seed, 2**31 - 1]).permutation(len(ACTIONS))


def generate_sequence(config: SynthConfig, index: int, camera: OcamCamera | None = None,
                      progress: bool = False) -> tuple[Sequence, SequenceExtras]:
    """Sequence `index` of the data set `config.seed` describes: events in sensor pixels,
    ground truth at the pose rate (pose f timed at the end of its window, (f+1)/pose_hz).
    Deterministic: everything is drawn from one Generator seeded by (seed, index)."""
    config.validate()
    camera = camera or ee3d_default()
    rng = np.random.default_rng([config.seed, index])
    frames = round(config.seconds * config.pose_hz)
    sub = config.render_hz // config.pose_hz
    t_s = np.arange(frames * sub + 1) / config.render_hz
    traj = make_trajectory(t_s, index, frames / config.pose_hz, config.segment_s,
                           action_order(config.seed), rng)
    renderer = Renderer(camera, config.render_scale, traj.room, rng)
    pix, t_us, pol, body = _simulate(traj, renderer, config.events, rng, progress, f"seq {index}")

    # Render pixel -> a random sensor pixel of its block; then add background activity.
    b = renderer.block
    xy = renderer.pixel_xy[pix] * b + rng.integers(0, b, size=(pix.size, 2))
    n_xy, n_t, n_p = noise_events(rng, camera.width * camera.height, config.events.noise_hz_per_pixel,
                                  0.0, t_s[-1] * 1e6)
    x = np.concatenate([xy[:, 0], n_xy % camera.width])
    y = np.concatenate([xy[:, 1], n_xy // camera.width])
    t = np.floor(np.concatenate([t_us, n_t])).astype(np.int64)
    order = np.argsort(t, kind="stable")
    is_noise = np.concatenate([np.zeros(pix.size, bool), np.ones(n_t.size, bool)])[order]
    is_body = np.concatenate([body, np.zeros(n_t.size, bool)])[order]
    events = EventStream(x[order].astype(np.int32), y[order].astype(np.int32), t[order],
                         np.concatenate([pol, n_p])[order].astype(np.uint8), (camera.height, camera.width))

    pose_idx = np.arange(1, frames + 1) * sub
    j3d = traj.joints_cam()[pose_idx]
    in_image = camera.in_image(j3d)
    occluded = occlusion(traj, pose_idx, j3d) & in_image
    seq = Sequence(
        name=f"seq_{index:04d}", events=events,
        j3d_m=j3d.astype(np.float32), j2d_px=camera.project(j3d).astype(np.float32),
        visible=(in_image & ~occluded).astype(np.uint8),
        t_us=np.round(t_s[pose_idx] * 1e6).astype(np.int64),
        action=traj.action[pose_idx].astype(np.int16), action_names=ACTIONS,
        meta={"subject": dataclasses.asdict(traj.shape), "room": dataclasses.asdict(traj.room),
              "seed": config.seed, "index": index, "render_hz": config.render_hz,
              "render_scale": config.render_scale},
    )
    return seq, SequenceExtras(is_body, is_noise, in_image, occluded)


def _simulate(traj: Trajectory, renderer: Renderer, params: EventParams, rng: np.random.Generator,
              progress: bool, label: str):
    radii, albedo = traj.shape.radii(), traj.shape.capsule_albedo()

    def render(i: int):
        ends, forward = capsules_cam(traj, i)
        return renderer.render(traj.cam_pos[i], traj.cam_rot[i], ends, radii, albedo, forward)

    log_prev, body_prev = render(0)
    sim = EventSimulator(log_prev, params, rng)
    chunks: list[tuple[np.ndarray, ...]] = []
    steps = range(1, traj.t_s.size)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc=label, unit="render", leave=False)
    for i in steps:
        log_next, body_next = render(i)
        ev = sim.step(log_prev, log_next, traj.t_s[i - 1] * 1e6, traj.t_s[i] * 1e6)
        chunks.append((ev.pixel, ev.t_us, ev.p, body_prev[ev.pixel] | body_next[ev.pixel]))
        log_prev, body_prev = log_next, body_next
    return tuple(np.concatenate([c[k] for c in chunks]) for k in range(4))


def occlusion(traj: Trajectory, pose_idx: np.ndarray, j3d: np.ndarray) -> np.ndarray:
    """[F, 16] True where another body part lies between the camera and the joint.

    Capsules that contain the joint (its own limb) are ignored: their surface is always in
    front of a joint inside them.
    """
    radii = traj.shape.radii()
    out = np.zeros(j3d.shape[:2], dtype=bool)
    for f, i in enumerate(pose_idx):
        ends, _ = capsules_cam(traj, i)
        joints = j3d[f]
        dist = np.linalg.norm(joints, axis=-1)
        rays = joints / dist[:, None]
        for (a, b), r in zip(ends, radii):
            outside = _distance_to_segment(joints, a, b) > r
            t = intersect_capsule(rays, a, b, r)
            out[f] |= outside & (t < dist - OCCLUSION_MARGIN_M)
    return out


def _distance_to_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.linalg.norm(p - closest_on_segment(p, a, b)[1], axis=-1)

