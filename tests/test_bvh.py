"""Tests of segmo.motion.bvh and segmo.motion.skeleton_fit.

The written files are read back by three independent parsers (`bvh`, with forward
kinematics done here from its offsets and channels; `bvhio` and `pybvh`, with their own),
and the joints they compute must land on the input joints."""

from __future__ import annotations

import ast
import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from segmo.motion import (
    T2M,
    features_to_joints,
    forward_kinematics,
    joints_to_features,
    rest_offsets,
)
from segmo.motion.bvh import ORDERS, continuous_euler, joints_to_bvh, write_bvh
from segmo.motion.quaternion import axis_angle_to_quat, euler_to_matrix
from segmo.motion.skeleton_fit import fit_motion, fit_skeleton, foot_contacts, foot_skating
from segmo.synth.sequence import sample_motion

bvh = pytest.importorskip("bvh", reason="the `bvh` parser (dev extra) is not installed")
bvhio = pytest.importorskip("bvhio", reason="the `bvhio` reader (dev extra) is not installed")
pybvh = pytest.importorskip("pybvh", reason="the `pybvh` reader (dev extra) is not installed")

FIXTURE = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "humanml3d" / "012314_joints.npy"


def _rigid_fk_joints(frames: int = 40) -> np.ndarray:
    """FK joints whose multi-child joints move their children rigidly, like real data."""
    g = torch.Generator().manual_seed(0)
    angles = (0.05 * torch.randn(frames, 22, 3, generator=g, dtype=torch.float64)).cumsum(0)
    quats = axis_angle_to_quat(angles)
    quats[:, [1, 2, 3, 12, 13, 14]] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    root = torch.tensor([0.0, 0.9, 0.0], dtype=torch.float64) + torch.linspace(0, 1, frames)[:, None] * torch.tensor([0.5, 0.0, 1.0])
    return forward_kinematics(quats, root, rest_offsets(T2M, dtype=torch.float64), T2M.parents).numpy()


def _corpus_joints(seed: int = 0) -> np.ndarray:
    """Joints of one built-in corpus motion as the corpus stores them (via its features), of
    version 4, whose rig a BVH hierarchy can follow."""
    motion = sample_motion(np.random.default_rng(seed), version=4)
    return features_to_joints(joints_to_features(motion.joints.astype(np.float64)))


def _stretched(joints: np.ndarray, amount: float = 0.1, seed: int = 0) -> np.ndarray:
    """Joints whose bones grow and shrink smoothly by up to `amount`, as generated ones do."""
    rng = np.random.default_rng(seed)
    parents = T2M.parents
    bones = joints - joints[:, [max(p, 0) for p in parents]]
    factor = 1 + amount * np.tanh(np.cumsum(rng.normal(0, 0.05, (len(joints), 22)), 0))
    out = joints.copy()
    for c in range(1, 22):
        out[:, c] = out[:, parents[c]] + bones[:, c] * factor[:, c : c + 1]
    return out


def _bvh_positions(path: Path) -> tuple[np.ndarray, list[str], float]:
    """Forward kinematics from the `bvh` package's parse: (t, j, 3) in file order."""
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
            positions[:, k] = positions[:, parent_index] + np.einsum("tij,j->ti", world_rot[names[parent_index]], offset)
            world_rot[name] = world_rot[names[parent_index]] @ local
    return positions, names, mocap.frame_time


def _read(path: Path, reader: str) -> np.ndarray:
    """(t, 22, 3) joints in segmo's order by a third-party reader's forward kinematics."""
    if reader == "bvh":
        positions, names, _ = _bvh_positions(path)
    elif reader == "pybvh":
        mocap = pybvh.read_bvh_file(str(path))
        positions, names = mocap.joint_positions(), list(mocap.joint_names)
    else:
        root = bvhio.readAsHierarchy(str(path))
        joints = [j for j, *_ in root.layout()]
        names = [j.Name for j in joints]
        frames = []
        for frame in range(len(_bvh_positions(path)[0])):
            root.loadPose(frame)
            frames.append([np.array(j.PositionWorld, dtype=np.float64) for j in joints])
        positions = np.asarray(frames)
    return positions[:, [names.index(name) for name in T2M.joint_names]]


