"""Forward and inverse kinematics on joint positions, batched over leading dimensions.

Convention (HumanML3D's `Skeleton`): joint c's local quaternion `q[c]` rotates the bone
that ends at c, i.e. the offset from parent(c) to c. Bone rotations accumulate along
`rotation_parents`:

    G[0] = q[0];  G[c] = G[rotation_parents[c]] * q[c]
    p[0] = root;  p[c] = p[parents[c]] + G[c] rotates offsets[c]

With `rotation_parents = parents` (the default) this is an ordinary tree in which rotating
q[c] turns the bone parent(c)->c and everything below it. The 263-d features use
`skeleton.rotation_parents`, HumanML3D's chain convention, where the first bone of every
kinematic chain is relative to the root (t2m: the collars ignore the spine's rotation).

Example, bend the left knee of the t2m rest pose by 90 degrees (the shin is the bone that
ends at the left ankle, joint 7):

    q = identity_quat(22); q[7] = axis_angle_to_quat(torch.tensor([1.5708, 0.0, 0.0]))
    joints = forward_kinematics(q, torch.tensor([0, 0.9, 0]), rest_offsets(T2M), T2M.parents)
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from segmo.motion.quaternion import identity_quat, qbetween, qinv, qmul, qrot
from segmo.motion.skeleton import SkeletonSpec, get_skeleton

__all__ = [
    "rest_offsets", "bone_lengths", "forward_kinematics", "inverse_kinematics",
    "facing_direction", "gaussian_filter1d",
]


def rest_offsets(
    skeleton: str | SkeletonSpec,
    lengths: Tensor | Sequence[float] | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """Rest-pose bone offsets (j, 3) = raw_offsets direction x bone length.

    lengths: (..., j) bone lengths; default the skeleton's reference_bone_lengths.
    Returns (..., j, 3); the root's offset is zero.
    """
    spec = get_skeleton(skeleton)
    if lengths is None:
        if spec.reference_bone_lengths is None:
            raise ValueError(
                f"rest_offsets: skeleton {spec.name!r} has no reference_bone_lengths; "
                "pass lengths= (e.g. bone_lengths(joints[0], skeleton.parents))"
            )
        lengths = spec.reference_bone_lengths
    lengths = torch.as_tensor(lengths, dtype=dtype)
    if lengths.shape[-1] != spec.num_joints:
        raise ValueError(
            f"rest_offsets: lengths must end with {spec.num_joints} joints, got {tuple(lengths.shape)}"
        )
    directions = torch.tensor(spec.raw_offsets, dtype=dtype, device=lengths.device)
    return directions * lengths[..., None]


def bone_lengths(positions: Tensor, parents: Sequence[int]) -> Tensor:
    """Length of each joint's bone to its parent: (..., j, 3) -> (..., j), root 0."""
    parent_index = torch.tensor([max(p, 0) for p in parents], device=positions.device)
    lengths = (positions - positions[..., parent_index, :]).norm(dim=-1)
    lengths[..., 0] = 0.0
    return lengths


def _check_order(parents: Sequence[int], name: str) -> None:
    if parents[0] != -1 or any(not 0 <= p < c for c, p in enumerate(parents) if c > 0):
        raise ValueError(
            f"forward_kinematics: {name} must start with -1 and list every parent before "
            f"its child, got {tuple(parents)}"
        )


def forward_kinematics(
    local_quats: Tensor,
    root_positions: Tensor,
    offsets: Tensor,
    parents: Sequence[int],
    rotation_parents: Sequence[int] | None = None,
) -> Tensor:
    """Joint positions from local bone rotations (convention in the module docstring).

    local_quats: (..., j, 4) unit quaternions (w, x, y, z); q[0] is the root rotation.
    root_positions: (..., 3).
    offsets: (j, 3) or (..., j, 3) rest-pose bone offsets (see `rest_offsets`).
    Returns positions (..., j, 3).
    """
    rotation_parents = parents if rotation_parents is None else rotation_parents
    _check_order(parents, "parents")
    _check_order(rotation_parents, "rotation_parents")
    j = len(parents)
    if local_quats.shape[-2:] != (j, 4):
        raise ValueError(
            f"forward_kinematics: local_quats must be (..., {j}, 4), got {tuple(local_quats.shape)}"
        )
    if root_positions.shape[-1] != 3 or offsets.shape[-2:] != (j, 3):
        raise ValueError(
            "forward_kinematics: root_positions must be (..., 3) and offsets (j, 3), got "
            f"{tuple(root_positions.shape)} and {tuple(offsets.shape)}"
        )
    offsets = offsets.to(local_quats)
    rotations: list[Tensor] = [local_quats[..., 0, :]]
    positions: list[Tensor] = [root_positions.to(local_quats).expand(*local_quats.shape[:-2], 3)]
    for c in range(1, j):
        rotations.append(qmul(rotations[rotation_parents[c]], local_quats[..., c, :]))
        positions.append(positions[parents[c]] + qrot(rotations[c], offsets[..., c, :]))
    return torch.stack(positions, dim=-2)


