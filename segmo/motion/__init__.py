"""Motion representation: skeleton specs, quaternions, kinematics, joints <-> features.

    >>> from segmo.motion import joints_to_features, features_to_joints
    >>> features = joints_to_features(joints)          # (t, 22, 3) -> (t - 1, 263)
    >>> recovered = features_to_joints(features)       # (t - 1, 263) -> (t - 1, 22, 3)
"""

from segmo.motion.features import (
    features_to_joints,
    joint_errors,
    joints_to_features,
    process_joints,
)
from segmo.motion.kinematics import (
    bone_lengths,
    forward_kinematics,
    inverse_kinematics,
    rest_offsets,
)
from segmo.motion.mirror import mirror_features, mirror_joints
from segmo.motion.skeleton import KIT, T2M, SkeletonSpec, get_skeleton

__all__ = [
    "SkeletonSpec", "get_skeleton", "T2M", "KIT",
    "joints_to_features", "features_to_joints", "process_joints", "joint_errors",
    "forward_kinematics", "inverse_kinematics", "rest_offsets", "bone_lengths",
    "mirror_joints", "mirror_features",
]