@pytest.mark.parametrize("reader", ["bvh", "bvhio", "pybvh"])
@pytest.mark.parametrize("source", ["fixture", "fk", "corpus"])
def test_bvh_round_trip(tmp_path, source, reader):
    if source == "fixture":
        if not FIXTURE.exists():
            pytest.skip(f"HumanML3D fixture {FIXTURE} not found (needs the shared fixtures folder)")
        joints = np.load(FIXTURE).astype(np.float64)
    elif source == "fk":
        joints = _rigid_fk_joints()
    else:
        joints = _corpus_joints()
    path = joints_to_bvh(joints, tmp_path / "motion.bvh", fps=20, foot_lock=False,
                         bone_lengths="motion" if source == "fk" else None)
    assert _bvh_positions(path)[2] == pytest.approx(0.05)
    error = np.linalg.norm(_read(path, reader) - joints, axis=-1)
    print(f"\nBVH {source} via {reader}: mean {error.mean() * 1000:.3f} mm, max {error.max() * 1000:.3f} mm")
    assert error.mean() < 0.001 and error.max() < {"fixture": 0.01, "fk": 0.003, "corpus": 0.001}[source]


def test_corpus_version_4_round_trips_where_version_3_cannot(tmp_path):
    # Motion 955 of seed 0 (arms stretched up): version 3's neck moves apart from the
    # collars by up to 23 mm, which no BVH hierarchy shows; version 4's rig turns a joint's
    # children together.
    errors = {}
    for version in (3, 4):
        motion = sample_motion(np.random.default_rng([0, 955]), version=version)
        joints = features_to_joints(joints_to_features(motion.joints.astype(np.float64)))
        path = joints_to_bvh(joints, tmp_path / f"v{version}.bvh", foot_lock=False)
        errors[version] = float(np.linalg.norm(_read(path, "pybvh") - joints, axis=-1).max())
    print(f"\ncorpus motion 955: largest BVH error v3 {errors[3] * 1000:.2f} mm, v4 {errors[4] * 1000:.4f} mm")
    assert errors[4] < 1e-5 < 5e-3 < errors[3]


def test_fit_keeps_bones_fixed_and_does_not_carry_a_stretch_down_the_chain():
    stretched = _stretched(_corpus_joints(1))
    fit = fit_skeleton(stretched)
    lengths = np.linalg.norm(fit.joints[:, 1:] - fit.joints[:, list(T2M.parents[1:])], axis=-1)
    assert np.allclose(lengths, np.asarray(T2M.reference_bone_lengths[1:]), atol=1e-9)
    error = np.linalg.norm(fit.joints - stretched, axis=-1)
    start = np.linalg.norm(fit_skeleton(stretched, iterations=0).joints - stretched, axis=-1)
    print(f"\nstretched bones: mean {error.mean() * 1000:.2f} mm (start {start.mean() * 1000:.2f}), "
          f"max {error.max() * 1000:.1f} mm (start {start.max() * 1000:.1f})")
    assert error.mean() < start.mean() and error.max() < start.max() and error.mean() < 0.01


def test_heading_turns_do_not_flip_channels(tmp_path):
    """A body turning twice round itself: no channel jumps more than 30 degrees between
    frames (the old ZYX root order flipped at every quarter turn)."""
    joints = _corpus_joints(2)
    turn = np.linspace(0, 4 * np.pi, len(joints))
    spin = Rotation.from_euler("y", turn[:, None]).as_matrix()  # (t, 3, 3)
    centre = joints[:, :1, :] * np.array([1, 0, 1])
    turned = np.einsum("tij,tkj->tki", spin, joints - centre) + centre
    path = joints_to_bvh(turned, tmp_path / "spin.bvh", foot_lock=False)
    lines = path.read_text().splitlines()
    values = np.array([[float(v) for v in line.split()] for line in lines[lines.index("MOTION") + 3:]])
    jumps = np.abs(np.diff(values[:, 3:], axis=0))
    assert jumps.max() < 30.0, f"a channel jumps {jumps.max():.1f} degrees between frames"
    assert np.linalg.norm(_read(path, "pybvh") - turned, axis=-1).max() < 0.003


