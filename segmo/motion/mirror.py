"""Left/right mirroring of joints and of feature vectors (HumanML3D's `M` copies).

Mirroring reflects x (x -> -x) and swaps each left joint with its right partner. On the
feature vector this is exact except for the retargeting step of `joints_to_features`:
the reference skeleton's left and right bones differ by a few millimetres, so
`joints_to_features(mirror_joints(j))` re-scales bones that `mirror_features` keeps.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from segmo.motion.skeleton import SkeletonSpec, get_skeleton

__all__ = ["mirror_joints", "mirror_features"]


def _take(x: Any, index: list[int], axis: int) -> Any:
    if isinstance(x, np.ndarray):
        return np.take(x, index, axis=axis)
    if isinstance(x, torch.Tensor):
        return x.index_select(axis, torch.tensor(index, device=x.device))
    raise TypeError(f"mirror: expected a numpy array or a torch tensor, got {type(x).__name__}")


def _sign(x: Any, signs: list[float]) -> Any:
    if isinstance(x, np.ndarray):
        return np.asarray(signs, dtype=x.dtype)
    return torch.tensor(signs, dtype=x.dtype, device=x.device)


def mirror_joints(joints: Any, skeleton: str | SkeletonSpec = "t2m") -> Any:
    """Joints (..., j, 3) -> mirrored joints (..., j, 3): x negated, left <-> right."""
    spec = get_skeleton(skeleton)
    if joints.ndim < 2 or tuple(joints.shape[-2:]) != (spec.num_joints, 3):
        raise ValueError(
            f"mirror_joints: joints must be (..., {spec.num_joints}, 3) for skeleton "
            f"{spec.name!r}, got {tuple(joints.shape)}"
        )
    swapped = _take(joints, list(spec.mirror_permutation), axis=joints.ndim - 2)
    return swapped * _sign(joints, [-1.0, 1.0, 1.0])


def _feature_permutation_and_signs(spec: SkeletonSpec) -> tuple[list[int], list[float]]:
    """Index map and sign per output dimension: mirrored[..., k] = sign[k] * x[..., index[k]]."""
    j = spec.num_joints
    perm = spec.mirror_permutation
    parts = spec.feature_slices()
    index: list[int] = []
    signs: list[float] = []

    def joint_block(start: int, joints: range, width: int, block_signs: list[float]) -> None:
        first = joints.start
        for joint in joints:
            source = start + (perm[joint] - first) * width
            index.extend(range(source, source + width))
            signs.extend(block_signs)

    # Heading is a rotation about y: the reflection reverses it; lateral velocity flips.
    index += [0, 1, 2, 3]
    signs += [-1.0, -1.0, 1.0, 1.0]
    joint_block(parts["positions"].start, range(1, j), 3, [-1.0, 1.0, 1.0])
    # 6-D = first two columns of R; the reflected rotation is M R M with M = diag(-1, 1, 1),
    # which negates R[1,0], R[2,0] (column 0) and R[0,1] (column 1).
    joint_block(parts["rotations"].start, range(1, j), 6, [1.0, -1.0, -1.0, -1.0, 1.0, 1.0])
    joint_block(parts["velocities"].start, range(0, j), 3, [-1.0, 1.0, 1.0])
    contacts = parts["contacts"].start
    index += [contacts + 2, contacts + 3, contacts, contacts + 1]  # left feet <-> right feet
    signs += [1.0] * 4
    return index, signs


def mirror_features(features: Any, skeleton: str | SkeletonSpec = "t2m") -> Any:
    """Features (..., d), not z-scored -> features of the mirrored motion (..., d).

    To mirror z-scored features, de-normalise first: the statistics are not symmetric.
    """
    spec = get_skeleton(skeleton)
    if features.ndim < 1 or features.shape[-1] != spec.feature_dim:
        raise ValueError(
            f"mirror_features: features must be (..., {spec.feature_dim}) for skeleton "
            f"{spec.name!r}, got {tuple(features.shape)}"
        )
    index, signs = _feature_permutation_and_signs(spec)
    return _take(features, index, axis=features.ndim - 1) * _sign(features, signs)
