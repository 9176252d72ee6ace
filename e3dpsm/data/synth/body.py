"""Articulated 16-joint body: per-subject shape, joint-angle forward kinematics, capsules.

World frame: z up, floor at z = 0. Body-local frames: x forward, y to the body's left,
z up. All functions are vectorised over time (leading axis T).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from e3dpsm.joints import JOINT_NAMES, NUM_JOINTS, PARENTS

J = {name: i for i, name in enumerate(JOINT_NAMES)}

# Joint-angle vector layout (radians). Zero is standing upright, arms and legs hanging.
POSE_PARAMS: tuple[str, ...] = (
    "body_pitch", "body_roll",                    # whole body about the hips (lean, sway)
    "torso_pitch", "torso_roll", "torso_twist",   # chest relative to pelvis
    "head_pitch", "head_yaw", "head_roll",        # head relative to chest
    "r_sh_flex", "r_sh_abd", "r_elbow",           # shoulder flexion (forward), abduction
    "l_sh_flex", "l_sh_abd", "l_elbow",
    "r_hip_flex", "r_hip_abd", "r_knee", "r_ankle",
    "l_hip_flex", "l_hip_abd", "l_knee", "l_ankle",
)
P = {name: i for i, name in enumerate(POSE_PARAMS)}
NUM_PARAMS = len(POSE_PARAMS)

# Extra surface anchors after the 16 joints: pelvis centre and lower neck (torso capsule).
PELVIS, CHEST_TOP = NUM_JOINTS, NUM_JOINTS + 1

# Rendered primitives: (point a, point b, radius as a fraction of the subject's girth,
# albedo group). Head and face are not rendered: they move rigidly with the camera, so
# they would add no events, only a fixed occluder at the border of the view.
CAPSULES: tuple[tuple[int, int, float, str], ...] = (
    # Torso: a spine capsule and one per flank, so it is wider than deep.
    (CHEST_TOP, PELVIS, 0.10, "top"),
    (J["R_shoulder"], J["R_hip"], 0.085, "top"),
    (J["L_shoulder"], J["L_hip"], 0.085, "top"),
    (J["R_shoulder"], J["L_shoulder"], 0.055, "top"),
    (J["R_hip"], J["L_hip"], 0.095, "bottom"),
    (J["R_shoulder"], J["R_elbow"], 0.047, "top"),
    (J["R_elbow"], J["R_wrist"], 0.038, "skin"),
    (J["L_shoulder"], J["L_elbow"], 0.047, "top"),
    (J["L_elbow"], J["L_wrist"], 0.038, "skin"),
    (J["R_hip"], J["R_knee"], 0.07, "bottom"),
    (J["R_knee"], J["R_ankle"], 0.052, "bottom"),
    (J["R_ankle"], J["R_foot"], 0.042, "shoe"),
    (J["L_hip"], J["L_knee"], 0.07, "bottom"),
    (J["L_knee"], J["L_ankle"], 0.052, "bottom"),
    (J["L_ankle"], J["L_foot"], 0.042, "shoe"),
    (J["R_wrist"], J["R_wrist"], 0.048, "skin"),  # hands as spheres
    (J["L_wrist"], J["L_wrist"], 0.048, "skin"),
)
ALBEDO_GROUPS: tuple[str, ...] = ("top", "bottom", "skin", "shoe")


@dataclass(frozen=True)
class BodyShape:
    """Segment lengths (metres) of one subject, plus girth and clothing albedo."""

    spine: float        # pelvis centre -> neck
    neck_head: float    # neck -> head centre
    shoulder_width: float
    hip_width: float
    upper_arm: float
    forearm: float
    thigh: float
    shin: float
    foot: float
    girth: float        # multiplies the capsule radii
    albedo: tuple[float, ...]  # one per ALBEDO_GROUPS entry, in (0, 1]

    def radii(self) -> np.ndarray:
        return np.array([c[2] for c in CAPSULES]) * self.girth

    def capsule_albedo(self) -> np.ndarray:
        return np.array([self.albedo[ALBEDO_GROUPS.index(c[3])] for c in CAPSULES])


def sample_body(rng: np.random.Generator) -> BodyShape:
    """A subject 1.55-1.90 m tall with +-5% per-segment proportion changes."""
    height = rng.uniform(1.55, 1.90)
    # Segment fractions of body height for an average adult (anthropometric tables).
    fractions = np.array([0.29, 0.10, 0.22, 0.115, 0.17, 0.15, 0.25, 0.245, 0.085])
    lengths = height * fractions * rng.uniform(0.95, 1.05, size=fractions.size)
    return BodyShape(
        *[float(v) for v in lengths],
        girth=float(rng.uniform(0.85, 1.2)),
        albedo=tuple(float(a) for a in rng.uniform([0.25, 0.2, 0.45, 0.1], [0.95, 0.8, 0.8, 0.6])),
    )


def bone_lengths(j3d: np.ndarray) -> np.ndarray:
    """Length of the bone from each joint to its parent (0 for the root), [..., 16]."""
    return np.linalg.norm(j3d - j3d[..., list(PARENTS), :], axis=-1)


def _rot(axis: str, angle: np.ndarray) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    o, z = np.ones_like(angle), np.zeros_like(angle)
    rows = {
        "x": [[o, z, z], [z, c, -s], [z, s, c]],
        "y": [[c, z, s], [z, o, z], [-s, z, c]],
        "z": [[c, -s, z], [s, c, z], [z, z, o]],
    }[axis]
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _apply(rot: np.ndarray, vec: np.ndarray) -> np.ndarray:
    return np.einsum("tij,tj->ti", rot, np.broadcast_to(vec, rot.shape[:-1]))


def _limb(flex: np.ndarray, abd: np.ndarray, bend: np.ndarray, side: float, bend_sign: float):
    """Directions of a two-segment limb in its parent frame.

    The proximal segment hangs down at zero angles, swings forward with `flex` and
    sideways (to `side`) with `abd`. The distal segment bends by `bend` in the plane
    spanned by the proximal segment and its flexion direction (forward/up for elbows,
    `bend_sign` = -1 turns it backward for knees). Returns (proximal, distal, distal
    forward normal) unit vectors [T, 3].
    """
    sf, cf, sa, ca = np.sin(flex), np.cos(flex), np.sin(abd), np.cos(abd)
    prox = np.stack([sf * ca, side * sa, -cf * ca], axis=-1)
    hint = bend_sign * np.stack([cf, np.zeros_like(cf), sf], axis=-1)
    hint = hint - np.sum(hint * prox, axis=-1, keepdims=True) * prox
    hint /= np.linalg.norm(hint, axis=-1, keepdims=True)
    sb, cb = np.sin(bend)[:, None], np.cos(bend)[:, None]
    dist = cb * prox + sb * hint
    normal = sb * prox - cb * hint  # perpendicular to the distal segment, in the bend plane
    return prox, dist, normal


def forward_kinematics(params: np.ndarray, root_xy: np.ndarray, yaw: np.ndarray,
                       shape: BodyShape) -> tuple[np.ndarray, np.ndarray]:
    """Joint positions with the pelvis at height 0: ([T, 18, 3] joints + anchors,
    head rotation [T, 3, 3] world-from-head). `ground_contact` lifts them onto the floor."""
    p = {name: params[:, i] for name, i in P.items()}
    t = params.shape[0]
    r_pelvis = _rot("z", yaw) @ _rot("y", p["body_pitch"]) @ _rot("x", p["body_roll"])
    r_torso = (r_pelvis @ _rot("z", p["torso_twist"]) @ _rot("y", p["torso_pitch"])
               @ _rot("x", p["torso_roll"]))
    r_head = r_torso @ _rot("z", p["head_yaw"]) @ _rot("y", p["head_pitch"]) @ _rot("x", p["head_roll"])

    pts = np.zeros((t, NUM_JOINTS + 2, 3))
    pelvis = np.concatenate([root_xy, np.zeros((t, 1))], axis=-1)
    neck = pelvis + _apply(r_torso, np.array([0.0, 0.0, shape.spine]))
    pts[:, PELVIS], pts[:, J["Neck"]] = pelvis, neck
    pts[:, CHEST_TOP] = pelvis + _apply(r_torso, np.array([0.0, 0.0, 0.8 * shape.spine]))
    pts[:, J["Head"]] = neck + _apply(r_head, np.array([0.03, 0.0, shape.neck_head]))
    for side, prefix in ((-1.0, "R"), (1.0, "L")):
        low = prefix.lower()
        shoulder = neck + _apply(r_torso, np.array([0.0, side * shape.shoulder_width / 2, -0.04]))
        upper, fore, _ = _limb(p[f"{low}_sh_flex"], p[f"{low}_sh_abd"], p[f"{low}_elbow"], side, 1.0)
        elbow = shoulder + _apply(r_torso, upper * shape.upper_arm)
        pts[:, J[f"{prefix}_shoulder"]], pts[:, J[f"{prefix}_elbow"]] = shoulder, elbow
        pts[:, J[f"{prefix}_wrist"]] = elbow + _apply(r_torso, fore * shape.forearm)

        hip = pelvis + _apply(r_pelvis, np.array([0.0, side * shape.hip_width / 2, 0.0]))
        thigh, shin, shin_normal = _limb(
            p[f"{low}_hip_flex"], p[f"{low}_hip_abd"], p[f"{low}_knee"], side, -1.0)
        knee = hip + _apply(r_pelvis, thigh * shape.thigh)
        ankle = knee + _apply(r_pelvis, shin * shape.shin)
        # ankle = 0: foot at right angles to the shin; positive points the toes down.
        ank = p[f"{low}_ankle"][:, None]
        foot_dir = np.cos(ank) * shin_normal + np.sin(ank) * shin
        pts[:, J[f"{prefix}_hip"]], pts[:, J[f"{prefix}_knee"]] = hip, knee
        pts[:, J[f"{prefix}_ankle"]] = ankle
        pts[:, J[f"{prefix}_foot"]] = ankle + _apply(r_pelvis, foot_dir * shape.foot)
    return pts, r_head


def ground_contact(points: np.ndarray, shape: BodyShape, lift: np.ndarray) -> np.ndarray:
    """Height offset [T] that puts the lowest rendered surface on the floor, plus `lift`
    (the flight height of jumps)."""
    radii = shape.radii()
    lowest = np.full(points.shape[0], np.inf)
    for (a, b, _, _), r in zip(CAPSULES, radii):
        lowest = np.minimum(lowest, np.minimum(points[:, a, 2], points[:, b, 2]) - r)
    return -lowest + lift
