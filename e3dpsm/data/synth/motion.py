"""A subject's full trajectory: action schedule, blended motion, root path, head camera.

The schedule cycles through a dataset-wide permutation of the ten actions, so that any
dataset with at least ten segments in total covers every class; consecutive segments are
cross-faded over `BLEND_S` seconds so poses (and therefore events) stay continuous.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from e3dpsm.data.synth.actions import Motion, make_action
from e3dpsm.data.synth.body import (
    CAPSULES, BodyShape, P, forward_kinematics, ground_contact, sample_body,
)
from e3dpsm.joints import ACTIONS, NUM_JOINTS

BLEND_S = 0.6


@dataclass(frozen=True)
class Room:
    half_x: float
    half_y: float
    height: float


@dataclass
class Trajectory:
    """Everything sampled on the render grid `t_s` (seconds)."""

    t_s: np.ndarray          # [T]
    points_world: np.ndarray  # [T, 18, 3]: 16 joints + surface anchors (body.PELVIS, CHEST_TOP)
    cam_pos: np.ndarray      # [T, 3] camera centre, world
    cam_rot: np.ndarray      # [T, 3, 3] world-from-camera (columns: camera x, y, z in world)
    body_forward: np.ndarray  # [T, 3] pelvis forward axis, world (texture reference)
    action: np.ndarray       # [T] int16 index into ACTIONS
    shape: BodyShape
    room: Room

    def to_camera(self, pts_world: np.ndarray) -> np.ndarray:
        """World points [T, K, 3] -> camera frame [T, K, 3]."""
        return np.einsum("tji,tkj->tki", self.cam_rot, pts_world - self.cam_pos[:, None, :])

    def joints_cam(self) -> np.ndarray:
        return self.to_camera(self.points_world[:, :NUM_JOINTS])


def schedule(seconds: float, seq_index: int, segment_s: float, order: np.ndarray,
             rng: np.random.Generator) -> list[tuple[int, float, float]]:
    """Segments (action index, start, end) covering [0, seconds]. Sequence i continues
    the dataset's action cycle where sequence i - 1 stopped."""
    n = max(1, int(round(seconds / segment_s)))
    weights = rng.uniform(0.7, 1.3, size=n)
    edges = np.concatenate([[0.0], np.cumsum(weights) / weights.sum() * seconds])
    first = seq_index * n
    return [(int(order[(first + k) % len(order)]), edges[k], edges[k + 1]) for k in range(n)]


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def blend_segments(t: np.ndarray, segments: list[tuple[int, float, float]], rng: np.random.Generator,
                   shape: BodyShape) -> tuple[Motion, np.ndarray]:
    """Cross-faded motion over all segments, and the per-sample action label. The fade is
    shortened for segments shorter than `BLEND_S` so the weights still sum to one."""
    blend = min(BLEND_S, min(end - start for _, start, end in segments))
    total = Motion(np.zeros((t.size, len(P))), np.zeros(t.size), np.zeros(t.size), np.zeros(t.size))
    label = np.zeros(t.size, dtype=np.int16)
    for k, (action, start, end) in enumerate(segments):
        fade_in = np.ones(t.size) if k == 0 else _smoothstep((t - start) / blend + 0.5)
        fade_out = np.ones(t.size) if k == len(segments) - 1 else 1 - _smoothstep((t - end) / blend + 0.5)
        weight = fade_in * fade_out
        active = weight > 0
        label[(t >= start) & (t < end)] = action
        style_rng = np.random.default_rng(rng.integers(2**63))
        if not active.any():  # a segment shorter than one sample
            continue
        fn = make_action(ACTIONS[action], style_rng, shape)
        m = fn(t[active] - start)
        w = weight[active]
        total.params[active] += w[:, None] * m.params
        for name in ("speed", "yaw_rate", "lift"):
            getattr(total, name)[active] += w * getattr(m, name)
    label[t >= segments[-1][2]] = segments[-1][0]
    return total, label


