"""Parametric generators for the ten EE3D action classes.

`make_action(name, rng, shape)` draws a style (tempo, amplitudes, handedness) and returns a
function of segment time t [n] -> `Motion` (joint angles plus root speed, turn rate and
jump lift). Angles follow `body.POSE_PARAMS`; the shapes are hand-tuned cycles, not
motion capture, meant to give each class its typical silhouette and event pattern.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from e3dpsm.data.synth.body import NUM_PARAMS, P, BodyShape


@dataclass
class Motion:
    params: np.ndarray    # [n, NUM_PARAMS]
    speed: np.ndarray     # [n] forward speed, m/s
    yaw_rate: np.ndarray  # [n] rad/s
    lift: np.ndarray      # [n] height above ground contact (jumps), m

    @staticmethod
    def rest(n: int) -> "Motion":
        params = np.zeros((n, NUM_PARAMS))
        for name, value in (("r_elbow", 0.25), ("l_elbow", 0.25), ("r_sh_abd", 0.12),
                            ("l_sh_abd", 0.12), ("r_knee", 0.05), ("l_knee", 0.05),
                            ("head_pitch", 0.3)):
            params[:, P[name]] = value
        return Motion(params, np.zeros(n), np.zeros(n), np.zeros(n))

    def set(self, **angles: np.ndarray | float) -> "Motion":
        for name, value in angles.items():
            self.params[:, P[name]] = value
        return self


ActionFn = Callable[[np.ndarray], Motion]


class _Pulses:
    """Smooth pulses in [0, 1] at random times (punches, kicks, reaches), drawn once so
    that evaluating a segment over any time range gives the same motion."""

    SPAN_S = 120.0  # longer than any segment

    def __init__(self, rng: np.random.Generator, rate: float, width: float):
        gaps = rng.uniform(0.5, 1.5, size=int(self.SPAN_S * rate) + 2) / rate
        self.centres, self.width = np.cumsum(gaps) - 0.5 / rate, width

    def __call__(self, t: np.ndarray) -> np.ndarray:
        lo, hi = np.searchsorted(self.centres, [t.min() - 5 * self.width, t.max() + 5 * self.width])
        c = self.centres[lo:hi]
        return np.clip(np.exp(-0.5 * ((t[:, None] - c[None, :]) / self.width) ** 2).sum(1), 0, 1)


def _walk(rng, shape):
    freq, amp, speed = rng.uniform(0.8, 1.1), rng.uniform(0.8, 1.2), rng.uniform(0.9, 1.5)
    turn = rng.uniform(-0.3, 0.3)

    def fn(t):
        ph = 2 * np.pi * freq * t
        m = Motion.rest(t.size)
        m.speed[:], m.yaw_rate[:] = speed * amp, turn
        for side, off in (("r", 0.0), ("l", np.pi)):
            s = np.sin(ph + off)
            m.set(**{f"{side}_hip_flex": 0.42 * amp * s,
                     f"{side}_knee": 0.15 + 0.55 * amp * np.clip(np.sin(ph + off - 1.9), 0, None),
                     f"{side}_ankle": 0.15 * np.cos(ph + off),
                     f"{side}_sh_flex": -0.35 * amp * s, f"{side}_elbow": 0.35 + 0.2 * (1 - s)})
        return m.set(torso_twist=0.08 * np.sin(ph), torso_pitch=0.06, body_roll=0.03 * np.sin(ph))
    return fn


def _crouch(rng, shape):
    period, depth = rng.uniform(2.2, 4.0), rng.uniform(0.6, 1.0)

    def fn(t):
        d = depth * 0.5 * (1 - np.cos(2 * np.pi * t / period))
        m = Motion.rest(t.size)
        for side in "rl":
            m.set(**{f"{side}_hip_flex": 1.7 * d, f"{side}_knee": 2.2 * d, f"{side}_ankle": -0.5 * d,
                     f"{side}_sh_flex": 1.3 * d, f"{side}_hip_abd": 0.15 * d})
        return m.set(body_pitch=0.2 * d, torso_pitch=0.35 * d, head_pitch=0.3 + 0.2 * d)
    return fn


def _prone_pitch(reach: float, body_len: float) -> np.ndarray | float:
    """Lean from vertical of a straight body of `body_len` whose shoulders are held
    `reach` above the ground at its other end (hands and feet, or hands and knees)."""
    return np.arccos(np.clip(reach / body_len, 0.0, 0.95))


def _pushup(rng, shape):
    period = rng.uniform(1.4, 2.6)
    body_len = shape.spine + shape.thigh + shape.shin + 0.8 * shape.foot

    def fn(t):
        d = 0.5 * (1 - np.cos(2 * np.pi * t / period))
        elbow = 0.1 + 1.3 * d
        # Upper arms stay vertical; the bent forearm sets the shoulder height.
        lean = _prone_pitch(shape.upper_arm + shape.forearm * np.cos(elbow), body_len)
        m = Motion.rest(t.size)
        for side in "rl":
            m.set(**{f"{side}_sh_flex": lean, f"{side}_sh_abd": 0.25, f"{side}_elbow": elbow,
                     f"{side}_knee": 0.05, f"{side}_ankle": 0.6})
        return m.set(body_pitch=lean, head_pitch=0.35)
    return fn


def _boxing(rng, shape):
    rate, hand = rng.uniform(0.8, 1.8), rng.choice([-1.0, 1.0])
    bob = rng.uniform(1.0, 2.0)
    punch_r, punch_l = _Pulses(rng, rate, 0.07), _Pulses(rng, rate, 0.07)

    def fn(t):
        m = Motion.rest(t.size)
        m.yaw_rate[:] = 0.4 * np.sin(0.7 * t)
        m.speed[:] = 0.15 * np.sin(bob * t)
        punches = {"r": punch_r(t), "l": punch_l(t)}
        for side in "rl":
            p = punches[side]
            m.set(**{f"{side}_sh_flex": 0.9 + 0.7 * p, f"{side}_sh_abd": 0.25 - 0.15 * p,
                     f"{side}_elbow": 2.0 * (1 - p) + 0.15 * p,
                     f"{side}_hip_flex": 0.25, f"{side}_knee": 0.35 + 0.1 * np.sin(2 * bob * t)})
        return m.set(torso_twist=hand * 0.35 * (punches["l"] - punches["r"]), body_pitch=0.1,
                     head_pitch=0.15)
    return fn


def _kick(rng, shape):
    rate, height = rng.uniform(0.4, 0.8), rng.uniform(0.9, 1.5)
    kicks = {"r": _Pulses(rng, rate, 0.16), "l": _Pulses(rng, rate, 0.16)}

    def fn(t):
        m = Motion.rest(t.size)
        lean = np.zeros(t.size)
        for side in "rl":
            k = kicks[side](t)
            lean += k
            m.set(**{f"{side}_hip_flex": 0.15 + height * k, f"{side}_knee": 0.3 + 1.6 * k - 1.5 * k**2,
                     f"{side}_sh_flex": 0.8, f"{side}_elbow": 1.8, f"{side}_ankle": 0.4 * k})
        return m.set(body_pitch=-0.2 * np.clip(lean, 0, 1), head_pitch=0.3)
    return fn


def _dance(rng, shape):
    freq, amp, spin = rng.uniform(0.8, 1.6), rng.uniform(0.7, 1.2), rng.uniform(-1.0, 1.0)

    def fn(t):
        ph = 2 * np.pi * freq * t
        m = Motion.rest(t.size)
        m.yaw_rate[:] = spin * np.sin(0.3 * ph)
        m.speed[:] = 0.2 * np.sin(0.5 * ph) ** 2
        for side, off in (("r", 0.0), ("l", np.pi)):
            m.set(**{f"{side}_sh_flex": amp * (0.9 + 0.8 * np.sin(ph + off)),
                     f"{side}_sh_abd": 0.6 + 0.5 * np.sin(0.5 * ph + off),
                     f"{side}_elbow": 0.6 + 0.5 * np.cos(ph + off),
                     f"{side}_hip_flex": 0.35 * np.clip(np.sin(ph + off), 0, None),
                     f"{side}_knee": 0.2 + 0.5 * np.clip(np.sin(ph + off), 0, None)})
        return m.set(body_roll=0.12 * np.sin(ph), torso_twist=0.3 * np.sin(0.5 * ph),
                     torso_roll=0.1 * np.sin(ph + 1), head_yaw=0.2 * np.sin(0.5 * ph))
    return fn


def _interaction(rng, shape):
    rate = rng.uniform(0.3, 0.5)
    targets = rng.uniform(size=(int(_Pulses.SPAN_S * rate) + 2, 3))  # per reach: height, hand, head turn
    reaches = _Pulses(rng, rate, 0.45)

    def fn(t):
        m = Motion.rest(t.size)
        reach = reaches(t)
        idx = np.clip((t * rate).astype(int), 0, len(targets) - 1)
        low = 1 - targets[idx, 0]  # 1: picking something up from the floor
        m.speed[:] = 0.5 * (1 - reach)
        m.yaw_rate[:] = 0.6 * (targets[idx, 2] - 0.5)
        for side, use in (("r", targets[idx, 1] > 0.35), ("l", targets[idx, 1] < 0.65)):
            r = reach * use
            m.set(**{f"{side}_sh_flex": r * (2.4 - 1.3 * low), f"{side}_elbow": 0.3 + 0.6 * r * (1 - low),
                     f"{side}_hip_flex": 0.8 * r * low, f"{side}_knee": 1.2 * r * low})
        return m.set(torso_pitch=0.9 * reach * low, body_pitch=0.3 * reach * low,
                     head_pitch=0.3 + 0.3 * reach * low - 0.4 * reach * (1 - low),
                     head_yaw=0.5 * reach * (targets[idx, 2] - 0.5))
    return fn


def _crawl(rng, shape):
    freq = rng.uniform(0.5, 0.9)
    # hands under the shoulders, knees under the hips
    pitch = _prone_pitch(shape.upper_arm + shape.forearm - shape.thigh, shape.spine)

    def fn(t):
        ph = 2 * np.pi * freq * t
        m = Motion.rest(t.size)
        m.speed[:] = 0.35 * freq
        m.yaw_rate[:] = 0.3 * np.sin(0.2 * ph)
        for side, off in (("r", 0.0), ("l", np.pi)):
            s = np.sin(ph + off)
            m.set(**{f"{side}_sh_flex": pitch + 0.25 * s, f"{side}_elbow": 0.1 + 0.2 * np.clip(s, 0, None),
                     f"{side}_hip_flex": pitch - 0.25 * s, f"{side}_knee": 1.5 - 0.2 * s,
                     f"{side}_ankle": 1.5, f"{side}_sh_abd": 0.1})  # instep flat on the floor
        return m.set(body_pitch=pitch + 0.03 * np.sin(2 * ph), head_pitch=-0.3,
                     head_yaw=0.15 * np.sin(0.5 * ph))
    return fn


def _sports(rng, shape):
    rate, hand = rng.uniform(0.5, 1.0), rng.choice(["r", "l"])
    swings, hops = _Pulses(rng, rate, 0.2), _Pulses(rng, 0.3, 0.12)

    def fn(t):
        m = Motion.rest(t.size)
        swing, hop = swings(t), hops(t)
        m.speed[:] = 0.8 * np.sin(1.3 * t)
        m.yaw_rate[:] = 0.9 * np.sin(0.6 * t)
        m.lift[:] = 0.25 * hop
        other = "l" if hand == "r" else "r"
        for side in "rl":
            m.set(**{f"{side}_hip_flex": 0.35 + 0.5 * hop, f"{side}_knee": 0.6 + 0.5 * hop})
        m.set(**{f"{hand}_sh_flex": 0.4 + 2.2 * swing, f"{hand}_sh_abd": 0.4 + 0.3 * swing,
                 f"{hand}_elbow": 0.9 - 0.6 * swing, f"{other}_sh_flex": 0.6 + 0.4 * swing,
                 f"{other}_elbow": 1.2})
        return m.set(torso_twist=0.6 * (swing - 0.4), body_pitch=0.2, head_pitch=0.1)
    return fn


def _jump(rng, shape):
    period, height, forward = rng.uniform(1.2, 1.9), rng.uniform(0.15, 0.4), rng.uniform(0.0, 1.0)

    def fn(t):
        ph = (t / period) % 1.0
        flight = np.clip(np.sin(np.pi * (ph - 0.4) / 0.3), 0, None) * ((ph > 0.4) & (ph < 0.7))
        crouch = np.exp(-0.5 * ((ph - 0.3) / 0.08) ** 2) + np.exp(-0.5 * ((ph - 0.8) / 0.08) ** 2)
        m = Motion.rest(t.size)
        m.lift[:] = height * flight
        m.speed[:] = forward * flight
        for side in "rl":
            m.set(**{f"{side}_hip_flex": 1.1 * crouch + 0.2 * flight, f"{side}_knee": 1.6 * crouch + 0.3 * flight,
                     f"{side}_ankle": 0.6 * flight - 0.3 * crouch,
                     f"{side}_sh_flex": -0.6 * crouch + 2.4 * flight, f"{side}_elbow": 0.3})
        return m.set(body_pitch=0.35 * crouch, head_pitch=0.3 + 0.2 * crouch)
    return fn


_FACTORIES = {
    "walk": _walk, "crouch": _crouch, "pushup": _pushup, "boxing": _boxing, "kick": _kick,
    "dance": _dance, "interaction": _interaction, "crawl": _crawl, "sports": _sports, "jump": _jump,
}


def make_action(name: str, rng: np.random.Generator, shape: BodyShape) -> ActionFn:
    """A motion generator for action `name` with a style drawn from `rng`."""
    return _FACTORIES[name](rng, shape)
