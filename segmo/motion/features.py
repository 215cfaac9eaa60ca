"""Joint positions <-> the HumanML3D motion feature vector (spec section 2).

`joints_to_features` is HumanML3D's `process_file` (motion_representation notebook):
retarget to the reference skeleton, put on the floor, centre the root's XZ at frame 0,
turn frame 0 to face +Z, then extract

    [root angular velocity (1), root linear velocity xz (2), root height (1),
     root-relative positions (j-1)*3, 6-D rotations (j-1)*6, local velocities j*3,
     foot contacts (left ankle, left toe, right ankle, right toe)]

for t-1 frames. `features_to_joints` is its inverse on the position part
(HumanML3D's `recover_from_ric`). Both accept numpy arrays or torch tensors with any
leading batch dimensions and return the type they were given; the arithmetic runs in
float64 because the root trajectory is a cumulative sum.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from segmo.motion.kinematics import (
    bone_lengths,
    facing_direction,
    forward_kinematics,
    inverse_kinematics,
    rest_offsets,
)
from segmo.motion.quaternion import qbetween, qinv, qmul, qrot, quat_to_cont6d
from segmo.motion.skeleton import SkeletonSpec, get_skeleton

__all__ = ["joints_to_features", "features_to_joints", "process_joints", "FOOT_CONTACT_THRESHOLD"]

# Squared per-frame displacement (m^2) under which a foot joint counts as in contact.
FOOT_CONTACT_THRESHOLD = 0.002


def _as_float64(x: Any, name: str) -> tuple[Tensor, Any]:
    """-> (float64 tensor, how to convert back)."""
    if isinstance(x, np.ndarray):
        dtype = x.dtype if np.issubdtype(x.dtype, np.floating) else np.float32
        return torch.from_numpy(np.array(x, dtype=np.float64)), lambda y: y.numpy().astype(dtype)
    if isinstance(x, Tensor):
        dtype = x.dtype if x.is_floating_point() else torch.float32
        return x.to(torch.float64), lambda y: y.to(dtype)
    raise TypeError(f"{name} must be a numpy array or a torch tensor, got {type(x).__name__}")


def _check_joints(joints: Tensor, spec: SkeletonSpec, caller: str) -> None:
    if joints.dim() < 3 or joints.shape[-2:] != (spec.num_joints, 3):
        raise ValueError(
            f"{caller}: joints must be (t, {spec.num_joints}, 3) or (b, t, {spec.num_joints}, 3) "
            f"for skeleton {spec.name!r}, got {tuple(joints.shape)}"
        )


def _retarget(positions: Tensor, spec: SkeletonSpec) -> Tensor:
    """HumanML3D `uniform_skeleton`: same bone directions, reference bone lengths, root
    trajectory scaled by the ratio of leg lengths. (..., t, j, 3) -> same."""
    target = torch.tensor(spec.reference_bone_lengths, dtype=positions.dtype)
    source = bone_lengths(positions[..., 0, :, :], spec.parents)  # (..., j) from frame 0
    knee, ankle = spec.leg_joints
    scale = (target[knee] + target[ankle]) / (source[..., knee] + source[..., ankle])
    quats = inverse_kinematics(positions, spec)
    root = positions[..., 0, :] * scale[..., None, None]
    return forward_kinematics(quats, root, rest_offsets(spec, dtype=positions.dtype), spec.parents)


def _process(positions: Tensor, spec: SkeletonSpec) -> Tensor:
    if spec.reference_bone_lengths is not None:
        positions = _retarget(positions, spec)
    # On the floor: the lowest joint of the whole clip at y = 0.
    floor = positions[..., 1].amin(dim=(-2, -1))
    positions = positions - torch.stack(
        [torch.zeros_like(floor), floor, torch.zeros_like(floor)], -1
    )[..., None, None, :]
    # Root XZ of frame 0 at the origin.
    start = positions[..., 0, 0, :] * positions.new_tensor([1.0, 0.0, 1.0])
    positions = positions - start[..., None, None, :]
    # Frame 0 faces +Z.
    forward = facing_direction(positions[..., 0, :, :], spec.face_joints)
    target = torch.zeros_like(forward)
    target[..., 2] = 1.0
    return qrot(qbetween(forward, target)[..., None, None, :], positions)


def process_joints(joints: Any, skeleton: str | SkeletonSpec = "t2m") -> Any:
    """Canonicalise joints (..., t, j, 3) as HumanML3D does before feature extraction:
    retarget (skeletons with reference_bone_lengths), floor, centre, face +Z."""
    spec = get_skeleton(skeleton)
    positions, back = _as_float64(joints, "process_joints: joints")
    _check_joints(positions, spec, "process_joints")
    return back(_process(positions, spec))


def joints_to_features(
    joints: Any, skeleton: str | SkeletonSpec = "t2m", feet_threshold: float | None = None
) -> Any:
    """Joint positions (..., t, j, 3), y up, in the skeleton's units -> features (..., t-1, d).

    feet_threshold: squared displacement per frame below which a foot joint is in
    contact, in squared data units; default 0.002 m^2 converted with `skeleton.unit`.
    """
    spec = get_skeleton(skeleton)
    positions, back = _as_float64(joints, "joints_to_features: joints")
    _check_joints(positions, spec, "joints_to_features")
    if positions.shape[-3] < 2:
        raise ValueError(f"joints_to_features: need at least 2 frames, got {positions.shape[-3]}")
    if feet_threshold is None:
        feet_threshold = FOOT_CONTACT_THRESHOLD / spec.unit**2
    positions = _process(positions, spec)  # (..., t, j, 3)
    j = spec.num_joints

    displacement = ((positions[..., 1:, :, :] - positions[..., :-1, :, :]) ** 2).sum(-1)
    feet = list(spec.feet_left) + list(spec.feet_right)
    contacts = (displacement[..., feet] < feet_threshold).to(positions.dtype)  # (..., t-1, 4)

    quats = inverse_kinematics(
        positions, spec, smooth_forward=True, rotation_parents=spec.rotation_parents
    )  # (..., t, j, 4)
    r_rot = quats[..., 0, :]  # world -> body heading, (..., t, 4)
    root_velocity = qrot(r_rot[..., 1:, :], positions[..., 1:, 0, :] - positions[..., :-1, 0, :])
    # HumanML3D stores asin of the y component: half the heading change per frame.
    r_velocity = qmul(r_rot[..., 1:, :], qinv(r_rot[..., :-1, :]))
    angular = torch.asin(r_velocity[..., 2:3].clamp(-1.0, 1.0))

    local = positions.clone()
    local[..., 0] -= positions[..., 0:1, 0]
    local[..., 2] -= positions[..., 0:1, 2]
    ric = qrot(r_rot[..., None, :], local)  # (..., t, j, 3)
    velocities = qrot(
        r_rot[..., :-1, None, :], positions[..., 1:, :, :] - positions[..., :-1, :, :]
    )
    rotations = quat_to_cont6d(quats[..., 1:, :])  # (..., t, j-1, 6)

    lead = positions.shape[:-3]
    t = positions.shape[-3] - 1
    features = torch.cat(
        [
            angular,
            root_velocity[..., [0, 2]],
            ric[..., :-1, 0, 1:2],
            ric[..., :-1, 1:, :].reshape(*lead, t, (j - 1) * 3),
            rotations[..., :-1, :, :].reshape(*lead, t, (j - 1) * 6),
            velocities.reshape(*lead, t, j * 3),
            contacts,
        ],
        dim=-1,
    )
    return back(features)


def features_to_joints(features: Any, skeleton: str | SkeletonSpec = "t2m") -> Any:
    """Features (..., t, d) -> joint positions (..., t, j, 3) from the root and
    root-relative position parts (HumanML3D `recover_from_ric`). Differentiable for
    tensors. Features must be de-normalised (not z-scored)."""
    spec = get_skeleton(skeleton)
    data, back = _as_float64(features, "features_to_joints: features")
    if data.dim() < 2 or data.shape[-1] != spec.feature_dim:
        raise ValueError(
            f"features_to_joints: features must be (..., t, {spec.feature_dim}) for skeleton "
            f"{spec.name!r}, got {tuple(data.shape)}"
        )
    j = spec.num_joints
    # Heading: cumulative (half-)angle, zero at frame 0.
    angle = torch.cumsum(torch.cat([torch.zeros_like(data[..., :1, 0]), data[..., :-1, 0]], -1), -1)
    zeros = torch.zeros_like(angle)
    r_rot = torch.stack([torch.cos(angle), zeros, torch.sin(angle), zeros], dim=-1)  # (..., t, 4)
    step = torch.zeros(*data.shape[:-1], 3, dtype=data.dtype, device=data.device)
    step[..., 1:, 0] = data[..., :-1, 1]
    step[..., 1:, 2] = data[..., :-1, 2]
    root = torch.cumsum(qrot(qinv(r_rot), step), dim=-2)
    root = torch.cat([root[..., :1], data[..., 3:4], root[..., 2:3]], dim=-1)

    ric = data[..., 4 : 4 + (j - 1) * 3].reshape(*data.shape[:-1], j - 1, 3)
    ric = qrot(qinv(r_rot)[..., None, :], ric)
    ric = ric + torch.stack([root[..., 0], zeros, root[..., 2]], dim=-1)[..., None, :]
    return back(torch.cat([root[..., None, :], ric], dim=-2))


def joint_errors(real: Tensor, fake: Tensor) -> tuple[Tensor, Tensor]:
    """Per-frame mean joint distance of two joint sequences (..., t, j, 3), in the joints'
    unit, as two (..., t) tensors: root-aligned (each frame's root joints put on each other
    first: the pose error MoMask reports as MPJPE) and global (the root trajectory, which
    the features integrate from velocities, so its drift counts too)."""
    aligned = (real - real[..., :1, :]) - (fake - fake[..., :1, :])
    return aligned.norm(dim=-1).mean(-1), (real - fake).norm(dim=-1).mean(-1)
