"""Tests of segmo.motion.bvh: the written file is parsed by the independent `bvh` package
and its forward kinematics (done here, from the parsed offsets and channels) must land on
the input joints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from segmo.motion import T2M, forward_kinematics, rest_offsets
from segmo.motion.bvh import joints_to_bvh
from segmo.motion.quaternion import axis_angle_to_quat, euler_to_matrix

bvh = pytest.importorskip("bvh", reason="the `bvh` parser (dev extra) is not installed")

FIXTURE = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "humanml3d" / "012314_joints.npy"


def _rigid_fk_joints(frames: int = 40) -> np.ndarray:
    """FK joints whose multi-child joints move their children rigidly, like real data."""
    g = torch.Generator().manual_seed(0)
    angles = (0.05 * torch.randn(frames, 22, 3, generator=g, dtype=torch.float64)).cumsum(0)
    quats = axis_angle_to_quat(angles)
    quats[:, [1, 2, 3, 12, 13, 14]] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    root = torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64) + torch.linspace(0, 1, frames)[:, None] * torch.tensor([0.5, 0.0, 1.0])
    return forward_kinematics(quats, root, rest_offsets(T2M, dtype=torch.float64), T2M.parents).numpy()


def _bvh_positions(path: Path) -> tuple[np.ndarray, list[str], float]:
    """Forward kinematics from the parsed BVH: (t, j, 3) in file order."""
    mocap = bvh.Bvh(path.read_text())
    names = mocap.get_joints_names()
    world_rot: dict[str, np.ndarray] = {}
    positions = np.zeros((mocap.nframes, len(names), 3))
    for k, name in enumerate(names):
        channels = mocap.joint_channels(name)
        values = np.asarray(mocap.frames_joint_channels(name, channels), dtype=np.float64)
        rotation_channels = [c for c in channels if c.endswith("rotation")]
        order = "".join(c[0] for c in rotation_channels)
        angles = np.radians(values[:, [channels.index(c) for c in rotation_channels]])
        local = euler_to_matrix(torch.from_numpy(angles), order).numpy()
        offset = np.asarray(mocap.joint_offset(name), dtype=np.float64)
        parent_index = mocap.joint_parent_index(name)
        if parent_index < 0:
            position_channels = [channels.index(f"{axis}position") for axis in "XYZ"]
            positions[:, k] = offset + values[:, position_channels]
            world_rot[name] = local
        else:
            parent = names[parent_index]
            positions[:, k] = positions[:, parent_index] + np.einsum("tij,j->ti", world_rot[parent], offset)
            world_rot[name] = world_rot[parent] @ local
    return positions, names, mocap.frame_time


@pytest.mark.parametrize("source", ["fixture", "fk"])
def test_bvh_round_trip(tmp_path, source):
    if source == "fixture":
        if not FIXTURE.exists():
            pytest.skip(f"HumanML3D fixture {FIXTURE} not found (needs the shared fixtures folder)")
        joints = np.load(FIXTURE)
    else:
        joints = _rigid_fk_joints()
    path = joints_to_bvh(joints, tmp_path / "motion.bvh", fps=20)
    positions, names, frame_time = _bvh_positions(path)
    assert sorted(names) == sorted(T2M.joint_names) and frame_time == pytest.approx(0.05)
    positions = positions[:, [names.index(name) for name in T2M.joint_names]]
    error = np.abs(positions - joints).max()
    print(f"\nBVH ({source}) max joint position error: {error * 1000:.3f} mm")
    assert positions.shape == joints.shape and error < 0.01


def test_bvh_rejects_wrong_shape(tmp_path):
    with pytest.raises(ValueError, match=r"\(t, 22, 3\)"):
        joints_to_bvh(np.zeros((5, 21, 3)), tmp_path / "x.bvh")
