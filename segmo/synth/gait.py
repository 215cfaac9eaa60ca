"""Stepping: walking, running, side steps, circles and turns on the spot.

A gait is built pelvis-first: the pelvis follows a speed profile (ease in, cruise, ease
out) along a heading that may turn; each footstep lands where its foot belongs relative
to the pelvis at mid-stance, so planted feet never slide. The pelvis is then lowered
wherever a stance foot would be out of reach, and a trailing foot peels off the floor by
pivoting about its toe, so the leg IK nearly always reaches its target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from segmo.synth.rig import (
    ANKLE_HEIGHT,
    CHEST_WRISTS,
    LEG_REACH,
    REST_OFFSETS,
    SIT_FEET,
    SIT_HEIGHT,
    STAND_FEET,
    STAND_HEIGHT,
    BodyTrack,
    axis_angle,
    identity,
    qmul,
    qrot,
)

FPS = 20.0
_TOE = REST_OFFSETS[[10, 11]]  # ankle -> toe, rest pose
_HIPS = REST_OFFSETS[[1, 2]]


def smoothstep(x) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def gaussian(x: np.ndarray, sigma: float) -> np.ndarray:
    """Smooth along axis 0 with edge replication."""
    if sigma <= 0:
        return x
    r = int(3 * sigma + 0.5)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    idx = np.clip(np.arange(len(x))[:, None] + np.arange(-r, r + 1)[None], 0, len(x) - 1)
    return np.tensordot(k, x[idx], axes=([0], [1])) if x.ndim > 1 else (x[idx] * k).sum(1)


def sliding(x: np.ndarray, radius: int, reduce=np.max) -> np.ndarray:
    """Sliding-window max/min of (t,) with edge replication."""
    idx = np.clip(np.arange(len(x))[:, None] + np.arange(-radius, radius + 1)[None], 0, len(x) - 1)
    return reduce(x[idx], axis=1)


def neutral_track(t: int, sitting: bool = False) -> BodyTrack:
    """A motionless neutral pose (standing or sitting) for t frames at the origin."""
    height = SIT_HEIGHT if sitting else STAND_HEIGHT
    feet = (SIT_FEET if sitting else STAND_FEET) + np.array([0.0, height, 0.0])
    pelvis = axis_angle((1, 0, 0), np.full(t, -0.12 if sitting else 0.0))
    return BodyTrack(
        root=np.tile([0.0, height, 0.0], (t, 1)), yaw=np.zeros(t), pelvis=pelvis,
        spine=identity(t, 3), neck=identity(t), feet=np.tile(feet, (t, 1, 1)),
        foot_rot=identity(t, 2), knee_pole=np.tile([0.0, 0.0, 1.0], (t, 2, 1)),
        wrists=np.tile(CHEST_WRISTS, (t, 1, 1)), elbow_pole=np.tile([0.0, -0.3, -1.0], (t, 2, 1)),
    )


def yaw_rotate(yaw: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate (..., 3) vectors about +y by yaw (...)."""
    return qrot(axis_angle((0, 1, 0), yaw), v)


@dataclass
class GaitStyle:
    """Shape of a gait. stance: fraction of a stride a foot is on the floor (walking > 0.5,
    running < 0.5); lift: swing-foot clearance (m); crouch: pelvis lowered (m); lean:
    forward torso lean (rad); arm_swing: wrist travel per metre of foot separation;
    arm_bend: how far the hands come up (running arms), 0..1."""

    stance: float = 0.6
    lift: float = 0.08
    crouch: float = 0.015
    lean: float = 0.03
    arm_swing: float = 0.3
    arm_bend: float = 0.0
    bob: float = 0.0


