"""Skeleton specifications: everything that differs between datasets, in one place.

A dataset is described by one `SkeletonSpec` (conventions rule 4), never by
`if dataset == ...` blocks. Joint order and the directional offsets follow the
HumanML3D processing tools so that features are interchangeable with the real data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class SkeletonSpec:
    name: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    # Unit direction of each bone in the rest pose (HumanML3D `raw_offsets`), used by the
    # inverse kinematics of the rotation features.
    raw_offsets: tuple[tuple[float, float, float], ...]
    # Unit direction of each bone in the rest pose of the skeleton that a BVH file carries
    # (`segmo.motion.skeleton_fit`): a T-pose, arms out along x and head up, which is what
    # animation tools and retargeting expect (the raw offsets hang the arms down).
    tpose_directions: tuple[tuple[float, float, float], ...]
    # Bone length of each joint to its parent (metres for t2m) of the reference subject that
    # joints are retargeted to. None: keep the subject's own proportions.
    reference_bone_lengths: tuple[float, ...] | None
    kinematic_chains: tuple[tuple[int, ...], ...]
    feet_left: tuple[int, int]  # ankle, toe
    feet_right: tuple[int, int]
    face_joints: tuple[int, int, int, int]  # right hip, left hip, right shoulder, left shoulder
    leg_joints: tuple[int, int]  # knee, ankle of one leg; their bone sets the scale
    mirror_pairs: tuple[tuple[int, int], ...]  # (left, right) joint pairs
    fps: float
    min_frames: int  # motions shorter than this are filtered out of a dataset
    max_frames: int  # ... and motions this long or longer (spec §2)
    unit: float = 1.0  # metres per data unit

    @property
    def num_joints(self) -> int:
        return len(self.parents)

    @property
    def feature_dim(self) -> int:
        """4 root + (J-1)*3 positions + (J-1)*6 rotations + J*3 velocities + 4 contacts."""
        j = self.num_joints
        return 4 + (j - 1) * 3 + (j - 1) * 6 + j * 3 + 4

    @property
    def rotation_parents(self) -> tuple[int, ...]:
        """Joint whose accumulated rotation each joint's local rotation is relative to, in
        the HumanML3D convention used by the rotation features: along each kinematic chain
        the previous joint, but the first joint after a chain's start is relative to the
        root (so in t2m the collars' rotations are relative to the pelvis, not to spine3,
        exactly as HumanML3D's Skeleton does). -1 for the root."""
        rot_parents = [-1] * self.num_joints
        for chain in self.kinematic_chains:
            rot_parents[chain[1]] = 0
            for previous, joint in zip(chain[1:-1], chain[2:]):
                rot_parents[joint] = previous
        return tuple(rot_parents)

    @property
    def mirror_permutation(self) -> tuple[int, ...]:
        perm = list(range(self.num_joints))
        for left, right in self.mirror_pairs:
            perm[left], perm[right] = right, left
        return tuple(perm)

    def feature_slices(self) -> dict[str, slice]:
        """Named parts of the feature vector (spec §2)."""
        j = self.num_joints
        ric = 4 + (j - 1) * 3
        rot = ric + (j - 1) * 6
        vel = rot + j * 3
        return {
            "root_angular_velocity": slice(0, 1),
            "root_linear_velocity": slice(1, 3),
            "root_height": slice(3, 4),
            "root": slice(0, 4),
            "positions": slice(4, ric),
            "rotations": slice(ric, rot),
            "velocities": slice(rot, vel),
            "contacts": slice(vel, vel + 4),
        }


T2M = SkeletonSpec(
    name="t2m",
    joint_names=(
        "pelvis", "left_hip", "right_hip", "spine1", "left_knee", "right_knee", "spine2",
        "left_ankle", "right_ankle", "spine3", "left_foot", "right_foot", "neck",
        "left_collar", "right_collar", "head", "left_shoulder", "right_shoulder",
        "left_elbow", "right_elbow", "left_wrist", "right_wrist",
    ),
    parents=(-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19),
    raw_offsets=(
        (0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, -1, 0), (0, 1, 0),
        (0, -1, 0), (0, -1, 0), (0, 1, 0), (0, 0, 1), (0, 0, 1), (0, 1, 0), (1, 0, 0),
        (-1, 0, 0), (0, 0, 1), (0, -1, 0), (0, -1, 0), (0, -1, 0), (0, -1, 0), (0, -1, 0),
        (0, -1, 0),
    ),
    tpose_directions=(  # raw_offsets but shoulders, elbows, wrists along their collar; head up
        (0, 0, 0), (1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, -1, 0), (0, 1, 0),
        (0, -1, 0), (0, -1, 0), (0, 1, 0), (0, 0, 1), (0, 0, 1), (0, 1, 0), (1, 0, 0),
        (-1, 0, 0), (0, 1, 0), (1, 0, 0), (-1, 0, 0), (1, 0, 0), (-1, 0, 0), (1, 0, 0),
        (-1, 0, 0),
    ),
    reference_bone_lengths=(
        0.0, 0.1031, 0.1099, 0.1316, 0.3936, 0.3902, 0.1432, 0.4324, 0.4256, 0.0574, 0.1434,
        0.1494, 0.2194, 0.1375, 0.1434, 0.1030, 0.1316, 0.1230, 0.2568, 0.2631, 0.2660, 0.2699,
    ),
    kinematic_chains=(
        (0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15),
        (9, 14, 17, 19, 21), (9, 13, 16, 18, 20),
    ),
    feet_left=(7, 10),
    feet_right=(8, 11),
    face_joints=(2, 1, 17, 16),
    leg_joints=(5, 8),
    mirror_pairs=((1, 2), (4, 5), (7, 8), (10, 11), (13, 14), (16, 17), (18, 19), (20, 21)),
    fps=20.0,
    min_frames=40,
    max_frames=200,
)

KIT = SkeletonSpec(
    name="kit",
    joint_names=(
        "root", "torso", "chest", "neck", "head", "right_shoulder", "right_elbow",
        "right_wrist", "left_shoulder", "left_elbow", "left_wrist", "right_hip",
        "right_knee", "right_ankle", "right_heel", "right_toe", "left_hip", "left_knee",
        "left_ankle", "left_heel", "left_toe",
    ),
    parents=(-1, 0, 1, 2, 3, 3, 5, 6, 3, 8, 9, 0, 11, 12, 13, 14, 0, 16, 17, 18, 19),
    raw_offsets=(
        (0, 0, 0), (0, 1, 0), (0, 1, 0), (0, 1, 0), (0, 1, 0), (1, 0, 0), (0, -1, 0),
        (0, -1, 0), (-1, 0, 0), (0, -1, 0), (0, -1, 0), (1, 0, 0), (0, -1, 0), (0, -1, 0),
        (0, 0, 1), (0, 0, 1), (-1, 0, 0), (0, -1, 0), (0, -1, 0), (0, 0, 1), (0, 0, 1),
    ),
    tpose_directions=(  # raw_offsets but elbows and wrists along their shoulder
        (0, 0, 0), (0, 1, 0), (0, 1, 0), (0, 1, 0), (0, 1, 0), (1, 0, 0), (1, 0, 0),
        (1, 0, 0), (-1, 0, 0), (-1, 0, 0), (-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, -1, 0),
        (0, 0, 1), (0, 0, 1), (-1, 0, 0), (0, -1, 0), (0, -1, 0), (0, 0, 1), (0, 0, 1),
    ),
    reference_bone_lengths=None,
    kinematic_chains=(
        (0, 11, 12, 13, 14, 15), (0, 16, 17, 18, 19, 20), (0, 1, 2, 3, 4),
        (3, 5, 6, 7), (3, 8, 9, 10),
    ),
    feet_left=(19, 20),
    feet_right=(14, 15),
    face_joints=(11, 16, 5, 8),
    leg_joints=(17, 18),
    mirror_pairs=((8, 5), (9, 6), (10, 7), (16, 11), (17, 12), (18, 13), (19, 14), (20, 15)),
    fps=12.5,
    min_frames=24,
    max_frames=200,
    unit=0.001,  # KIT-ML joints are stored in millimetres
)

SKELETONS: dict[str, SkeletonSpec] = {"t2m": T2M, "kit": KIT}
# The names, as the type of a task's `skeleton` argument (the CLI offers exactly these).
SkeletonName = Literal["t2m", "kit"]


def get_skeleton(skeleton: str | SkeletonSpec) -> SkeletonSpec:
    """Look a skeleton up by name ("t2m" or "kit"); a spec passes through unchanged."""
    if isinstance(skeleton, SkeletonSpec):
        return skeleton
    try:
        return SKELETONS[skeleton]
    except KeyError:
        raise ValueError(f"unknown skeleton {skeleton!r}; expected one of {sorted(SKELETONS)}") from None
