"""Export joint positions to BVH (Biovision hierarchy) for Blender, MotionBuilder, etc.

The hierarchy is the skeleton's own joint tree (t2m: the 22 SMPL joints). Each joint's
rotation turns all of its child bones (the BVH convention), so a joint with several
children (pelvis, spine3) gets the rotation that best maps its rest child offsets onto
the observed ones (Kabsch); for recorded or HumanML3D-processed motions the children of
a joint keep their relative geometry, and the fit is exact. Single-child joints use the
shortest-arc rotation (twist about a bone cannot be seen in positions and is zero).

Rest pose: bones along the skeleton's raw_offsets directions (a T-pose for t2m) with the
motion's mean bone lengths, except the children of multi-child joints, whose offsets
come from frame 0 (heading removed) so that the hips and collars keep their real layout.

Channels: the root has `Xposition Yposition Zposition Zrotation Yrotation Xrotation`,
every other joint `Zrotation Yrotation Xrotation`, in degrees; the local rotation is
R = Rz(z) @ Ry(y) @ Rx(x), and a child's position is parent + R_parent_global @ offset.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from segmo.motion.kinematics import bone_lengths, facing_direction
from segmo.motion.quaternion import matrix_to_euler, qbetween, quat_to_matrix
from segmo.motion.skeleton import SkeletonSpec, get_skeleton

__all__ = ["joints_to_bvh"]

END_SITE_LENGTH = 0.05  # metres: the nominal tip drawn after leaf joints


def _kabsch(rest: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """Rotations (t, 3, 3) minimising sum_k |R rest_k - observed_t,k|^2.
    rest: (k, 3); observed: (t, k, 3)."""
    h = np.einsum("ki,tkj->tij", rest, observed)  # (t, 3, 3) = sum rest_k observed_k^T
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
    fix = np.ones((len(h), 3))
    fix[:, 2] = d
    return np.swapaxes(vt, 1, 2) @ (fix[:, :, None] * np.swapaxes(u, 1, 2))


def _rest_offsets(positions: np.ndarray, spec: SkeletonSpec, children: list[list[int]]) -> np.ndarray:
    lengths = bone_lengths(torch.from_numpy(positions), spec.parents).mean(0).numpy()
    offsets = np.asarray(spec.raw_offsets, dtype=np.float64) * lengths[:, None]
    forward = facing_direction(torch.from_numpy(positions[0]), spec.face_joints)
    to_front = qbetween(forward, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    frame0 = (quat_to_matrix(to_front).numpy() @ (positions[0] - positions[0, list(np.maximum(spec.parents, 0))]).T).T
    for kids in children:
        if len(kids) > 1:
            for c in kids:
                offsets[c] = frame0[c] / np.linalg.norm(frame0[c]) * lengths[c]
    return offsets


def _global_rotations(positions: np.ndarray, offsets: np.ndarray, spec: SkeletonSpec,
                      children: list[list[int]]) -> np.ndarray:
    """(t, j, 3, 3) world rotation of each joint (rotating its child bones)."""
    t, j = positions.shape[:2]
    rotations = np.empty((t, j, 3, 3))
    for p in range(j):
        kids = children[p]
        if not kids:  # a leaf turns nothing: keep its parent's rotation
            rotations[:, p] = rotations[:, spec.parents[p]]
            continue
        observed = positions[:, kids] - positions[:, p : p + 1]  # (t, k, 3)
        if len(kids) == 1:
            q = qbetween(torch.from_numpy(np.broadcast_to(offsets[kids[0]], observed[:, 0].shape).copy()),
                         torch.from_numpy(observed[:, 0]))
            rotations[:, p] = quat_to_matrix(q).numpy()
        else:
            rotations[:, p] = _kabsch(offsets[kids], observed)
    return rotations


def joints_to_bvh(
    joints: Any,
    path: str | Path,
    fps: float | None = None,
    skeleton: str | SkeletonSpec = "t2m",
    scale: float = 1.0,
) -> Path:
    """Write joints (t, j, 3) (numpy or torch, y up) as a BVH file and return its path.

    fps: frame rate, default the skeleton's (t2m: 20). scale: multiplies all lengths
    (1 keeps the data units, metres for t2m; 100 gives centimetres).
    """
    spec = get_skeleton(skeleton)
    if hasattr(joints, "detach"):
        joints = joints.detach().cpu().numpy()
    positions = np.asarray(joints, dtype=np.float64)
    if positions.ndim != 3 or positions.shape[1:] != (spec.num_joints, 3) or len(positions) < 1:
        raise ValueError(
            f"joints_to_bvh: joints must be (t, {spec.num_joints}, 3) for skeleton {spec.name!r}, "
            f"got {positions.shape}"
        )
    fps = spec.fps if fps is None else fps
    j = spec.num_joints
    children: list[list[int]] = [[] for _ in range(j)]
    for c, p in enumerate(spec.parents):
        if p >= 0:
            children[p].append(c)

    offsets = _rest_offsets(positions, spec, children)
    world = _global_rotations(positions, offsets, spec, children)
    parent_world = world[:, [max(p, 0) for p in spec.parents]]
    local = np.swapaxes(parent_world, -1, -2) @ world
    local[:, 0] = world[:, 0]
    angles = np.degrees(matrix_to_euler(torch.from_numpy(local), "ZYX").numpy())  # (t, j, 3)

    lines = ["HIERARCHY"]

    def write(joint: int, depth: int) -> None:
        pad = "  " * depth
        name = spec.joint_names[joint]
        offset = offsets[joint] * scale
        lines.append(f"{pad}{'ROOT' if joint == 0 else 'JOINT'} {name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}  OFFSET {offset[0]:.6f} {offset[1]:.6f} {offset[2]:.6f}")
        if joint == 0:
            lines.append(f"{pad}  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation")
        else:
            lines.append(f"{pad}  CHANNELS 3 Zrotation Yrotation Xrotation")
        for child in children[joint]:
            write(child, depth + 1)
        if not children[joint]:
            tip = np.asarray(spec.raw_offsets[joint], dtype=np.float64) * END_SITE_LENGTH / spec.unit * scale
            lines.append(f"{pad}  End Site")
            lines.append(f"{pad}  {{")
            lines.append(f"{pad}    OFFSET {tip[0]:.6f} {tip[1]:.6f} {tip[2]:.6f}")
            lines.append(f"{pad}  }}")
        lines.append(f"{pad}}}")

    write(0, 0)
    lines += ["MOTION", f"Frames: {len(positions)}", f"Frame Time: {1.0 / fps:.6f}"]
    order = _depth_first(children)
    for frame in range(len(positions)):
        values = list(positions[frame, 0] * scale)
        for joint in order:
            values.extend(angles[frame, joint])
        lines.append(" ".join(f"{v:.6f}" for v in values))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
    return path


def _depth_first(children: list[list[int]]) -> list[int]:
    """Joint order of the MOTION columns: the order joints appear in the hierarchy."""
    order, stack = [], [0]
    while stack:
        joint = stack.pop()
        order.append(joint)
        stack.extend(reversed(children[joint]))
    return order