@pytest.mark.parametrize("order", ORDERS)
def test_continuous_euler_round_trips_through_gimbal_lock(order):
    t = np.linspace(0, 3 * np.pi, 120)
    middle = np.full_like(t, np.pi / 2)
    middle[::2] -= 1e-9  # at and next to the lock
    rotations = Rotation.from_euler(order, np.stack([t, middle, 0.5 * t], -1)).as_matrix()
    angles = continuous_euler(rotations, order)
    assert np.abs(Rotation.from_euler(order, angles).as_matrix() - rotations).max() < 1e-6
    assert np.degrees(np.abs(np.diff(angles, axis=0))).max() < 30.0


def test_foot_lock_reduces_skating(tmp_path):
    joints = _stretched(_corpus_joints(3), amount=0.05, seed=3)
    contacts = foot_contacts(joints)
    assert contacts.any(), "the test motion never touches the ground"
    skating = {}
    for lock in (False, True):
        path = joints_to_bvh(joints, tmp_path / f"lock_{lock}.bvh", foot_lock=lock)
        skating[lock] = foot_skating(_read(path, "pybvh"), contacts)
    print(f"\nfoot skating: {skating[False] * 100:.2f} cm/s unlocked, {skating[True] * 100:.2f} cm/s locked")
    assert skating[True] < 0.5 * skating[False]


def test_bvh_target_frame_rate(tmp_path):
    joints = _corpus_joints(4)
    path = joints_to_bvh(joints, tmp_path / "60.bvh", fps=20, target_fps=60, foot_lock=False)
    positions, _, frame_time = _bvh_positions(path)
    assert frame_time == pytest.approx(1 / 60, abs=1e-6) and len(positions) == 3 * (len(joints) - 1) + 1
    original = _read(joints_to_bvh(joints, tmp_path / "20.bvh", foot_lock=False), "bvh")
    assert np.abs(_read(path, "bvh")[::3] - original).max() < 1e-4  # the 20 fps frames are kept


@pytest.mark.parametrize("frames, fps, target_fps", [(76, 20, 22.4), (251, 12, 47.952)])
def test_bvh_resampling_whose_last_frame_rounds_past_the_motions_end(tmp_path, frames, fps,
                                                                      target_fps):
    """The last resampled frame, k / target_fps, came out one rounding error after the
    motion's end, and scipy's Slerp raised a ValueError after the whole fit."""
    joints = np.concatenate([_corpus_joints(4)] * 4)[:frames]
    path = joints_to_bvh(joints, tmp_path / "x.bvh", fps=fps, target_fps=target_fps,
                         foot_lock=False)
    resampled = _read(path, "bvh")
    assert len(resampled) == int((frames - 1) / fps * target_fps + 1e-9) + 1
    kept = _read(joints_to_bvh(joints, tmp_path / "same.bvh", fps=fps, foot_lock=False), "bvh")
    assert np.abs(resampled[-1] - kept[-1]).max() < 1e-4  # the last frame is the motion's last


@pytest.mark.parametrize("rates", [{"target_fps": 1e-9}, {"target_fps": 1000}, {"fps": 1e-9},
                                   {"fps": 20, "target_fps": float("nan")}])
def test_bvh_refuses_a_frame_rate_out_of_range(tmp_path, rates):
    """1e-9 fps wrote one frame, 1e7 fps asked for gigabytes: refused, naming the argument."""
    name = "target_fps" if "target_fps" in rates else "fps"
    with pytest.raises(ValueError, match=rf"joints_to_bvh: {name}: expected a frame rate in \[12, 480\]"):
        joints_to_bvh(_corpus_joints(4), tmp_path / "x.bvh", foot_lock=False, **rates)
    assert not (tmp_path / "x.bvh").exists()