def _smooth_noise(t: np.ndarray, rng: np.random.Generator, amp: float, n: int = 3) -> np.ndarray:
    freqs, phases = rng.uniform(0.1, 0.7, n), rng.uniform(0, 2 * np.pi, n)
    amps = rng.uniform(0.5, 1.0, n) * amp / n
    return (amps * np.sin(2 * np.pi * freqs * t[:, None] + phases)).sum(1)


def integrate_root(t: np.ndarray, speed: np.ndarray, yaw_rate: np.ndarray, room: Room,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Planar path from speed and turn rate, steered back toward the room centre near walls."""
    dt = np.diff(t, prepend=t[0])
    pos = np.zeros((t.size, 2))
    yaw = np.zeros(t.size)
    x, y = rng.uniform(-0.3, 0.3) * room.half_x, rng.uniform(-0.3, 0.3) * room.half_y
    h = rng.uniform(-np.pi, np.pi)
    limit = np.array([room.half_x, room.half_y]) * 0.55
    for i in range(t.size):
        off = np.array([x, y]) / limit
        if np.hypot(*off) > 1.0:  # near a wall: turn toward the centre
            to_centre = np.arctan2(-y, -x)
            h += 2.0 * np.sin(to_centre - h) * dt[i]
        h += yaw_rate[i] * dt[i]
        x += speed[i] * np.cos(h) * dt[i]
        y += speed[i] * np.sin(h) * dt[i]
        pos[i], yaw[i] = (x, y), h
    return pos, yaw


def camera_mount(tilt: float, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Head-from-camera rotation for a camera tilted `tilt` below the head's forward axis,
    and its position in the head frame. Camera axes: x right, y down the image, z optical."""
    s, c = np.sin(tilt), np.cos(tilt)
    x_cam, z_cam = np.array([0.0, -1.0, 0.0]), np.array([c, 0.0, -s])
    return np.stack([x_cam, np.cross(z_cam, x_cam), z_cam], axis=1), offset


def make_trajectory(t: np.ndarray, seq_index: int, seconds: float, segment_s: float,
                    order: np.ndarray, rng: np.random.Generator) -> Trajectory:
    shape = sample_body(rng)
    room = Room(rng.uniform(3.0, 5.0), rng.uniform(3.0, 5.0), rng.uniform(2.6, 3.2))
    segments = schedule(seconds, seq_index, segment_s, order, rng)
    motion, label = blend_segments(t, segments, rng, shape)
    for name, amp in (("head_yaw", 0.2), ("head_pitch", 0.12), ("head_roll", 0.06)):
        motion.params[:, P[name]] += _smooth_noise(t, rng, amp)
    root_xy, yaw = integrate_root(t, motion.speed, motion.yaw_rate, room, rng)
    pts, r_head = forward_kinematics(motion.params, root_xy, yaw, shape)
    pts[..., 2] += ground_contact(pts, shape, motion.lift)[:, None]

    mount_rot, mount_pos = camera_mount(np.radians(rng.uniform(45, 60)),
                                        np.array([rng.uniform(0.14, 0.2), 0.0, rng.uniform(0.02, 0.06)]))
    cam_pos = pts[:, 0] + np.einsum("tij,j->ti", r_head, mount_pos)
    cam_rot = r_head @ mount_rot
    forward = np.stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)], axis=-1)
    return Trajectory(t, pts, cam_pos, cam_rot, forward, label, shape, room)


def capsules_cam(traj: Trajectory, i: int) -> tuple[np.ndarray, np.ndarray]:
    """Capsule end points [K, 2, 3] in the camera frame at sample i, and the body forward
    axis in the camera frame (texture reference)."""
    idx = np.array([[a, b] for a, b, _, _ in CAPSULES])
    rot, pos = traj.cam_rot[i], traj.cam_pos[i]
    ends = (traj.points_world[i][idx] - pos) @ rot
    return ends, traj.body_forward[i] @ rot
