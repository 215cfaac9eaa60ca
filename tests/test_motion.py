"""Tests of segmo.motion: quaternions, kinematics, features, mirroring."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from segmo.motion import (
    KIT,
    T2M,
    bone_lengths,
    features_to_joints,
    forward_kinematics,
    get_skeleton,
    inverse_kinematics,
    joints_to_features,
    mirror_features,
    mirror_joints,
    process_joints,
    rest_offsets,
)
from segmo.motion.kinematics import gaussian_filter1d
from segmo.motion.quaternion import (
    axis_angle_to_quat,
    cont6d_to_matrix,
    cont6d_to_quat,
    euler_to_matrix,
    matrix_to_euler,
    matrix_to_quat,
    qbetween,
    qinv,
    qmul,
    qnormalize,
    qrot,
    quat_to_cont6d,
    quat_to_matrix,
)

FIXTURES = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "humanml3d"


def random_quats(*shape: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return qnormalize(torch.randn(*shape, 4, generator=g, dtype=torch.float64))


def random_walk_joints(
    frames: int = 60, skeleton=T2M, seed: int = 0, lengths=None, scale: float = 1.0
) -> torch.Tensor:
    """(frames, j, 3) float64: a skeleton walking a random path with random, smoothly
    varying joint rotations, built with forward kinematics."""
    spec = get_skeleton(skeleton)
    g = torch.Generator().manual_seed(seed)
    j = spec.num_joints
    # Smooth joint angles: cumulative sums of small random axis-angle steps.
    steps = 0.05 * torch.randn(frames, j, 3, generator=g, dtype=torch.float64)
    local = axis_angle_to_quat(0.3 * torch.randn(j, 3, generator=g, dtype=torch.float64) + steps.cumsum(0))
    heading = (0.1 * torch.randn(frames, generator=g, dtype=torch.float64)).cumsum(0)
    local[:, 0] = torch.stack(
        [torch.cos(heading / 2), torch.zeros_like(heading), torch.sin(heading / 2), torch.zeros_like(heading)], -1
    )
    speed = 0.05 * scale * torch.rand(frames, generator=g, dtype=torch.float64)
    root = torch.stack([(speed * torch.sin(heading)).cumsum(0), torch.full_like(speed, 0.9 * scale),
                        (speed * torch.cos(heading)).cumsum(0)], -1)
    if lengths is None:
        offsets = rest_offsets(spec, dtype=torch.float64)
    else:
        offsets = rest_offsets(spec, lengths, dtype=torch.float64)
    return forward_kinematics(local, root, offsets * (1.0 if lengths is not None else scale), spec.parents)


# --- quaternions -------------------------------------------------------------------------


def test_quaternion_algebra():
    a, b = random_quats(10, seed=1), random_quats(10, seed=2)
    v = torch.randn(10, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    # qrot agrees with the matrix, and composes like qmul.
    assert torch.allclose(qrot(a, v), (quat_to_matrix(a) @ v[..., None])[..., 0], atol=1e-12)
    assert torch.allclose(qrot(qmul(a, b), v), qrot(a, qrot(b, v)), atol=1e-12)
    assert torch.allclose(qrot(qinv(a), qrot(a, v)), v, atol=1e-12)
    # matrix -> quaternion is the inverse up to sign.
    back = matrix_to_quat(quat_to_matrix(a))
    assert torch.allclose(back * torch.sign((back * a).sum(-1, keepdim=True)), a, atol=1e-10)
    # 6-D: first two matrix columns, and Gram-Schmidt recovers the matrix.
    d6 = quat_to_cont6d(a)
    assert torch.allclose(d6[..., :3], quat_to_matrix(a)[..., :, 0])
    assert torch.allclose(cont6d_to_matrix(d6), quat_to_matrix(a), atol=1e-12)
    assert torch.allclose(quat_to_matrix(cont6d_to_quat(d6)), quat_to_matrix(a), atol=1e-10)


def test_qbetween_and_axis_angle():
    g = torch.Generator().manual_seed(4)
    v0 = torch.randn(20, 3, generator=g, dtype=torch.float64)
    v1 = torch.randn(20, 3, generator=g, dtype=torch.float64)
    v1[0] = -2.0 * v0[0]  # opposite directions: the degenerate case
    q = qbetween(v0, v1)
    unit = v1 / v1.norm(dim=-1, keepdim=True)
    assert torch.allclose(qrot(q, v0) / v0.norm(dim=-1, keepdim=True), unit, atol=1e-9)
    q = axis_angle_to_quat(torch.tensor([0.0, math.pi / 2, 0.0], dtype=torch.float64))
    assert torch.allclose(qrot(q, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)),
                          torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-12)
    assert torch.allclose(axis_angle_to_quat(torch.zeros(3)), torch.tensor([1.0, 0.0, 0.0, 0.0]))


def test_qbetween_opposite_vectors_in_float32():
    # Rounding left |q| near 1e-7 for opposite float32 vectors, above the fixed 1e-9 test
    # of the half-turn fallback: the "rotation" was normalised noise (80 % of such pairs).
    v0 = torch.randn(1000, 3, generator=torch.Generator().manual_seed(3))
    v0 = v0 / v0.norm(dim=-1, keepdim=True)
    assert (qrot(qbetween(v0, -v0), v0) + v0).abs().max() < 1e-5


@pytest.mark.parametrize("order", ["ZYX", "XYZ"])
def test_euler_round_trip(order):
    m = quat_to_matrix(random_quats(50, seed=5))
    assert torch.allclose(euler_to_matrix(matrix_to_euler(m, order), order), m, atol=1e-9)


@pytest.mark.parametrize("order", ["ZYX", "XYZ"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_euler_round_trip_at_gimbal_lock(order, dtype):
    # Middle angle at +-90 degrees: both atan2 calls got (0, 0) and the turn was lost.
    angles = torch.tensor([[0.7, math.pi / 2, 0.0], [0.7, -math.pi / 2, -0.4], [-2.0, math.pi / 2, 1.1]],
                          dtype=dtype)
    m = euler_to_matrix(angles, order)
    m = quat_to_matrix(matrix_to_quat(m))  # as a matrix arrives from elsewhere
    tol = 1e-9 if dtype == torch.float64 else 1e-3
    assert torch.allclose(euler_to_matrix(matrix_to_euler(m, order), order), m, atol=tol)


def test_gaussian_filter_matches_scipy():
    ndimage = pytest.importorskip("scipy.ndimage")
    x = np.random.default_rng(0).normal(size=(50, 3))
    expected = ndimage.gaussian_filter1d(x, 20, axis=0, mode="nearest")
    assert np.allclose(gaussian_filter1d(torch.from_numpy(x), 20.0, dim=0).numpy(), expected, atol=1e-12)


# --- kinematics --------------------------------------------------------------------------


@pytest.mark.parametrize("use_chains", [False, True])
def test_forward_inverse_kinematics_round_trip(use_chains):
    joints = random_walk_joints(30, seed=6)
    rotation_parents = T2M.rotation_parents if use_chains else None
    quats = inverse_kinematics(joints, T2M, rotation_parents=rotation_parents)
    assert quats.shape == (30, 22, 4)
    offsets = rest_offsets(T2M, bone_lengths(joints[0], T2M.parents), dtype=torch.float64)
    rebuilt = forward_kinematics(quats, joints[:, 0], offsets, T2M.parents, rotation_parents)
    assert (rebuilt - joints).abs().max() < 1e-9


def test_forward_kinematics_rest_pose_and_errors():
    offsets = rest_offsets(T2M)
    joints = forward_kinematics(torch.zeros(22, 4).index_fill_(1, torch.tensor([0]), 1.0),
                                torch.zeros(3), offsets, T2M.parents)
    # Rest pose: the left ankle is straight below the left hip by thigh + shin.
    assert torch.allclose(joints[7] - joints[1], torch.tensor([0.0, -(0.3936 + 0.4324), 0.0]))
    assert torch.allclose(bone_lengths(joints, T2M.parents), torch.tensor(T2M.reference_bone_lengths), atol=1e-6)
    with pytest.raises(ValueError, match="local_quats"):
        forward_kinematics(torch.zeros(21, 4), torch.zeros(3), offsets, T2M.parents)
    with pytest.raises(ValueError, match="no reference_bone_lengths"):
        rest_offsets(KIT)


# --- features ----------------------------------------------------------------------------


def _fixture(name: str) -> np.ndarray:
    path = FIXTURES / name
    if not path.exists():
        pytest.skip(f"HumanML3D fixture {path} not found (needs the shared fixtures folder)")
    return np.load(path)


def test_features_to_joints_reproduces_fixture():
    joints, features = _fixture("012314_joints.npy"), _fixture("012314_features.npy")
    recovered = features_to_joints(features)
    error = float(np.abs(recovered - joints).max())
    print(f"\nfeatures_to_joints vs 012314_joints.npy: max abs error {error:.3g} m")
    assert isinstance(recovered, np.ndarray) and recovered.dtype == np.float32
    assert error <= 1e-5


def test_joints_to_features_reproduces_fixture():
    joints, features = _fixture("012314_joints.npy"), _fixture("012314_features.npy")
    extracted = joints_to_features(joints)
    assert extracted.shape == (169, 263) and extracted.dtype == np.float32
    diff = np.abs(extracted - features[:169])
    parts = {name: float(diff[:, s].mean()) for name, s in T2M.feature_slices().items()}
    print(f"\njoints_to_features vs 012314_features.npy: mean abs {diff.mean():.3g}, "
          f"max abs {diff.max():.3g}; per part mean {parts}")
    assert diff.mean() <= 1e-3
    assert np.array_equal(extracted[:, -4:], features[:169, -4:])


def test_round_trip_on_random_walk():
    joints = random_walk_joints(60, seed=7)
    features = joints_to_features(joints)
    assert features.shape == (59, 263) and features.dtype == torch.float64
    assert set(features[:, -4:].unique().tolist()) <= {0.0, 1.0}
    recovered = features_to_joints(features)
    canonical = process_joints(joints)
    assert (recovered - canonical[:-1]).abs().max() < 1e-9
    # The canonical pose: on the floor, root at the origin, retargeted bone lengths.
    assert canonical[..., 1].min().abs() < 1e-12 and canonical[0, 0, [0, 2]].abs().max() < 1e-12
    assert torch.allclose(bone_lengths(canonical, T2M.parents),
                          torch.tensor(T2M.reference_bone_lengths, dtype=torch.float64), atol=1e-9)


def test_batched_equals_unbatched_and_types():
    batch = torch.stack([random_walk_joints(40, seed=s) for s in (8, 9, 10)])  # (3, 40, 22, 3)
    features = joints_to_features(batch)
    assert features.shape == (3, 39, 263)
    for i in range(3):
        assert torch.allclose(features[i], joints_to_features(batch[i]), atol=1e-12)
    joints = features_to_joints(features)
    assert joints.shape == (3, 39, 22, 3)
    assert torch.allclose(joints[1], features_to_joints(features[1]), atol=1e-12)
    # numpy in, numpy out (same dtype); float32 tensors stay float32.
    as_numpy = joints_to_features(batch[0].numpy().astype(np.float32))
    assert isinstance(as_numpy, np.ndarray) and as_numpy.dtype == np.float32
    assert np.allclose(as_numpy, features[0].numpy(), atol=1e-4)
    assert features_to_joints(features.float()).dtype == torch.float32
    # float64 views with negative strides or read-only memory (a reversed clip, an mmap)
    # were handed to torch.from_numpy as they were: ValueError, or a torch warning.
    reversed_clip = batch[0].numpy()[::-1]
    assert np.allclose(joints_to_features(reversed_clip), joints_to_features(batch[0].flip(0)).numpy())
    frozen = features[0].numpy().copy()
    frozen.flags.writeable = False
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.allclose(features_to_joints(frozen[::-1]), features_to_joints(features[0].flip(0)).numpy())


def test_features_to_joints_is_differentiable():
    features = joints_to_features(random_walk_joints(20, seed=11)).float().requires_grad_()
    features_to_joints(features).sum().backward()
    assert features.grad is not None and features.grad[:, 4:67].abs().sum() > 0


def test_kit_features_in_millimetres():
    # Shoulders wider than hips, as in people: HumanML3D's facing direction in the IK
    # subtracts the hip vector from the shoulder vector (see kinematics.facing_direction).
    lengths = [0.0] + [0.25] * 20
    lengths[5] = lengths[8] = 0.2
    lengths[11] = lengths[16] = 0.1
    joints = 1000.0 * random_walk_joints(40, KIT, seed=12, lengths=lengths)
    features = joints_to_features(joints, "kit")
    assert features.shape == (39, 251)
    recovered = features_to_joints(features, KIT)
    assert (recovered - process_joints(joints, KIT)[:-1]).abs().max() < 1e-6
    # Contacts use the threshold scaled to mm^2: a still foot is in contact.
    still = joints[:1].repeat(10, 1, 1)
    assert (joints_to_features(still, "kit")[:, -4:] == 1).all()


def test_shape_errors():
    with pytest.raises(ValueError, match="joints must be"):
        joints_to_features(np.zeros((10, 21, 3)))
    with pytest.raises(ValueError, match="features must be"):
        features_to_joints(np.zeros((10, 251)))
    with pytest.raises(TypeError):
        joints_to_features([[0.0]])


# --- mirroring ---------------------------------------------------------------------------


def _symmetric_t2m():
    lengths = np.array(T2M.reference_bone_lengths)
    symmetric = 0.5 * (lengths + lengths[list(T2M.mirror_permutation)])
    return dataclasses.replace(T2M, reference_bone_lengths=tuple(symmetric.tolist()))


def test_mirror_features_matches_mirrored_joints():
    spec = _symmetric_t2m()  # symmetric bones: retargeting commutes with mirroring
    joints = random_walk_joints(50, spec, seed=13)
    a = mirror_features(joints_to_features(joints, spec), spec)
    b = joints_to_features(mirror_joints(joints, spec), spec)
    assert (a - b).abs().max() < 1e-8


def test_mirror_twice_is_identity():
    joints = random_walk_joints(20, seed=14).numpy()
    features = joints_to_features(joints)
    assert np.array_equal(mirror_joints(mirror_joints(joints)), joints)
    assert np.array_equal(mirror_features(mirror_features(features)), features)
    mirrored = mirror_joints(joints)
    assert np.allclose(mirrored[:, 1, 0], -joints[:, 2, 0])  # left hip <- right hip
    assert torch.equal(mirror_features(mirror_features(torch.from_numpy(features))), torch.from_numpy(features))


def test_the_skeleton_names_a_task_accepts_are_the_known_skeletons():
    from typing import get_args

    from segmo.motion.skeleton import SKELETONS, SkeletonName

    assert get_args(SkeletonName) == tuple(SKELETONS)
