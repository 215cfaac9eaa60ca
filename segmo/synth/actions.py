"""The action library: parametric, procedural atomic actions on the t2m skeleton.

Each action samples its parameters (`sample(rng)` -> JSON-able dict) and builds a
`BodyTrack` (`build(rng, params, sitting)`) that starts and ends in the neutral pose of
its body state. Upper-body actions are also arm overlays (`arm_overlay`) so that they can
run on top of a locomotion ("walks forward while waving").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from segmo.synth.gait import FPS, GaitStyle, gaussian, neutral_track, smoothstep, stepping
from segmo.synth.rig import (
    CHEST_SHOULDERS,
    CHEST_WRISTS,
    SIT_FEET,
    SIT_HEIGHT,
    STAND_FEET,
    STAND_HEIGHT,
    BodyTrack,
    axis_angle,
    qmul,
)

SIDES = {"left": 0, "right": 1}
_SIGN = {"left": 1.0, "right": -1.0}  # +x is the body's left


def _frames(seconds: float) -> int:
    return max(2, int(round(seconds * FPS)))


def _envelope(t: int, rise: int, fall: int, lead: int = 0) -> np.ndarray:
    """0 -> 1 over `rise` frames after `lead`, back to 0 over the last `fall` frames."""
    i = np.arange(t, dtype=float)
    return smoothstep((i - lead) / max(rise, 1)) * smoothstep((t - 1 - i) / max(fall, 1))


def _pitch(angle) -> np.ndarray:
    return axis_angle((1, 0, 0), angle)


# ---------------------------------------------------------------- arm overlays
@dataclass
class ArmOverlay:
    """wrists, pole: (t, 2, 3) chest-frame targets; weight: (t, 2) blend towards them."""

    wrists: np.ndarray
    pole: np.ndarray
    weight: np.ndarray
    twist: np.ndarray | None = None  # (t,) torso yaw, standalone use only


def _arm_base(t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.tile(CHEST_WRISTS, (t, 1, 1)), np.tile([0.0, -0.3, -1.0], (t, 2, 1)), np.zeros((t, 2))


def arm_overlay(name: str, params: dict, t: int) -> ArmOverlay:
    """The arm part of an upper-body action, stretched over t frames."""
    wrists, pole, weight = _arm_base(t)
    env = _envelope(t, _frames(0.4), _frames(0.4), lead=1)
    time = np.arange(t) / FPS
    twist = None
    if name == "wave":
        sides = ["left", "right"] if params["hand"] == "both" else [params["hand"]]
        active = max(t / FPS - 0.9, 0.3)
        freq = params.get("count", 0) / active if params.get("count") else 2.0
        osc = np.sin(2 * np.pi * freq * np.clip(time - 0.45, 0, None)) * smoothstep((time - 0.3) / 0.2)
        for side in sides:
            k, s = SIDES[side], _SIGN[side]
            wrists[:, k] = CHEST_SHOULDERS[k] + np.array([s * 0.26, 0.3, 0.12])
            wrists[:, k, 0] += s * 0.11 * osc
            pole[:, k] = [s, -0.6, -0.2]
            weight[:, k] = env
    elif name == "clap":
        count = params.get("count") or max(2, int(t / FPS * 2))
        active = max(t / FPS - 0.9, 0.3)
        phase = np.clip((time - 0.45) / active, 0, 1) * count
        gap = 0.5 + 0.5 * np.cos(2 * np.pi * phase)  # 1 = apart, 0 = hands together
        for k, s in ((0, 1.0), (1, -1.0)):
            wrists[:, k, 0], wrists[:, k, 1], wrists[:, k, 2] = s * (0.025 + 0.16 * gap), 0.02, 0.36
            pole[:, k] = [s * 0.5, -1.0, -0.2]
            weight[:, k] = env
    elif name in ("raise_arm", "stretch_arms_up"):
        sides = ["left", "right"] if name == "stretch_arms_up" else [params["side"]]
        up = _envelope(t, _frames(0.8), _frames(0.8), lead=1)
        theta = np.radians(172.0) * up
        for side in sides:
            k, s = SIDES[side], _SIGN[side]
            wrists[:, k] = CHEST_SHOULDERS[k] + 0.52 * np.stack(
                [np.full(t, s * 0.12), -np.cos(theta), np.sin(theta)], -1)
            pole[:, k] = [s, 0.0, -0.4]
            weight[:, k] = np.minimum(1.0, up * 3)
    elif name == "punch":
        k, s = SIDES[params["side"]], _SIGN[params["side"]]
        for kk, ss in ((0, 1.0), (1, -1.0)):  # guard: both fists up in front of the chin
            wrists[:, kk] = [ss * 0.1, 0.13, 0.3]
            pole[:, kk] = [ss * 0.4, -1.0, 0.0]
            weight[:, kk] = env
        count = params.get("count", 1)
        hit = np.zeros(t)
        starts = 0.5 + np.arange(count) * 0.5
        for start in starts:
            u = (time - start) / 0.4
            hit = np.maximum(hit, np.where((u > 0) & (u < 1), np.sin(np.pi * np.clip(u, 0, 1)) ** 0.7, 0))
        wrists[:, k] = (1 - hit[:, None]) * wrists[:, k] + hit[:, None] * (
            CHEST_SHOULDERS[k] + np.array([-s * 0.08, 0.06, 0.52]))
        twist = s * -0.3 * hit  # the punching shoulder comes forward
    else:
        raise ValueError(f"arm_overlay: {name!r} is not an upper-body action")
    return ArmOverlay(wrists, pole, weight, twist)


def apply_arms(track: BodyTrack, overlay: ArmOverlay, torso: bool = True) -> BodyTrack:
    w = overlay.weight[..., None]
    track.wrists = (1 - w) * track.wrists + w * overlay.wrists
    track.elbow_pole = (1 - w) * track.elbow_pole + w * overlay.pole
    if torso and overlay.twist is not None:
        track.spine[:, 2] = qmul(track.spine[:, 2], axis_angle((0, 1, 0), overlay.twist))
    return track


def _upper_duration(name: str, params: dict) -> float:
    if name == "wave":
        return 0.9 + params["count"] * 0.5
    if name == "clap":
        return 0.9 + params["count"] * 0.42
    if name == "punch":
        return 1.0 + params["count"] * 0.5
    return 1.6 + params["hold"]  # raise_arm, stretch_arms_up


def _upper(name: str):
    def build(rng, params, sitting):
        t = _frames(_upper_duration(name, params))
        track = neutral_track(t, sitting)
        track = apply_arms(track, arm_overlay(name, params, t))
        if name == "stretch_arms_up":
            env = _envelope(t, _frames(0.6), _frames(0.6), lead=1)
            track.spine[:, 1] = _pitch(-0.12 * env)
            track.neck = _pitch(-0.25 * env)
        return track
    return build


# ---------------------------------------------------------------- whole-body actions
def _locomotion(kind: str):
    def build(rng, p, sitting):
        if kind == "walk_forward":
            return stepping(rng, p["speed"], p["steps"], 1.6 + 0.45 * p["speed"])
        if kind == "walk_backward":
            return stepping(rng, p["speed"], p["steps"], 1.5 + 0.5 * p["speed"], direction=(0, -1),
                            style=GaitStyle(lift=0.06, lean=-0.02, arm_swing=0.2))
        if kind == "jog":
            return stepping(rng, p["speed"], p["steps"], 2.6 + 0.1 * p["speed"], style=GaitStyle(
                stance=0.42, lift=0.13, crouch=0.035, lean=0.08, arm_swing=0.35, arm_bend=0.8, bob=0.03))
        if kind == "run":
            return stepping(rng, p["speed"], p["steps"], 2.6 + 0.12 * p["speed"], style=GaitStyle(
                stance=0.35, lift=0.2, crouch=0.05, lean=0.15, arm_swing=0.4, arm_bend=1.0, bob=0.05))
        if kind == "side_step":
            s = _SIGN[p["direction"]]
            return stepping(rng, p["speed"], p["steps"], 1.6, direction=(s, 0),
                            style=GaitStyle(lift=0.05, arm_swing=0.0), first_foot=SIDES[p["direction"]])
        if kind == "walk_circle":
            s = _SIGN[p["direction"]]
            distance = 2 * np.pi * p["radius"]
            cadence = 1.6 + 0.45 * p["speed"]
            steps = max(4, int(round(distance / p["speed"] * cadence)))
            return stepping(rng, p["speed"], steps, cadence, turn=s * 2 * np.pi)
        if kind in ("turn", "spin"):
            angle = 360.0 if kind == "spin" else p["angle"]
            steps = p.get("steps", 2 + int(round(angle / 60)))
            return stepping(rng, 0.0, steps, 2.3 if kind == "spin" else 1.8,
                            turn=_SIGN[p["direction"]] * np.radians(angle), turn_with_distance=False,
                            style=GaitStyle(lift=0.06, arm_swing=0.0))
        raise ValueError(kind)
    return build


def _jump(rng, p, sitting, hop_side: str | None = None):
    """Jumps (both feet, in place or forward) or hops on one foot (hop_side = support)."""
    count, dist = p["count"], p.get("distance", 0.0)
    hop = hop_side is not None
    height = p.get("height", 0.1 if hop else 0.22)
    flight = 2 * np.sqrt(2 * height / 9.81)
    # "ground" (version 2): seconds on the ground between two jumps; the crouches before
    # take-off and after landing shrink with it, the flight (gravity) does not.
    ground = p.get("ground", 0.25 if hop else 0.55)
    k = ground / (0.25 if hop else 0.55)
    prep, period = 0.45 * k, flight + ground
    total = prep + count * period + 0.6 * k
    t = _frames(total)
    time = np.arange(t) / FPS
    track = neutral_track(t)
    base_feet = track.feet.copy()
    lift = np.zeros(t)
    crouch = np.zeros(t)
    forward = np.zeros(t)
    for i in range(count):
        t0 = prep + i * period
        u = (time - t0) / flight
        air = (u > 0) & (u < 1)
        lift = np.where(air, 4 * height * u * (1 - u), lift)
        forward += dist * smoothstep(u)
        depth = 0.05 if hop else 0.16
        crouch += depth * np.exp(-0.5 * ((time - (t0 - 0.15 * k)) / (0.09 * k)) ** 2)
        crouch += depth * np.exp(-0.5 * ((time - (t0 + flight + 0.12 * k)) / (0.09 * k)) ** 2)
    lean = 1.6 * crouch
    track.root[:, 1] += lift - crouch
    track.root[:, 2] += forward
    track.pelvis = _pitch(lean)
    track.spine[:, 1] = _pitch(0.5 * lean)
    feet_up = np.maximum(lift - 0.02, 0) * 0.9
    for k in (0, 1):
        track.feet[:, k, 1] = base_feet[:, k, 1] + feet_up
        track.feet[:, k, 2] = base_feet[:, k, 2] + forward
    swing = -0.25 * crouch / 0.16 + 0.35 * np.clip(lift / max(height, 1e-3), 0, 1)
    track.wrists[..., 2] += swing[:, None] * (0.2 if not hop else 0.3)
    track.wrists[..., 1] += np.maximum(swing, 0)[:, None] * 0.15
    if hop:
        k = SIDES[hop_side]
        other = 1 - k
        env = _envelope(t, _frames(0.35), _frames(0.35), lead=1)
        track.root[:, 0] += STAND_FEET[k, 0] * 0.7 * env
        track.feet[:, other, 1] += 0.3 * env
        track.feet[:, other, 2] -= 0.22 * env
        track.feet[:, other, 0] += (STAND_FEET[k, 0] * 0.7) * env
        track.wrists[..., 0] += np.array([0.12, -0.12]) * env[:, None]
        track.wrists[..., 1] += 0.1 * env[:, None]
        track.feet[:, other, 1] += lift * 0.9
    return track


def _sit(rng, p, sitting, reverse: bool = False):
    t = _frames(p["duration"])
    u = np.linspace(0, 1, t)
    if reverse:
        u = u[::-1]
    track = neutral_track(t)
    track.root[:, 2] = -SIT_FEET[0, 2] * smoothstep(u * 1.25)
    track.root[:, 1] = STAND_HEIGHT - (STAND_HEIGHT - SIT_HEIGHT) * smoothstep((u - 0.12) / 0.8)
    lean = 0.55 * np.sin(np.pi * np.clip(u * 1.1, 0, 1)) ** 1.5
    track.pelvis = _pitch(0.6 * lean)
    track.spine[:, 1] = _pitch(0.4 * lean)
    track.wrists[..., 2] += 0.25 * np.sin(np.pi * u)[:, None]
    track.wrists[..., 1] += 0.15 * np.sin(np.pi * u)[:, None]
    if reverse:
        track.root[:, 2] -= track.root[0, 2]  # the action's frame starts at the seated pelvis
        track.feet[..., 2] += SIT_FEET[0, 2]
    return track


def _bend(kind: str):
    """Squat (count), crouch (hold) and bow (angle): feet planted, pelvis and torso move."""
    def build(rng, p, sitting):
        if kind == "bow":
            t = _frames(1.4 + p["hold"])
            env = _envelope(t, _frames(0.6), _frames(0.6), lead=1)
            angle = np.radians(p["angle"]) * env
            track = neutral_track(t)
            track.pelvis = _pitch(0.35 * angle)
            track.spine[:, 1] = _pitch(0.35 * angle)
            track.spine[:, 2] = _pitch(0.3 * angle)
            track.root[:, 2] -= 0.12 * angle
            track.root[:, 1] -= 0.03 * angle
            return track
        if kind == "squat":
            reps, per = p["count"], 1.5
            t = _frames(0.3 + reps * per + 0.3)
            time = np.arange(t) / FPS
            down = np.where((time > 0.3) & (time < 0.3 + reps * per),
                            np.sin(np.pi * ((time - 0.3) / per)) ** 2, 0.0)
            depth, lean, hands = p["depth"] * down, 0.5 * down, down
        else:  # crouch: go down, stay, come back up
            t = _frames(1.4 + p["hold"])
            down = _envelope(t, _frames(0.6), _frames(0.6), lead=1)
            depth, lean, hands = p["depth"] * down, 0.7 * down, down
        track = neutral_track(t)
        track.root[:, 1] -= depth
        track.root[:, 2] -= 0.35 * depth
        track.pelvis = _pitch(lean * 0.8)
        track.spine[:, 1] = _pitch(lean * 0.3)
        track.knee_pole[..., 0] += np.array([0.4, -0.4]) * hands[:, None, None][..., 0]
        reach = np.array([0.0, -0.05, 0.45]) if kind == "squat" else np.array([0.0, -0.25, 0.35])
        for k in (0, 1):
            target = CHEST_SHOULDERS[k] + reach
            track.wrists[:, k] += (target - CHEST_WRISTS[k]) * hands[:, None]
        return track
    return build


def _kick(rng, p, sitting):
    k, s = SIDES[p["side"]], _SIGN[p["side"]]
    t = _frames(1.6)
    time = np.arange(t) / FPS
    track = neutral_track(t)
    env = _envelope(t, _frames(0.3), _frames(0.3), lead=1)
    track.root[:, 0] -= s * 0.06 * env
    key_t = [0.0, 0.3, 0.55, 0.75, 1.0, 1.3, 1.6]
    key_up = [0.0, 0.0, 0.2, p["height"], 0.25, 0.0, 0.0]
    key_fwd = [0.0, 0.0, -0.1, 0.55, 0.1, 0.0, 0.0]
    up = gaussian(np.interp(time, key_t, key_up), 1.0)
    fwd = gaussian(np.interp(time, key_t, key_fwd), 1.0)
    track.feet[:, k, 1] += up
    track.feet[:, k, 2] += fwd
    track.foot_rot[:, k] = _pitch(-0.6 * up / max(p["height"], 0.1))
    track.pelvis = _pitch(-0.2 * up / max(p["height"], 0.1))
    track.wrists[:, 1 - k, 2] += 0.2 * up
    track.wrists[..., 0] += np.array([0.1, -0.1]) * env[:, None]
    return track


def _stand_still(rng, p, sitting):
    t = _frames(p["duration"])
    track = neutral_track(t, sitting)
    time = np.arange(t) / FPS
    track.root[:, 0] += 0.008 * np.sin(2 * np.pi * time / 3.1 + rng.uniform(0, 6))
    track.neck = axis_angle((0, 1, 0), 0.08 * np.sin(2 * np.pi * time / 4.3))
    return track


# ---------------------------------------------------------------- the registry
@dataclass(frozen=True)
class ActionSpec:
    """An atomic action: where it can start (`needs`), where it leaves the body, whether
    it is an upper-body action (can overlay a locomotion), and how to sample and build it."""

    name: str
    needs: str  # "standing", "sitting" or "any"
    sample: Callable[[np.random.Generator], dict]
    build: Callable[..., BodyTrack]
    ends: str | None = None  # the body state afterwards when it changes
    upper: bool = False
    locomotion: bool = False


def _r(x: float, n: int = 2) -> float:
    return round(float(x), n)


def _side(rng) -> str:
    return "left" if rng.random() < 0.5 else "right"


ACTIONS: dict[str, ActionSpec] = {a.name: a for a in [
    ActionSpec("walk_forward", "standing", lambda r: {"speed": _r(r.uniform(1.0, 1.8)),
               "steps": int(r.integers(4, 10))}, _locomotion("walk_forward"), locomotion=True),
    ActionSpec("walk_backward", "standing", lambda r: {"speed": _r(r.uniform(0.6, 1.0)),
               "steps": int(r.integers(3, 7))}, _locomotion("walk_backward"), locomotion=True),
    ActionSpec("jog", "standing", lambda r: {"speed": _r(r.uniform(1.9, 2.5)),
               "steps": int(r.integers(6, 12))}, _locomotion("jog"), locomotion=True),
    ActionSpec("run", "standing", lambda r: {"speed": _r(r.uniform(2.6, 3.9)),
               "steps": int(r.integers(6, 13))}, _locomotion("run")),
    ActionSpec("side_step", "standing", lambda r: {"direction": _side(r), "speed": _r(r.uniform(0.35, 0.6)),
               "steps": int(r.integers(2, 4)) * 2}, _locomotion("side_step")),
    ActionSpec("walk_circle", "standing", lambda r: {"direction": _side(r), "radius": _r(r.uniform(0.7, 1.2)),
               "speed": _r(r.uniform(1.0, 1.4))}, _locomotion("walk_circle"), locomotion=True),
    ActionSpec("turn", "standing", lambda r: {"direction": _side(r), "angle": 90 if r.random() < 0.6 else 180},
               _locomotion("turn")),
    ActionSpec("spin", "standing", lambda r: {"direction": _side(r)}, _locomotion("spin")),
    ActionSpec("jump_in_place", "standing", lambda r: {"count": int(r.integers(1, 4)),
               "height": _r(r.uniform(0.15, 0.3))}, _jump),
    ActionSpec("jump_forward", "standing", lambda r: {"count": int(r.integers(1, 4)),
               "height": _r(r.uniform(0.15, 0.25)), "distance": _r(r.uniform(0.4, 0.8))}, _jump),
    ActionSpec("hop", "standing", lambda r: {"foot": _side(r), "count": int(r.integers(2, 6))},
               lambda rng, p, s: _jump(rng, p, s, hop_side=p["foot"])),
    ActionSpec("sit_down", "standing", lambda r: {"duration": _r(r.uniform(1.6, 2.4))}, _sit, ends="sitting"),
    ActionSpec("stand_up", "sitting", lambda r: {"duration": _r(r.uniform(1.5, 2.2))},
               lambda rng, p, s: _sit(rng, p, s, reverse=True), ends="standing"),
    ActionSpec("squat", "standing", lambda r: {"count": int(r.integers(1, 4)),
               "depth": _r(r.uniform(0.3, 0.42))}, _bend("squat")),
    ActionSpec("crouch", "standing", lambda r: {"depth": _r(r.uniform(0.42, 0.5)),
               "hold": _r(r.uniform(0.6, 1.5))}, _bend("crouch")),
    ActionSpec("bow", "standing", lambda r: {"angle": int(r.integers(35, 70)),
               "hold": _r(r.uniform(0.3, 1.0))}, _bend("bow")),
    ActionSpec("stretch_arms_up", "any", lambda r: {"hold": _r(r.uniform(0.6, 1.6))},
               _upper("stretch_arms_up"), upper=True),
    ActionSpec("kick", "standing", lambda r: {"side": _side(r), "height": _r(r.uniform(0.45, 0.75))}, _kick),
    ActionSpec("punch", "any", lambda r: {"side": _side(r), "count": int(r.integers(1, 4))},
               _upper("punch"), upper=True),
    ActionSpec("wave", "any", lambda r: {"hand": ["left", "right", "both"][int(r.choice(3, p=[0.4, 0.4, 0.2]))],
               "count": int(r.integers(1, 5))}, _upper("wave"), upper=True),
    ActionSpec("raise_arm", "any", lambda r: {"side": _side(r), "hold": _r(r.uniform(0.4, 1.2))},
               _upper("raise_arm"), upper=True),
    ActionSpec("clap", "any", lambda r: {"count": int(r.integers(2, 6))}, _upper("clap"), upper=True),
    ActionSpec("stand_still", "standing", lambda r: {"duration": _r(r.uniform(1.2, 3.0))}, _stand_still),
]}

# Version 2 of the corpus: durations follow the action and its parameters, as real ones
# do. Locomotion and standing still take more steps / seconds (up to many seconds); the
# short actions are quicker ("tempo": performed that many times faster than version 1's
# timing, see `_retime`; jumps spend less time on the ground). The actions not listed
# sample as in version 1 (`ActionSpec.sample`), whose parameters stay as they were so
# that version 1 corpora are reproduced (byte for byte on one kind of CPU).
SAMPLE_V2: dict[str, Callable[[np.random.Generator], dict]] = {
    # long: a few seconds to many
    "walk_forward": lambda r: {"speed": _r(r.uniform(1.0, 1.8)), "steps": int(r.integers(6, 21))},
    "walk_backward": lambda r: {"speed": _r(r.uniform(0.6, 1.0)), "steps": int(r.integers(4, 13))},
    "jog": lambda r: {"speed": _r(r.uniform(1.9, 2.5)), "steps": int(r.integers(8, 27))},
    "run": lambda r: {"speed": _r(r.uniform(2.6, 3.9)), "steps": int(r.integers(8, 31))},
    "side_step": lambda r: {"direction": _side(r), "speed": _r(r.uniform(0.35, 0.6)),
                            "steps": int(r.integers(3, 9)) * 2},
    "walk_circle": lambda r: {"direction": _side(r), "radius": _r(r.uniform(0.8, 1.6)),
                              "speed": _r(r.uniform(1.0, 1.4))},
    "stand_still": lambda r: {"duration": _r(r.uniform(1.5, 8.0))},
    # medium: about two seconds (sit_down and stand_up sample as in version 1)
    "squat": lambda r: {"count": int(r.integers(1, 4)), "depth": _r(r.uniform(0.3, 0.42)),
                        "tempo": _r(r.uniform(1.3, 1.6))},
    "crouch": lambda r: {"depth": _r(r.uniform(0.42, 0.5)), "hold": _r(r.uniform(0.3, 1.0)),
                         "tempo": _r(r.uniform(1.3, 1.6))},
    "stretch_arms_up": lambda r: {"hold": _r(r.uniform(0.4, 1.2)), "tempo": _r(r.uniform(1.2, 1.5))},
    "hop": lambda r: {"foot": _side(r), "count": int(r.integers(2, 6)), "ground": _r(r.uniform(0.15, 0.22))},
    "spin": lambda r: {"direction": _side(r), "tempo": _r(r.uniform(1.4, 1.8))},
    # short: about a second
    "turn": lambda r: (lambda angle: {"direction": _side(r), "angle": angle, "steps": 2 if angle == 90 else 3,
                                      "tempo": _r(r.uniform(1.6, 2.0))})(90 if r.random() < 0.6 else 180),
    "jump_in_place": lambda r: {"count": int(r.choice(3, p=[0.5, 0.3, 0.2])) + 1,
                                "height": _r(r.uniform(0.1, 0.2)), "ground": _r(r.uniform(0.18, 0.28))},
    "jump_forward": lambda r: {"count": int(r.choice(3, p=[0.5, 0.3, 0.2])) + 1,
                               "height": _r(r.uniform(0.1, 0.2)), "distance": _r(r.uniform(0.4, 0.8)),
                               "ground": _r(r.uniform(0.18, 0.28))},
    "bow": lambda r: {"angle": int(r.integers(35, 70)), "hold": _r(r.uniform(0.1, 0.4)),
                      "tempo": _r(r.uniform(1.5, 1.8))},
    "kick": lambda r: {"side": _side(r), "height": _r(r.uniform(0.45, 0.75)), "tempo": _r(r.uniform(1.8, 2.3))},
    "punch": lambda r: {"side": _side(r), "count": int(r.integers(1, 4)), "tempo": _r(r.uniform(1.8, 2.2))},
    "wave": lambda r: {"hand": ["left", "right", "both"][int(r.choice(3, p=[0.4, 0.4, 0.2]))],
                       "count": int(r.integers(1, 5)), "tempo": _r(r.uniform(1.5, 1.9))},
    "raise_arm": lambda r: {"side": _side(r), "hold": _r(r.uniform(0.2, 0.8)), "tempo": _r(r.uniform(1.5, 1.8))},
    "clap": lambda r: {"count": int(r.integers(2, 5)), "tempo": _r(r.uniform(1.7, 2.1))},
}


# Version 3: sitting down and standing up take about a second, so that a motion that sits
# down and stands up again can still hold a long action about 4× as long.
SAMPLE_V3: dict[str, Callable[[np.random.Generator], dict]] = {
    "sit_down": lambda r: {"duration": _r(r.uniform(1.1, 1.6))},
    "stand_up": lambda r: {"duration": _r(r.uniform(1.0, 1.5))},
}


def sample_params(name: str, rng: np.random.Generator, version: int) -> dict:
    """The parameters of action `name` as corpus `version` samples them."""
    if version >= 3 and name in SAMPLE_V3:
        return SAMPLE_V3[name](rng)
    if version >= 2 and name in SAMPLE_V2:
        return SAMPLE_V2[name](rng)
    return ACTIONS[name].sample(rng)


# Upper-body actions that can run on top of a locomotion, and their parameters there.
OVERLAYS = {"wave": lambda r: {"hand": _side(r)}, "clap": lambda r: {},
            "raise_arm": lambda r: {"side": _side(r), "hold": 0.0}}


def _pad(track: BodyTrack, before: int, after: int) -> BodyTrack:
    def pad(x):
        return np.concatenate([np.repeat(x[:1], before, 0), x, np.repeat(x[-1:], after, 0)])
    return BodyTrack(**{k: pad(v) for k, v in vars(track).items()})


_QUATERNIONS = ("pelvis", "spine", "neck", "foot_rot")


def resample_frames(x: np.ndarray, frames: int) -> np.ndarray:
    """(frames, ...) of (t ≥ 2, ...) `x` slowed or sped up evenly: linear interpolation in
    time, the first and last frame kept."""
    t = len(x)
    at = np.linspace(0.0, t - 1, frames)
    lo = np.minimum(at.astype(int), t - 2)
    w = (at - lo).reshape((-1,) + (1,) * (x.ndim - 1))
    return (1 - w) * x[lo] + w * x[lo + 1]


def _retime(track: BodyTrack, tempo: float) -> BodyTrack:
    """The same movement `tempo` times faster: every channel resampled in time (linear,
    quaternions renormalised), first and last frame kept, so it still starts and ends at
    rest. Counts (waves, claps, steps) are unchanged; only their pace is."""
    frames = max(2, int(round((track.num_frames - 1) / tempo)) + 1)
    out = {}
    for key, x in vars(track).items():
        y = resample_frames(x, frames)
        if key in _QUATERNIONS:
            y = y / np.linalg.norm(y, axis=-1, keepdims=True)
        out[key] = y
    return BodyTrack(**out)


def build_action(name: str, params: dict, rng: np.random.Generator, sitting: bool,
                 overlay: tuple[str, dict] | None = None) -> BodyTrack:
    """Build one segment's track; `overlay` = (upper action, params) runs at the same time."""
    track = ACTIONS[name].build(rng, params, sitting)
    if "tempo" in params:
        track = _retime(track, params["tempo"])
    if overlay is not None:
        track = apply_arms(track, arm_overlay(overlay[0], overlay[1], track.num_frames), torso=False)
    # Every action starts and ends with a few frames at rest in its neutral pose.
    track = _pad(track, int(rng.integers(2, 5)), int(rng.integers(3, 7)))
    noise = gaussian(rng.normal(0, 0.012, (track.num_frames, 3)), 4.0)  # small idiosyncrasy
    track.neck = qmul(track.neck, axis_angle((0, 1, 0), noise[:, 0] * 3))
    track.wrists = track.wrists + noise[:, None, :]
    return track

