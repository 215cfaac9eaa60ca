"""BVH export checked as an animation tool would see it, on corpus and generated motions.

    python tools/bvh_check.py --data data/synth --split test [--model models/segmo] \\
        [--limit N] [--bvh-fps 20] [--out runs/bvh_check]

For every motion of the split (the corpus' joints) and, with --model, one generated motion
per motion (its first caption and length, seed 0): write the BVH with and without foot
locking, read it back with two third-party readers (`pybvh` for every file, `bvhio` for the
first --bvhio-files), and compare the joints of their forward kinematics with the input
joints. Reports per source: position error (mean, 99th percentile, max; mm), the largest
change of any rotation channel between frames, and of a joint that turned by less than
30 degrees (a flip of the angles, not a fast motion; degrees), the five files with the
largest position error (pybvh, no foot lock; by motion id) and how many files stay within
1 mm, and foot skating (mean horizontal
speed of the foot joints in contact, cm/s) of the input joints and of both BVH files, with
the contacts of the input joints. The last printed line is a JSON object of these figures.

--bvh-fps writes the files at that rate (`write_bvh`'s target_fps; a whole multiple of the
motions' 20 fps; default 60, the rate `segmo generate` writes): channel changes are then
between the file's frames, and positions are compared at the input's frames (every k-th
frame of the file).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from segmo.errors import non_negative_int, positive_int
from segmo.motion import T2M
from segmo.motion.bvh import ANIMATION_FPS, MAX_BVH_FPS, MIN_BVH_FPS, write_bvh
from segmo.motion.skeleton_fit import fit_motion, foot_contacts, foot_skating


def read_pybvh(path: Path) -> np.ndarray:
    import pybvh

    mocap = pybvh.read_bvh_file(str(path))
    names = list(mocap.joint_names)
    return mocap.joint_positions()[:, [names.index(n) for n in T2M.joint_names]]


def read_bvhio(path: Path, frames: int) -> np.ndarray:
    import bvhio

    root = bvhio.readAsHierarchy(str(path))
    joints = {j.Name: j for j, *_ in root.layout()}
    out = []
    for frame in range(frames):
        root.loadPose(frame)
        out.append([np.array(joints[n].PositionWorld, dtype=np.float64) for n in T2M.joint_names])
    return np.asarray(out)


def channel_jumps(path: Path) -> tuple[float, float]:
    """(largest change of a rotation channel between consecutive frames, the largest such
    change of a joint that turned by less than 30 degrees between those frames: a flip of
    the Euler angles rather than a fast motion), in degrees."""
    from scipy.spatial.transform import Rotation

    lines = path.read_text().splitlines()
    orders = ["".join(c[0] for c in line.split()[-3:]) for line in lines if "CHANNELS" in line]
    values = np.array([[float(v) for v in line.split()] for line in lines[lines.index("MOTION") + 3:]])
    if len(values) < 2:
        return 0.0, 0.0
    angles = values[:, 3:].reshape(len(values), len(orders), 3)
    jump = np.abs(np.diff(angles, axis=0)).max(-1)  # (t-1, j)
    turned = np.stack([(Rotation.from_euler(o, angles[1:, k], degrees=True)
                        * Rotation.from_euler(o, angles[:-1, k], degrees=True).inv()).magnitude()
                       for k, o in enumerate(orders)], -1)
    flips = jump[np.degrees(turned) < 30.0]
    return float(jump.max()), float(flips.max()) if flips.size else 0.0


def check(motions: list[np.ndarray], out: Path, bvhio_files: int, bvh_fps: float | None = None,
          names: list[str] | None = None) -> dict:
    errors: dict[str, list[np.ndarray]] = {"pybvh": [], "pybvh_foot_lock": [], "bvhio": [],
                                           "saved_joints": []}
    jumps, skating = [], {"input": [], "bvh": [], "bvh_foot_lock": []}
    every = 1 if bvh_fps is None else round(bvh_fps / T2M.fps)  # file frames per input frame
    for k, joints in enumerate(motions):
        contacts = foot_contacts(joints)
        skating["input"].append(foot_skating(joints, contacts))
        for lock in (False, True):
            fit = fit_motion(joints, foot_lock=lock)
            path = write_bvh(fit, out / f"{k:04d}{'_lock' if lock else ''}.bvh", target_fps=bvh_fps)
            read = read_pybvh(path)[::every]
            errors["pybvh_foot_lock" if lock else "pybvh"].append(np.linalg.norm(read - joints, axis=-1).ravel())
            if lock:  # what `GenerationOutput.save` writes as the joints file, against its BVH
                errors["saved_joints"].append(np.linalg.norm(read - fit.joints, axis=-1).ravel())
            skating["bvh_foot_lock" if lock else "bvh"].append(foot_skating(read, contacts))
            jumps.append(channel_jumps(path))
            if not lock and k < bvhio_files:
                frames = read_bvhio(path, every * (len(joints) - 1) + 1)[::every]
                errors["bvhio"].append(np.linalg.norm(frames - joints, axis=-1).ravel())

    def summary(e: list[np.ndarray]) -> dict | None:
        if not e:
            return None
        e = np.concatenate(e) * 1000
        return {"mean_mm": round(float(e.mean()), 3), "p99_mm": round(float(np.percentile(e, 99)), 2),
                "max_mm": round(float(e.max()), 2)}

    names = names or [f"{k:04d}" for k in range(len(motions))]
    largest_mm = [float(e.max()) * 1000 for e in errors["pybvh"]]  # per file
    worst = sorted(zip(largest_mm, names), reverse=True)[:5]
    return {"files": len(motions), **{f"error_{name}": summary(e) for name, e in errors.items()},
            "largest_pybvh_error_mm_by_file": {name: round(e, 2) for e, name in worst},
            "files_within_1mm": sum(e <= 1.0 for e in largest_mm),
            "max_channel_jump_deg": round(max(j for j, _ in jumps), 2),
            "max_channel_jump_of_a_joint_turning_under_30_deg": round(max(f for _, f in jumps), 2),
            "skating_cm_s": {k: round(100 * float(np.mean(v)), 3) for k, v in skating.items()}}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="dataset root (new_joints/, <split>.txt)")
    p.add_argument("--split", default="test")
    p.add_argument("--model", help="SegMo bundle: also check generated motions")
    p.add_argument("--limit", type=positive_int, default=None, help="first N motions of the split")
    p.add_argument("--bvhio-files", type=non_negative_int, default=20,
                   help="files also read with bvhio")
    p.add_argument("--bvh-fps", type=float, default=ANIMATION_FPS,
                   help=f"write the files at this rate, a whole multiple of 20 (default {ANIMATION_FPS:g}, "
                   "the exporter's; 20: the motions' own frames)")
    p.add_argument("--out", default="runs/bvh_check")
    args = p.parse_args(argv)
    if not MIN_BVH_FPS <= args.bvh_fps <= MAX_BVH_FPS or args.bvh_fps % T2M.fps:
        p.error(f"--bvh-fps must be a whole multiple of {T2M.fps:g} in [{MIN_BVH_FPS:g}, "
                f"{MAX_BVH_FPS:g}], got {args.bvh_fps:g}")
    root = Path(args.data)
    split = root / f"{args.split}.txt"
    if not split.is_file():
        p.error(f"--split {args.split}: no file {split}")
    ids = split.read_text().split()[: args.limit]
    if not ids:
        p.error(f"--split {args.split}: {split} lists no motion")
    corpus = [np.load(root / "new_joints" / f"{i}.npy").astype(np.float64) for i in ids]
    report: dict = {}
    start = time.perf_counter()
    out = Path(args.out)
    (out / "corpus").mkdir(parents=True, exist_ok=True)
    report["corpus"] = check(corpus, out / "corpus", args.bvhio_files, args.bvh_fps, ids)
    print(f"corpus: {json.dumps(report['corpus'])}", flush=True)
    if args.model:
        from segmo import SegMo

        model = SegMo.from_pretrained(args.model)
        texts = [(root / "texts" / f"{i}.txt").read_text().splitlines()[0].split("#")[0] for i in ids]
        lengths = [min(len(j) // 4 * 4, 196) for j in corpus]
        generated = []
        for b in range(0, len(texts), 32):
            result = model.generate(texts[b:b + 32], lengths[b:b + 32],
                                    generator=torch.Generator().manual_seed(b))
            generated += [result.motion_joints(i).astype(np.float64) for i in range(len(result))]
        (out / "generated").mkdir(parents=True, exist_ok=True)
        report["generated"] = check(generated, out / "generated", args.bvhio_files, args.bvh_fps, ids)
        print(f"generated: {json.dumps(report['generated'])}", flush=True)
    report["seconds"] = round(time.perf_counter() - start, 1)
    print(json.dumps(report))


if __name__ == "__main__":
    sys.exit(main())