def gaussian_filter1d(x: Tensor, sigma: float, dim: int = 0, truncate: float = 4.0) -> Tensor:
    """Gaussian smoothing along `dim` with edge replication, like
    `scipy.ndimage.gaussian_filter1d(x, sigma, axis=dim, mode="nearest")`."""
    radius = int(truncate * sigma + 0.5)
    steps = torch.arange(-radius, radius + 1, device=x.device)
    weights = torch.exp(-0.5 * (steps.to(x.dtype) / sigma) ** 2)
    weights = weights / weights.sum()
    x = x.movedim(dim, -1)
    t = x.shape[-1]
    index = (torch.arange(t, device=x.device)[:, None] + steps[None, :]).clamp(0, t - 1)
    smoothed = (x[..., index] * weights).sum(-1)  # (..., t, 2r+1) -> (..., t)
    return smoothed.movedim(-1, dim)


def facing_direction(
    positions: Tensor,
    face_joints: Sequence[int],
    hml_ik_quirk: bool = False,
    normalize: bool = True,
) -> Tensor:
    """Unit horizontal forward direction (..., 3) of poses (..., j, 3), y up.

    face_joints = (right hip, left hip, right shoulder, left shoulder); forward is
    y x (right - left). `hml_ik_quirk` reproduces HumanML3D's `inverse_kinematics_np`,
    which unpacks the hips in the opposite order (hip term sign flipped) - needed to
    reproduce the dataset's features exactly. normalize=False keeps y x unit(across),
    whose length shrinks when the across vector tilts (HumanML3D smooths that one).
    """
    r_hip, l_hip, r_shoulder, l_shoulder = face_joints
    hips = positions[..., r_hip, :] - positions[..., l_hip, :]
    across = (-hips if hml_ik_quirk else hips) + (
        positions[..., r_shoulder, :] - positions[..., l_shoulder, :]
    )
    across = across / across.norm(dim=-1, keepdim=True)
    up = torch.zeros_like(across)
    up[..., 1] = 1.0
    forward = torch.linalg.cross(up, across, dim=-1)
    return forward / forward.norm(dim=-1, keepdim=True) if normalize else forward


def inverse_kinematics(
    positions: Tensor,
    skeleton: str | SkeletonSpec = "t2m",
    smooth_forward: bool = False,
    rotation_parents: Sequence[int] | None = None,
    hml_ik_quirk: bool = True,
) -> Tensor:
    """Local quaternions from joint positions, as HumanML3D's `inverse_kinematics_np`.

    positions: (..., t, j, 3), y up. Each bone's global rotation is the shortest arc from
    its raw_offsets direction to the observed bone direction (twist is unobservable and
    set to zero). q[0] is HumanML3D's root quaternion: the rotation about y that turns the
    body's forward direction to +Z (world -> body heading, identity at frame 0);
    `smooth_forward` smooths the forward direction over time (Gaussian, sigma 20 frames).
    rotation_parents: default the skeleton's parents; pass `skeleton.rotation_parents`
    for the feature convention. `forward_kinematics` with the same rotation_parents and
    offsets of the observed bone lengths reproduces the positions.
    Returns (..., t, j, 4).
    """
    spec = get_skeleton(skeleton)
    rotation_parents = spec.parents if rotation_parents is None else rotation_parents
    j = spec.num_joints
    if positions.dim() < 3 or positions.shape[-2:] != (j, 3):
        raise ValueError(
            f"inverse_kinematics: positions must be (..., t, {j}, 3) for skeleton "
            f"{spec.name!r}, got {tuple(positions.shape)}"
        )
    forward = facing_direction(positions, spec.face_joints, hml_ik_quirk, normalize=False)
    if smooth_forward:  # (..., t, 3), smoothed before normalising as HumanML3D does
        forward = gaussian_filter1d(forward, 20.0, dim=-2)
    forward = forward / forward.norm(dim=-1, keepdim=True)
    target = torch.zeros_like(forward)
    target[..., 2] = 1.0
    root_quat = qbetween(forward, target)
    root_quat[..., 0, :] = identity_quat(dtype=positions.dtype, device=positions.device)

    raw = torch.tensor(spec.raw_offsets, dtype=positions.dtype, device=positions.device)
    parent_index = torch.tensor([max(p, 0) for p in spec.parents], device=positions.device)
    bones = positions - positions[..., parent_index, :]
    bones = bones / bones.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    bone_rot = qbetween(raw[1:].expand_as(bones[..., 1:, :]), bones[..., 1:, :])
    global_rot = torch.cat([root_quat[..., None, :], bone_rot], dim=-2)  # (..., t, j, 4)
    rot_parent_index = torch.tensor([max(p, 0) for p in rotation_parents], device=positions.device)
    local = qmul(qinv(global_rot[..., rot_parent_index, :]), global_rot)
    local[..., 0, :] = root_quat
    return local