def test_write_bvh_refuses_a_fit_of_another_skeleton(tmp_path):
    """A t2m fit written with skeleton="kit" gave a KIT hierarchy carrying t2m rotations at
    KIT's frame time, without a word (and a KIT fit with the default t2m an IndexError)."""
    fit = fit_motion(_corpus_joints(4)[:8], foot_lock=False)
    with pytest.raises(ValueError, match="write_bvh: the fit is of a skeleton of 22 joints "
                                         "other than 'kit'"):
        write_bvh(fit, tmp_path / "x.bvh", skeleton="kit")
    assert not (tmp_path / "x.bvh").exists()


def test_contacts_must_be_booleans_and_need_the_foot_lock(tmp_path):
    """The features' contact channels (0.1-1.1) passed as contacts locked both feet in
    every frame; contacts with foot_lock=False were ignored."""
    joints = _corpus_joints(4)[:8]
    with pytest.raises(ValueError, match=r"contacts must be booleans, got float64 \(threshold"):
        joints_to_bvh(joints, tmp_path / "x.bvh", contacts=np.full((8, 4), 0.2))
    with pytest.raises(ValueError, match="contacts given with foot_lock=False"):
        joints_to_bvh(joints, tmp_path / "x.bvh", contacts=np.ones((8, 4), bool), foot_lock=False)
    assert not (tmp_path / "x.bvh").exists()
    assert joints_to_bvh(joints, tmp_path / "x.bvh", contacts=np.ones((8, 4), bool)).is_file()


def test_bvh_rejects_wrong_shape(tmp_path):
    with pytest.raises(ValueError, match=r"\(t, 22, 3\)"):
        joints_to_bvh(np.zeros((5, 21, 3)), tmp_path / "x.bvh")
    with pytest.raises(ValueError, match="NaN"):
        joints_to_bvh(np.full((5, 22, 3), np.nan), tmp_path / "x.bvh", foot_lock=False)


def test_bvh_refuses_a_frame_of_absurd_joints_and_reads_bf16(tmp_path):
    """One frame whose root lies at 3e38 passed the bone-scale check (a median) and wrote
    110 rotations of ~1800 degrees; a bfloat16 tensor was a TypeError from numpy."""
    joints = _corpus_joints()
    broken = joints.copy()
    broken[5, 0] = 3e38
    with pytest.raises(ValueError, match=r"1 frame\(s\) hold NaN/inf or joints beyond 10000 m"
                                         r".* the first is frame 5"):
        joints_to_bvh(broken, tmp_path / "x.bvh")
    assert not (tmp_path / "x.bvh").exists()
    half = torch.from_numpy(joints).to(torch.bfloat16)
    written = joints_to_bvh(half, tmp_path / "bf16.bvh", foot_lock=False)
    error = np.linalg.norm(_read(written, "bvh") - half.double().numpy(), axis=-1)
    assert error.max() < 0.05


def test_the_file_does_not_depend_on_the_arrays_memory_order(tmp_path):
    """A Fortran-ordered copy of the same joints (np.load gives one for a file saved so)
    rounded otherwise in the fit and wrote other, equivalent, Euler triples."""
    joints = _corpus_joints()
    c = joints_to_bvh(np.ascontiguousarray(joints), tmp_path / "c.bvh")
    f = joints_to_bvh(np.asfortranarray(joints), tmp_path / "f.bvh")
    assert c.read_text() == f.read_text()


@pytest.mark.parametrize("scale", [float("nan"), 0.0, -1.0, "100", True])
def test_bvh_refuses_a_scale_that_is_not_a_positive_number(tmp_path, scale):
    """NaN wrote 'nan' into the file, 0 collapsed every bone, -1 mirrored the motion
    through the origin, and "100" failed in numpy after the whole fit."""
    with pytest.raises(ValueError, match="scale must be a finite number > 0"):
        joints_to_bvh(_corpus_joints(), tmp_path / "x.bvh", scale=scale)
    assert not (tmp_path / "x.bvh").exists()


