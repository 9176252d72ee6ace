"""The 16-joint skeleton of the EE3D benchmarks (paper Sec. 4: J = 16; the order and parents
of the released code: docs/model.md#citations, Skeleton)."""
from __future__ import annotations

JOINT_NAMES: tuple[str, ...] = (
    "Head", "Neck",
    "R_shoulder", "R_elbow", "R_wrist",
    "L_shoulder", "L_elbow", "L_wrist",
    "R_hip", "R_knee", "R_ankle", "R_foot",
    "L_hip", "L_knee", "L_ankle", "L_foot",
)
NUM_JOINTS = len(JOINT_NAMES)

# Parent of each joint; the root (Head) is its own parent. Hips hang from the shoulders,
# as in the public EventEgo3D skeleton.
PARENTS: tuple[int, ...] = (0, 0, 1, 2, 3, 1, 5, 6, 2, 8, 9, 10, 5, 12, 13, 14)

# The 8 limb pairs used by E-3DPSM's bone-length and bone-orientation losses.
LIMB_PAIRS: tuple[tuple[int, int], ...] = (
    (2, 3), (3, 4), (5, 6), (6, 7), (8, 9), (9, 10), (12, 13), (13, 14),
)

ACTIONS: tuple[str, ...] = (
    "walk", "crouch", "pushup", "boxing", "kick", "dance", "interaction", "crawl", "sports", "jump",
)
