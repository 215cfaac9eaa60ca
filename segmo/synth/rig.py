"""The synthetic character: rest pose, numpy rotation helpers, and a pose solver.

Poses are authored as a root trajectory, a heading, a few spine rotations, and targets
for the hands and feet; `solve_pose` turns them into local joint quaternions with
analytic two-bone IK. Quaternions are (w, x, y, z) as in `segmo.motion.quaternion`, and
local rotations follow `segmo.motion.kinematics`: joint c's quaternion rotates the bone
that ends at c, `B[c] = B[parent(c)] * q[c]`, `p[c] = p[parent(c)] + B[c] offsets[c]`.

The authoring maths is numpy (one motion is a few hundred frames, where numpy's small-array
overhead is far below torch's); the joint positions of a finished motion are computed by
the package's `forward_kinematics` (see `segmo.synth.sequence`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from segmo.motion.skeleton import T2M

PARENTS = T2M.parents
LENGTHS = np.asarray(T2M.reference_bone_lengths)

# Rest-pose bone directions of a relaxed standing person (y up, facing +Z, left = +X),
# read off the HumanML3D fixture clip 012314 and made symmetric; arms hang at the sides.
# Scaled to the reference bone lengths, so the retargeting in `joints_to_features` keeps
# every position.
_DIRECTIONS = np.array(
    [
        (0, 0, 0),  # pelvis
        (0.8, -0.58, 0.02), (-0.8, -0.58, 0.02),  # hips
        (0, 0.95, -0.3),  # spine1
        (0.04, -1, 0.01), (-0.04, -1, 0.01),  # knees
        (0, 0.97, 0.22),  # spine2
        (0, -1, -0.04), (0, -1, -0.04),  # ankles
        (0, 0.5, 0.87),  # spine3
        (0.2, -0.42, 0.88), (-0.2, -0.42, 0.88),  # toes
        (0, 0.97, -0.24),  # neck
        (0.35, 0.93, -0.05), (-0.35, 0.93, -0.05),  # collars
        (0, 0.85, 0.52),  # head
        (0.97, -0.1, -0.2), (-0.97, -0.1, -0.2),  # shoulders
        (0.12, -0.99, -0.05), (-0.12, -0.99, -0.05),  # elbows
        (0.05, -1, 0.12), (-0.05, -1, 0.12),  # wrists
    ],
    dtype=np.float64,
)
_norm = np.linalg.norm(_DIRECTIONS, axis=1, keepdims=True)
REST_OFFSETS = np.where(_norm > 0, _DIRECTIONS / np.maximum(_norm, 1e-12), 0.0) * LENGTHS[:, None]


def rest_positions() -> np.ndarray:
    """Rest-pose joints (22, 3) with the pelvis at the origin."""
    p = np.zeros((22, 3))
    for c in range(1, 22):
        p[c] = p[PARENTS[c]] + REST_OFFSETS[c]
    return p


_REST = rest_positions()
ANKLE_HEIGHT = float(_REST[7, 1] - _REST[10, 1])  # ankle above the floor when the toe touches it
# Pelvis height when standing: the toes on the floor, knees very slightly bent so that
# the leg IK never works at full extension.
STAND_HEIGHT = float(-_REST[10, 1]) - 0.01
# Ankle positions relative to the pelvis when standing (on the floor) and sitting.
STAND_FEET = np.array([[_REST[7, 0], ANKLE_HEIGHT - STAND_HEIGHT, _REST[7, 2]],
                       [_REST[8, 0], ANKLE_HEIGHT - STAND_HEIGHT, _REST[8, 2]]])
SIT_HEIGHT = 0.56
SIT_FEET = np.array([[0.11, ANKLE_HEIGHT - SIT_HEIGHT, 0.44], [-0.11, ANKLE_HEIGHT - SIT_HEIGHT, 0.44]])
# Rest wrist and elbow positions in the chest frame (bone rotation of spine3, origin at spine3).
CHEST_WRISTS = _REST[[20, 21]] - _REST[9]
CHEST_SHOULDERS = _REST[[16, 17]] - _REST[9]
LEG_REACH = float(LENGTHS[4] + LENGTHS[7])
ARM_REACH = float(LENGTHS[18] + LENGTHS[20])


# ---------------------------------------------------------------- numpy quaternions
# segmo.motion.quaternion is torch; the corpus builder does thousands of tiny per-joint
# operations per motion, where numpy is several times faster (2,000 motions in < 60 s).
def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product (..., 4) * (..., 4), broadcasting."""
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
         aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product of (..., 3) vectors (np.cross is slow on small arrays)."""
    ax, ay, az = a[..., 0], a[..., 1], a[..., 2]
    bx, by, bz = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], -1)


def qinv(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def qrot(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors (..., 3) by unit quaternions (..., 4)."""
    u = q[..., 1:]
    uv = cross(u, v)
    return v + 2.0 * (q[..., :1] * uv + cross(u, uv))