def test_bvh_refuses_joints_in_other_units_than_the_skeletons(tmp_path):
    """Centimetre joints got the reference's metre bones under a root that moved 100 times
    as far (a read-back error of 95 units): a BVH of another motion."""
    joints = _corpus_joints()
    for wrong, ratio in ((joints * 100, "100 times"), (joints * 0.0 + joints[:, :1], "0 times")):
        with pytest.raises(ValueError, match=f"bones are {ratio} as long as the 't2m' skeleton's"):
            joints_to_bvh(wrong, tmp_path / "x.bvh")
    with pytest.raises(ValueError, match="complex numbers"):
        joints_to_bvh(joints + 0j, tmp_path / "x.bvh")
    assert not (tmp_path / "x.bvh").exists()
    # The motion's own bones, in its own units, are what bone_lengths="motion" is for.
    written = joints_to_bvh(joints * 100, tmp_path / "cm.bvh", bone_lengths="motion",
                            foot_lock=False)
    error = np.linalg.norm(_read(written, "bvh") - joints * 100, axis=-1)
    assert error.max() < 1.0  # within a centimetre


def test_a_bone_swinging_past_opposite_its_rest_direction_does_not_flip_its_twist():
    """A shin (rest: down) swung round through straight up in 4-degree steps: the fitted
    rotation turns about 4 degrees a frame too (the shortest arc from the rest direction
    alone turns the bone ~180 degrees about itself as it passes straight up)."""
    from segmo.motion.skeleton_fit import _transported

    angle = np.radians(np.arange(0, 360, 4.0))
    directions = np.stack([np.sin(angle), -np.cos(angle), 0.1 * np.ones_like(angle)], -1)
    rotations = _transported(np.array([0.0, -1.0, 0.0]), directions)
    assert np.allclose(np.einsum("tij,j->ti", rotations, [0.0, -1.0, 0.0]),
                       directions / np.linalg.norm(directions, axis=-1, keepdims=True), atol=1e-9)
    steps = np.degrees(Rotation.from_matrix(rotations[1:] @ np.swapaxes(rotations[:-1], 1, 2)).magnitude())
    assert steps.max() < 5.0, f"the bone turns {steps.max():.0f} degrees in one frame"


def test_bvh_check_tool_at_the_exporters_frame_rates(tmp_path, capsys):
    """tools/bvh_check.py reads its files back at --bvh-fps 20 and at its default, the
    exporter's 60 fps: positions match at the input's frames either way, and at 60 fps each
    channel moves by about a third as much between frames; a rate that is not a multiple of
    20 is refused."""
    import json

    from conftest import load_tool

    tool = load_tool("bvh_check")
    data = tmp_path / "data"
    (data / "new_joints").mkdir(parents=True)
    for k, joints in enumerate([_rigid_fk_joints(30), _corpus_joints(5)[:40]]):
        np.save(data / "new_joints" / f"m{k}.npy", joints.astype(np.float32))
    (data / "test.txt").write_text("m0\nm1\n")
    reports = {}
    for fps in (20, None):
        argv = ["--data", str(data), "--bvhio-files", "1", "--out", str(tmp_path / f"out{fps}")]
        tool.main(argv + ([] if fps is None else ["--bvh-fps", str(fps)]))
        reports[fps] = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["corpus"]
    for report in reports.values():
        assert report["files"] == 2 and report["error_bvhio"]["max_mm"] < 5
        assert report["error_pybvh"]["mean_mm"] < 1 and set(report["largest_pybvh_error_mm_by_file"]) == {"m0", "m1"}
    assert 0 < reports[None]["max_channel_jump_deg"] < 0.5 * reports[20]["max_channel_jump_deg"]
    with pytest.raises(SystemExit):
        tool.main(["--data", str(data), "--bvh-fps", "25"])
    assert "multiple of 20" in capsys.readouterr().err
    # each was a traceback: write_bvh's range after the 20 fps check, max() of no motion
    (data / "none.txt").write_text("\n")
    for argv, message in ((["--bvh-fps", "500"], "in [12, 480], got 500"),
                          (["--limit", "0"], "--limit: expected a whole number >= 1"),
                          (["--split", "none"], "none.txt lists no motion"),
                          (["--split", "val"], "--split val: no file")):
        with pytest.raises(SystemExit):
            tool.main(["--data", str(data), "--out", str(tmp_path / "x"), *argv])
        assert message in capsys.readouterr().err