def stepping(
    rng: np.random.Generator,
    speed: float,
    num_steps: int,
    cadence: float,
    direction: tuple[float, float] = (0.0, 1.0),
    turn: float = 0.0,
    turn_with_distance: bool = True,
    style: GaitStyle | None = None,
    first_foot: int | None = None,
) -> BodyTrack:
    """A stepping action from and to the standing neutral pose.

    speed: cruising speed (m/s) along `direction` (x, z) in the body frame;
    num_steps: footsteps while moving; cadence: steps per second;
    turn: total heading change (rad, + = left), spread over the distance travelled or,
    when `turn_with_distance` is False (turning on the spot), over the time.
    """
    style = style or GaitStyle()
    step_time = 1.0 / cadence
    stride = 2 * step_time
    swing = (1 - style.stance) * stride
    lead = rng.uniform(0.1, 0.2)
    move = num_steps * step_time
    t_end = lead + move + swing
    num_frames = int(np.ceil((t_end + rng.uniform(0.25, 0.4)) * FPS))
    time = np.arange(num_frames) / FPS

    # Pelvis: speed ramps up over the first step and down over the last one.
    ramp = smoothstep((time - lead) / step_time) * smoothstep((lead + move + 0.5 * swing - time) / step_time)
    distance = np.cumsum(speed * ramp) / FPS
    distance -= distance[0]
    total = max(distance[-1], 1e-6)
    if turn_with_distance:
        yaw = turn * distance / total
    else:
        yaw = turn * smoothstep((time - lead) / (move + 0.5 * swing))
    dir3 = np.array([direction[0], 0.0, direction[1]])
    velocity = yaw_rotate(yaw, np.broadcast_to(dir3, (num_frames, 3))) * (speed * ramp)[:, None]
    root = np.concatenate([np.zeros((1, 3)), np.cumsum(velocity[:-1], 0) / FPS])

    # Footsteps: (foot, lift time, land time); the landing spot is where the foot sits
    # relative to the pelvis at mid-stance.
    def nominal(foot: int, at: float) -> tuple[np.ndarray, float]:
        i = min(int(round(at * FPS)), num_frames - 1)
        return root[i] + yaw_rotate(yaw[i], np.array([STAND_FEET[foot, 0], 0, STAND_FEET[foot, 2]])), yaw[i]

    if first_foot is None:
        first_foot = int(rng.integers(2))
    steps = []
    for k in range(num_steps):
        lift_t = lead + k * step_time
        land_t = lift_t + swing
        ref = land_t + 0.4 * style.stance * stride
        if abs(direction[0]) > 0.5:
            # Side steps: the leading foot reaches out, the trailing one closes up to it,
            # so the legs never cross.
            ref = land_t + (0.9 * step_time if k % 2 == 0 else 0.0)
        ref = min(ref, t_end)
        steps.append(((first_foot + k) % 2, lift_t, land_t, *nominal((first_foot + k) % 2, ref)))
    # Closing steps bring any foot that is not yet beside the other back to neutral.
    final = {f: nominal(f, t_end) for f in (0, 1)}
    last = {f: [s for s in steps if s[0] == f] for f in (0, 1)}
    t_next = lead + num_steps * step_time
    for k in range(2):
        f = (first_foot + num_steps + k) % 2
        prev = last[f][-1][3] if last[f] else None
        if prev is None or np.linalg.norm(prev - final[f][0]) > 0.02:
            steps.append((f, t_next, t_next + min(swing, 0.45), *final[f]))
            t_next += step_time
    num_frames = max(num_frames, int(np.ceil((t_next + 0.3) * FPS)))
    if num_frames > len(root):
        extra = num_frames - len(root)
        root = np.concatenate([root, np.repeat(root[-1:], extra, 0)])
        yaw = np.concatenate([yaw, np.repeat(yaw[-1:], extra)])
        ramp = np.concatenate([ramp, np.zeros(extra)])
        time = np.arange(num_frames) / FPS

    # Foot tracks, stance first (flat feet on their plant), then swings.
    feet = np.zeros((num_frames, 2, 3))
    foot_yaw = np.zeros((num_frames, 2))
    in_stance = np.ones((num_frames, 2), bool)
    for f in (0, 1):
        home = np.array([STAND_FEET[f, 0], 0.0, STAND_FEET[f, 2]])
        feet[:, f] = home
        for foot, _, land_t, pos, yaw_f in steps:
            if foot == f:
                after = time >= land_t
                feet[after, f] = pos
                foot_yaw[after, f] = yaw_f
        for foot, lift_t, land_t, _, _ in steps:
            if foot == f:
                in_stance[(time > lift_t) & (time < land_t), f] = False
    feet[..., 1] = ANKLE_HEIGHT

    # Pelvis height: lowered where a stance foot would be out of reach, allowing the
    # foot to peel off about its toe by up to 50 degrees.
    hips = root[:, None] + yaw_rotate(yaw[:, None], np.broadcast_to(_HIPS, (num_frames, 2, 3)))
    pitches = np.radians(np.arange(0, 55, 5.0))
    foot_q = qmul(axis_angle((0, 1, 0), foot_yaw)[..., None, :], axis_angle((1, 0, 0), pitches))
    toe = feet + yaw_rotate(foot_yaw, np.broadcast_to(_TOE, (num_frames, 2, 3)))
    ankles = toe[:, :, None] - qrot(foot_q, np.broadcast_to(_TOE[None, :, None], (num_frames, 2, len(pitches), 3)))
    reach = 0.985 * LEG_REACH
    horizontal = np.linalg.norm((ankles - hips[:, :, None])[..., [0, 2]], axis=-1)
    hip_drop = -_HIPS[:, 1][None, :, None]
    allowed = ankles[..., 1] + hip_drop + np.sqrt(np.clip(reach**2 - horizontal**2, 0, None))
    allowed = np.where(in_stance, allowed.max(-1), np.inf).min(1)
    flight = gaussian((~in_stance).all(1).astype(float), 1.5)
    base = STAND_HEIGHT - style.crouch * smoothstep(ramp * 2) + style.bob * flight
    height = np.minimum(base, allowed)
    height = sliding(height, 2, np.min)  # erode so that smoothing stays within reach
    height[:2], height[-2:] = base[:2], base[-2:]
    root[:, 1] = gaussian(np.minimum(base, height), 1.2)

    # Toe pivot: the smallest pitch that brings the ankle within reach.
    hips[..., 1] = root[:, None, 1] - hip_drop[..., 0]
    dist = np.linalg.norm(ankles - hips[:, :, None], axis=-1)
    ok = dist <= reach
    choice = np.where(ok.any(-1), ok.argmax(-1), len(pitches) - 1)
    pitch = np.where(in_stance, pitches[choice], 0.0)
    pitch = np.where(in_stance, gaussian(pitch, 0.8), 0.0)
    foot_rot = qmul(axis_angle((0, 1, 0), foot_yaw), axis_angle((1, 0, 0), pitch))
    stance_ankle = toe - qrot(foot_rot, np.broadcast_to(_TOE, (num_frames, 2, 3)))
    feet = np.where(in_stance[..., None], stance_ankle, feet)

    # Swings: from the (possibly peeled) lift-off ankle to the landing spot along an arc.
    for foot, lift_t, land_t, pos, yaw_f in steps:
        i0 = min(int(np.floor(lift_t * FPS)), num_frames - 1)
        mask = (time > lift_t) & (time < land_t)
        if not mask.any():
            continue
        u = (time[mask] - lift_t) / (land_t - lift_t)
        start, start_yaw, start_pitch = feet[i0, foot].copy(), foot_yaw[i0, foot], pitch[i0, foot]
        end = np.array([pos[0], ANKLE_HEIGHT, pos[2]])
        s = smoothstep(u)[:, None]
        arc = np.sin(np.pi * u) ** 1.5 * style.lift
        feet[mask, foot] = start + (end - start) * s + np.array([0.0, 1.0, 0.0]) * arc[:, None]
        yaw_now = start_yaw + (yaw_f - start_yaw) * s[:, 0]
        pitch_now = start_pitch * (1 - u) ** 2 - 0.25 * np.sin(np.pi * u) ** 2 * (style.lift > 0.1)
        foot_rot[mask, foot] = qmul(axis_angle((0, 1, 0), yaw_now), axis_angle((1, 0, 0), pitch_now))
        foot_yaw[mask, foot] = yaw_now

    track = neutral_track(num_frames)
    track.root, track.yaw, track.feet, track.foot_rot = root, yaw, feet, foot_rot
    knee_dir = np.stack([np.sin(foot_yaw), np.zeros_like(foot_yaw), np.cos(foot_yaw)], -1)
    track.knee_pole = knee_dir
    lean = style.lean * smoothstep(ramp * 1.5)
    track.spine = np.stack([axis_angle((1, 0, 0), lean * 0.5)] * 2 + [axis_angle((1, 0, 0), lean * 0.5)], 1)
    # Arms swing against the legs: each hand forward when the opposite foot is forward.
    local_feet = yaw_rotate(-yaw[:, None], feet - root[:, None])
    separation = local_feet[:, 1, 2] - local_feet[:, 0, 2]
    bend = style.arm_bend * smoothstep(ramp * 2)
    wrists = np.tile(CHEST_WRISTS, (num_frames, 1, 1))
    wrists[:, 0, 2] += style.arm_swing * separation
    wrists[:, 1, 2] -= style.arm_swing * separation
    wrists[..., 1] += 0.22 * bend[:, None]
    wrists[..., 2] += 0.12 * bend[:, None]
    track.wrists = wrists
    return track