def axis_angle(axis, angle) -> np.ndarray:
    """Quaternions (..., 4) for rotations by `angle` (...) about the fixed unit `axis` (3,)."""
    angle = np.asarray(angle, dtype=np.float64)
    half = 0.5 * angle[..., None]
    return np.concatenate([np.cos(half), np.sin(half) * np.asarray(axis, dtype=np.float64)], -1)


def euler_xyz(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    """Quaternions for intrinsic rotations about x (pitch), then y (yaw), then z (roll)."""
    x, y, z = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (x, y, z)))
    return qmul(qmul(axis_angle((0, 1, 0), y), axis_angle((1, 0, 0), x)), axis_angle((0, 0, 1), z))


def identity(*shape: int) -> np.ndarray:
    q = np.zeros((*shape, 4))
    q[..., 0] = 1.0
    return q


def matrix_to_quat(m: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> quaternions (..., 4) (Shepperd's method)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    sq = np.stack([1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22,
                   1 - m00 - m11 + m22], -1).clip(0.0)
    d21, d02, d10 = m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]
    s10, s02, s21 = m[..., 1, 0] + m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 2, 1] + m[..., 1, 2]
    cands = np.stack([
        np.stack([sq[..., 0], d21, d02, d10], -1), np.stack([d21, sq[..., 1], s10, s02], -1),
        np.stack([d02, s10, sq[..., 2], s21], -1), np.stack([d10, s02, s21, sq[..., 3]], -1),
    ], -2)
    best = sq.argmax(-1)
    q = np.take_along_axis(cands, best[..., None, None], -2)[..., 0, :]
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def slerp(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Spherical interpolation of (..., 4) quaternions with weights w (...) in [0, 1]."""
    dot = (a * b).sum(-1, keepdims=True)
    b = np.where(dot < 0, -b, b)
    dot = np.abs(dot).clip(max=1.0)
    theta = np.arccos(dot)
    sin = np.sin(theta)
    w = np.asarray(w)[..., None]
    small = sin < 1e-6
    safe = np.where(small, 1.0, sin)
    wa = np.where(small, 1 - w, np.sin((1 - w) * theta) / safe)
    wb = np.where(small, w, np.sin(w * theta) / safe)
    q = wa * a + wb * b
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-9)


def _frame(bone: np.ndarray, hinge: np.ndarray) -> np.ndarray:
    """Orthonormal frames (..., 3, 3) with columns bone, hinge, bone x hinge."""
    hinge = _unit(hinge - (hinge * bone).sum(-1, keepdims=True) * bone)
    return np.stack([bone, hinge, cross(bone, hinge)], -1)


def two_bone_ik(root, off_a, off_b, target, pole, hinge_rest):
    """Global rotations of two-bone limbs (hip-knee-ankle or shoulder-elbow-wrist).

    root, target, pole: (..., l, 3) for l limbs; pole is where the middle joint should
    point. off_a, off_b, hinge_rest: (l, 3) rest offsets of the two bones and the limb's
    hinge axis in the rest pose. Targets out of reach are clamped (the limb points at them).
    Returns (Ba, Bb) (..., l, 4): rotations of bone a (root->middle) and b (middle->end).
    """
    la = np.linalg.norm(off_a, axis=-1, keepdims=True)
    lb = np.linalg.norm(off_b, axis=-1, keepdims=True)
    d = target - root
    dist = np.sqrt((d * d).sum(-1, keepdims=True))
    dhat = d / np.maximum(dist, 1e-9)
    dist = np.clip(dist, np.abs(la - lb) + 1e-4, (la + lb) * 0.9995)
    p_perp = _unit(pole - (pole * dhat).sum(-1, keepdims=True) * dhat)
    cos_a = ((la**2 + dist**2 - lb**2) / (2 * la * dist)).clip(-1, 1)
    a1 = cos_a * dhat + np.sqrt(1 - cos_a**2) * p_perp
    b1 = _unit(dist * dhat - la * a1)
    hinge = cross(p_perp, dhat)
    rest_a, rest_b = _frame(off_a / la, hinge_rest), _frame(off_b / lb, hinge_rest)
    ba = matrix_to_quat(_frame(a1, hinge) @ np.swapaxes(rest_a, -1, -2))
    bb = matrix_to_quat(_frame(b1, hinge) @ np.swapaxes(rest_b, -1, -2))
    return ba, bb


# ---------------------------------------------------------------- pose solving
@dataclass
class BodyTrack:
    """What an action specifies per frame, in the action's own frame (metres, y up).

    root: (t, 3) pelvis position; yaw: (t,) heading in radians about +y (0 faces +Z);
    pelvis: (t, 4) pelvis tilt relative to the heading; spine: (t, 3, 4) local rotations of
    the bones ending at spine1, spine2, spine3; neck: (t, 4).
    feet: (t, 2, 3) ankle targets (left, right); foot_rot: (t, 2, 4) global foot rotations;
    knee_pole: (t, 2, 3) where the knees point.
    wrists: (t, 2, 3) wrist targets in the chest frame; elbow_pole: (t, 2, 3) chest frame.
    """

    root: np.ndarray
    yaw: np.ndarray
    pelvis: np.ndarray
    spine: np.ndarray
    neck: np.ndarray
    feet: np.ndarray
    foot_rot: np.ndarray
    knee_pole: np.ndarray
    wrists: np.ndarray
    elbow_pole: np.ndarray

    @property
    def num_frames(self) -> int:
        return len(self.root)


# Limbs as (upper bone, lower bone, hinge axis): knees bend about +x, elbows about -x
# (the forearm comes forward).
_UPPER = REST_OFFSETS[[4, 5, 18, 19]]
_LOWER = REST_OFFSETS[[7, 8, 20, 21]]
_HINGES = np.array([[1.0, 0, 0], [1.0, 0, 0], [-1.0, 0, 0], [-1.0, 0, 0]])


def solve_pose(track: BodyTrack) -> np.ndarray:
    """Local joint quaternions (t, 22, 4) for a `BodyTrack`; q[0] includes the heading."""
    t = track.num_frames
    q = identity(t, 22)
    b0 = qmul(axis_angle((0, 1, 0), track.yaw), track.pelvis)
    q[:, 0] = b0
    q[:, 3], q[:, 6], q[:, 9] = track.spine[:, 0], track.spine[:, 1], track.spine[:, 2]
    q[:, 12] = track.neck
    b3 = qmul(b0, q[:, 3])
    b6 = qmul(b3, q[:, 6])
    b9 = qmul(b6, q[:, 9])
    p9 = track.root + qrot(b3, np.broadcast_to(REST_OFFSETS[3], (t, 3)))
    p9 = p9 + qrot(b6, np.broadcast_to(REST_OFFSETS[6], (t, 3)))
    p9 = p9 + qrot(b9, np.broadcast_to(REST_OFFSETS[9], (t, 3)))
    # All four limbs in one IK call: left leg, right leg, left arm, right arm.
    hips = track.root[:, None] + qrot(b0[:, None], np.broadcast_to(REST_OFFSETS[[1, 2]], (t, 2, 3)))
    shoulders = p9[:, None] + qrot(b9[:, None], np.broadcast_to(CHEST_SHOULDERS, (t, 2, 3)))
    wrists = p9[:, None] + qrot(b9[:, None], track.wrists)
    ba, bb = two_bone_ik(
        np.concatenate([hips, shoulders], 1), _UPPER, _LOWER,
        np.concatenate([track.feet, wrists], 1),
        np.concatenate([track.knee_pole, qrot(b9[:, None], track.elbow_pole)], 1), _HINGES)
    parent = np.concatenate([np.repeat(b0[:, None], 2, 1), np.repeat(b9[:, None], 2, 1)], 1)
    q[:, [4, 5, 18, 19]] = qmul(qinv(parent), ba)
    q[:, [7, 8, 20, 21]] = qmul(qinv(ba), bb)
    q[:, [10, 11]] = qmul(qinv(bb[:, :2]), track.foot_rot)
    return q


# Joints with several children whose bones the rig turns apart: the pelvis's spine1 bone
# (spine1 with the locomotion lean; the hips keep the pelvis's rotation) and spine3's neck
# bone (the neck turn; the collars keep the chest's rotation). Version 4 moves each turn to
# the next bone down the chain: (turned bone's joint, next joint).
BRANCH_TURNS = ((3, 6), (12, 15))


def rigid_branches(q: np.ndarray) -> np.ndarray:
    """Local quaternions (t, 22, 4) whose multi-child joints turn their children together
    (corpus version 4): the spine1 bone's lean moves to the spine2 bone and the neck bone's
    turn to the head bone, so that spine2 and the head point as before while spine1 and
    the neck stay where the pelvis and the chest put them, as the hips and the collars
    do. A hierarchy that turns a joint's children together (SMPL, BVH) can then follow
    the motion exactly; in versions 1-3 it cannot (up to 23 mm in arms-up motions)."""
    out = q.copy()
    for joint, child in BRANCH_TURNS:
        out[:, child] = qmul(q[:, joint], q[:, child])
        out[:, joint] = identity(len(q))
    return out