def test_the_blender_tool_knows_segmos_joint_order():
    """Without --names the tool took Blender's bone order (the file's, depth first) for
    the joints' own: every bone was compared with another joint (380 mm off on average)."""
    tree = ast.parse((Path(__file__).resolve().parents[1] / "tools" / "blender_import.py").read_text())
    [names] = [ast.literal_eval(node.value) for node in tree.body if isinstance(node, ast.Assign)
               and getattr(node.targets[0], "id", None) == "T2M_JOINTS"]
    assert names == list(T2M.joint_names)


def test_blender_imports_the_file_onto_the_joints(tmp_path):
    """Blender's own BVH importer, where Blender is installed (Debian: apt install blender)."""
    if shutil.which("blender") is None:
        pytest.skip("Blender is not installed")
    joints = _corpus_joints(4)[:24]
    fit = fit_motion(joints)
    np.save(tmp_path / "joints.npy", fit.joints)
    path = joints_to_bvh(joints, tmp_path / "x.bvh", target_fps=60)
    tool = Path(__file__).resolve().parents[1] / "tools" / "blender_import.py"
    run = subprocess.run(["blender", "-b", "--python", str(tool), "--", str(path),
                          str(tmp_path / "joints.npy")], capture_output=True, text=True, timeout=300)
    [line] = [line for line in run.stdout.splitlines() if line.startswith("{")]
    report = json.loads(line)
    assert report["bones"] == 22 and report["every"] == 3 and report["max_mm"] < 1.0


def test_the_rest_pose_is_a_t_pose(tmp_path):
    """The rest pose hung the arms down from the collars (the raw offsets of HumanML3D's
    features), with the head in front of the neck; animation tools and retargeting expect
    the arms out and the head up, as the docs said."""
    path = joints_to_bvh(_corpus_joints(4)[:8], tmp_path / "x.bvh", foot_lock=False)
    mocap = bvh.Bvh(path.read_text())
    rest = {}
    for name in mocap.get_joints_names():
        parent = mocap.joint_parent(name)
        offset = np.asarray(mocap.joint_offset(name), dtype=np.float64)
        rest[name] = offset + (rest[parent.name] if parent is not None else 0)
    for side, sign in (("left", 1), ("right", -1)):
        arm = [rest[f"{side}_{joint}"] for joint in ("collar", "shoulder", "elbow", "wrist")]
        assert all(np.abs(b[1:] - arm[0][1:]).max() < 1e-6 for b in arm)  # level with the collar
        assert all(sign * (b[0] - a[0]) > 0.1 for a, b in zip(arm, arm[1:]))  # outwards
    head = rest["head"] - rest["neck"]
    assert head[1] > 0.09 and np.abs(head[[0, 2]]).max() < 1e-6


def test_a_kit_file_is_in_metres_unless_a_scale_says_otherwise(tmp_path):
    """KIT-ML's joints are in millimetres, and the file kept them: Blender, which reads a
    BVH unit as a metre, imported a figure 1.7 km tall."""
    from segmo.motion import KIT

    g = torch.Generator().manual_seed(0)
    quats = axis_angle_to_quat((0.05 * torch.randn(12, 21, 3, generator=g,
                                                   dtype=torch.float64)).cumsum(0))
    quats[:, [0, 3]] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    offsets = torch.tensor(KIT.raw_offsets, dtype=torch.float64) * 150.0  # millimetres
    root = torch.tensor([0.0, 1000.0, 0.0], dtype=torch.float64).expand(12, 3)
    joints = forward_kinematics(quats, root, offsets, KIT.parents).numpy()
    for scale, unit in ((None, 0.001), (1.0, 1.0)):
        path = joints_to_bvh(joints, tmp_path / f"{scale}.bvh", skeleton="kit", scale=scale,
                             foot_lock=False)
        mocap = bvh.Bvh(path.read_text())
        assert np.linalg.norm(mocap.joint_offset("torso")) == pytest.approx(150.0 * unit, rel=1e-3)
        root_y = float(mocap.frame_joint_channel(0, "root", "Yposition"))
        assert root_y == pytest.approx(1000.0 * unit, rel=1e-3)
