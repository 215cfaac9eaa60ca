"""Build the synthetic corpus in the HumanML3D layout (`segmo synth`).

    segmo synth --out data/synth --num-motions 2000 --seed 0 [--version 3]

`--version` picks how motions are sampled (`segmo.synth.sequence`): 3, the default, puts
a short action beside a long one in every motion of two or more (a long walk beside one
short jump); 2 lets durations follow the action without that; 1 reproduces the first
corpus, whose actions last nearly equally long; 4 is version 3 with a rig whose joints turn
their children together, as an SMPL or BVH hierarchy does, so that BVH files follow its
joints exactly. Versions 1 and 2 are reproduced byte for
byte. Motion i is generated from `numpy.random.default_rng([seed, i])` alone, so the files do
not depend on how many workers build them; the normalisation statistics are merged in
index order for the same reason. The corpus is built in `OUT.tmp-<pid>` and renamed into
place when complete (so its files, written at the paths of `segmo.data.layout`, need no
atomic writes of their own), while `OUT/.segmo-writer.lock` keeps other writers out. A folder
that already holds this corpus (same version, seed and size) is left as it is; one that
holds another corpus is rebuilt only when nothing else lives in it (text segments, text
features, runs: what a rebuild would delete) or with `--overwrite`.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import sys
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from segmo.data.layout import (
    GROUND_TRUTH,
    JOINTS,
    MOTIONS,
    STATISTICS,
    ground_truth_file,
    joints_file,
    motion_file,
    split_file,
    stats_files,
    texts_file,
)
from segmo.errors import ArgumentParser, SegmoError, non_negative_int, positive_int
from segmo.files import (
    LOCK_FILE,
    FolderLock,
    check_replaceable_place,
    replaced_folder,
    replacing_folder,
)
from segmo.motion.features import features_to_joints, joints_to_features
from segmo.synth.actions import ACTIONS
from segmo.synth.captions import HELD_OUT_TEMPLATES, Caption, make_captions, pos_tag
from segmo.synth.sequence import VERSION, VERSIONS, Segment, sample_motion
from segmo.text.captions import TEXTS

SPLITS = {"train": 0.80, "val": 0.05, "test": 0.15}
# Std floor: a feature that never varies in the train split (e.g. a joint that never moves
# relative to the root) would otherwise divide by zero when z-scoring.
STD_FLOOR = 1e-4
_SPLIT_STREAM = 7_411  # extra seed word so the split shuffle differs from motion 0's stream
# The most motions a corpus holds: far beyond HumanML3D's 14,616 (a million take hours of
# two cores and tens of GB), so that a typo fails at once instead of running out of memory.
MAX_MOTIONS = 1_000_000
# What a corpus folder holds when `build_corpus` wrote it; anything else is the user's.
FOLDERS = (MOTIONS, JOINTS, TEXTS, GROUND_TRUTH)
CORPUS_ENTRIES = frozenset({*FOLDERS, *(f"{s}.txt" for s in SPLITS), *STATISTICS, "corpus.json",
                            LOCK_FILE})


def split_assignment(num_motions: int, seed: int) -> list[str]:
    """Split name of each motion index (80/5/15, deterministic in seed and size)."""
    order = np.random.default_rng([seed, _SPLIT_STREAM]).permutation(num_motions)
    n_train = int(round(num_motions * SPLITS["train"]))
    n_val = int(round(num_motions * SPLITS["val"]))
    names = ["test"] * num_motions
    for rank, index in enumerate(order):
        names[index] = "train" if rank < n_train else "val" if rank < n_train + n_val else "test"
    return names


def motion_id(index: int) -> str:
    return f"{index:06d}"


def _build_one(job: tuple[str, int, int, str, int]) -> dict:
    """Generate and write motion `index`; returns its statistics for the parent."""
    root, seed, index, split, version = job
    root = Path(root)
    rng = np.random.default_rng([seed, index])
    motion = sample_motion(rng, version)
    features = joints_to_features(motion.joints.astype(np.float32), "t2m").astype(np.float32)
    captions = make_captions(motion.segments, rng, held_out=split != "train")
    write_motion(root, motion_id(index), features, motion.segments, captions)
    stats = {"split": split, "frames": len(features), "segments": len(motion.segments),
             "actions": [s.action for s in motion.segments]}
    if split == "train":
        x = features.astype(np.float64)
        stats["mean"], stats["m2"] = x.mean(0), ((x - x.mean(0)) ** 2).sum(0)
    return stats


def write_motion(root: Path, mid: str, features: np.ndarray, segments: list[Segment],
                 captions: list[Caption]) -> None:
    """One motion of a corpus: its features (t, 263) float32, the joints recovered from
    them, its caption lines and its ground truth (actions and each caption's segments)."""
    np.save(motion_file(root, mid), features)
    np.save(joints_file(root, mid), features_to_joints(features, "t2m").astype(np.float32))
    lines = [f"{c.text}#{pos_tag(c.text)}#0.0#0.0" for c in captions]
    texts_file(root, mid).write_text("\n".join(lines) + "\n")
    actions = [{"action": s.action, "params": s.params, "start": s.start, "end": s.end}
               | ({"with": {"action": s.overlay[0], "params": s.overlay[1]}} if s.overlay else {})
               for s in segments]
    truth = {
        "id": mid, "fps": 20.0, "num_frames": int(len(features)), "actions": actions,
        "captions": [{"text": c.text, "template": c.template, "segments": [
            {"text": text, "action": s.action, "start": s.start, "end": s.end}
            for text, s in zip(c.segments, segments)]} for c in captions],
    }
    ground_truth_file(root, mid).write_text(json.dumps(truth, indent=1) + "\n")


def _init_worker(parent: int) -> None:
    torch.set_num_threads(1)
    _end_with(parent)


def _end_with(parent: int) -> None:
    """Have the kernel end this worker when `parent` ends (Linux). Killed (SIGKILL, a job's
    time limit), the parent left its workers drawing motions for nobody, each printing a
    BrokenPipeError traceback when it tried to hand one over."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    PR_SET_PDEATHSIG = 1  # <sys/prctl.h>
    ctypes.CDLL(None).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:  # it ended before the request: nothing would signal us
        os._exit(0)


def _corpus_of(path: Path) -> dict | None:
    """The corpus.json of `path`, or None when it holds none (or an unreadable one)."""
    try:
        return json.loads((path / "corpus.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def build_corpus(out: str | Path, num_motions: int, seed: int = 0, workers: int = 1,
                 overwrite: bool = False, progress: bool = True, version: int = VERSION) -> Path:
    """Write a corpus of `num_motions` motions (sampled as corpus `version` does) to `out`;
    returns the path.

    Leaves a folder that already holds this very corpus, whole, untouched (one with a file
    of it missing is rebuilt: the same bytes). Refuses, unless
    `overwrite`, a non-empty `out` that is not a corpus, and a corpus folder holding
    anything a rebuild would delete (text_segments/, text_features/, ...).
    """
    out = Path(out)
    if not 1 <= num_motions <= MAX_MOTIONS:
        raise SegmoError(f"build_corpus: num_motions must be in [1, {MAX_MOTIONS:,}], got "
                         f"{num_motions}")
    if workers < 1:
        raise SegmoError(f"build_corpus: workers must be >= 1, got {workers}")
    if version not in VERSIONS:
        raise SegmoError(f"build_corpus: version must be one of {', '.join(map(str, VERSIONS))}, "
                         f"got {version!r}")
    if out.exists() and not out.is_dir():
        raise SegmoError(f"build_corpus: {out} exists and is not a folder")
    check_replaceable_place(out)  # before the lock, whose file would land there
    with FolderLock(out, "segmo synth"):
        existing = _corpus_of(out)
        wanted = {"version": version, "seed": seed, "num_motions": num_motions}
        extra = sorted(p.name for p in out.iterdir() if p.name not in CORPUS_ENTRIES)
        if existing is not None and all(existing.get(k) == v for k, v in wanted.items()):
            missing = _missing_file(out, num_motions)
            if missing is None:
                return out  # deterministic: rebuilding would write the same bytes
            if extra and not overwrite:
                raise SegmoError(f"build_corpus: {out} holds this corpus with {missing} missing, "
                                 f"and {', '.join(extra)}, which a rebuild would delete; pass "
                                 "overwrite=True (--overwrite) or restore the file")
            return _build(out, num_motions, seed, workers, progress, version)  # the same bytes
        if existing is None and any(p.name != LOCK_FILE for p in out.iterdir()) and not overwrite:
            raise SegmoError(f"build_corpus: {out} is not empty and holds no corpus.json; pass "
                             "overwrite=True (--overwrite) to replace it")
        if existing is not None and extra and not overwrite:
            raise SegmoError(
                f"build_corpus: {out} holds another corpus (version {existing.get('version')}, "
                f"seed {existing.get('seed')}, {existing.get('num_motions')} motions) and "
                f"{', '.join(extra)}, which a rebuild would delete; pass overwrite=True "
                "(--overwrite) or choose another folder")
        return _build(out, num_motions, seed, workers, progress, version)


def _missing_file(out: Path, num_motions: int) -> Path | None:
    """The first file of a `num_motions` corpus that `out` lacks (relative to it), or None:
    a corpus.json alone said the corpus was there after its files were deleted."""
    ids = [motion_id(i) for i in range(num_motions)]
    files = [split_file(out, s) for s in SPLITS] + list(stats_files(out)) + [
        path(out, mid) for mid in ids
        for path in (motion_file, joints_file, texts_file, ground_truth_file)]
    return next((f.relative_to(out) for f in files if not f.is_file()), None)


def _build(out: Path, num_motions: int, seed: int, workers: int, progress: bool,
           version: int) -> Path:
    # replacing_folder follows a symbolic link `out` and replaces its target: renaming the
    # link itself left the corpus where the link was and the target empty.
    with replacing_folder(out) as tmp:
        for sub in FOLDERS:
            (tmp / sub).mkdir()
        splits = split_assignment(num_motions, seed)
        jobs = [(str(tmp), seed, i, splits[i], version) for i in range(num_motions)]
        if workers > 1:
            context = multiprocessing.get_context("fork" if os.name == "posix" else "spawn")
            with context.Pool(workers, initializer=_init_worker, initargs=(os.getpid(),)) as pool:
                results = list(tqdm(pool.imap(_build_one, jobs, chunksize=4), total=num_motions,
                                    desc="synth", disable=not progress))
        else:
            # One motion is too small for intra-op threads; they only spin (and restore
            # the caller's setting afterwards).
            threads = torch.get_num_threads()
            torch.set_num_threads(1)
            try:
                results = [_build_one(j) for j in tqdm(jobs, desc="synth", disable=not progress)]
            finally:
                torch.set_num_threads(threads)
        _write_summary(tmp, results, splits, seed, num_motions, version)
    return out


def _write_summary(root: Path, results: list[dict], splits: list[str], seed: int, n: int,
                   version: int) -> None:
    for name in SPLITS:
        ids = [motion_id(i) for i in range(n) if splits[i] == name]
        split_file(root, name).write_text("".join(f"{i}\n" for i in ids))
    # Chan et al.'s pairwise merge of (count, mean, M2), in index order.
    count, mean, m2 = 0, None, None
    for r in results:
        if "mean" not in r:
            continue
        c = r["frames"]
        if mean is None:
            count, mean, m2 = c, r["mean"].copy(), r["m2"].copy()
            continue
        delta = r["mean"] - mean
        total = count + c
        mean = mean + delta * c / total
        m2 = m2 + r["m2"] + delta**2 * count * c / total
        count = total
    if mean is None:  # a corpus too small to have a train motion
        raise SegmoError("build_corpus: the train split is empty; use more motions")
    std = np.maximum(np.sqrt(m2 / count), STD_FLOOR)
    mean_file, std_file = stats_files(root)
    np.save(mean_file, mean.astype(np.float32))
    np.save(std_file, std.astype(np.float32))
    frames = np.array([r["frames"] for r in results])
    hist = np.bincount([r["segments"] for r in results], minlength=6)[1:]
    action_counts: dict[str, int] = {}
    for r in results:
        for a in r["actions"]:
            action_counts[a] = action_counts.get(a, 0) + 1
    summary = {
        "name": "segmo-synth", "version": version, "seed": seed, "num_motions": n, "fps": 20.0,
        "skeleton": "t2m", "actions": sorted(ACTIONS), "held_out_templates": list(HELD_OUT_TEMPLATES),
        "held_out_note": "these caption templates appear only in val/test captions",
        "std_floor": STD_FLOOR,
        "statistics": {
            "splits": {s: splits.count(s) for s in SPLITS},
            "frames": {"mean": round(float(frames.mean()), 2), "min": int(frames.min()),
                       "max": int(frames.max()), "total": int(frames.sum())},
            "segments_per_motion": {str(k + 1): int(v) for k, v in enumerate(hist)},
            "action_counts": dict(sorted(action_counts.items())),
        },
    }
    (root / "corpus.json").write_text(json.dumps(summary, indent=1) + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(prog="segmo synth", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, type=replaced_folder, help="output folder")
    parser.add_argument("--num-motions", type=positive_int, default=2000)
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--workers", type=positive_int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--overwrite", action="store_true",
                        help="replace a folder that holds something else than this corpus")
    parser.add_argument("--version", type=int, choices=VERSIONS, default=VERSION,
                        help="corpus version: 3 a short action beside a long one (default), 2 "
                        "durations follow the action, 1 the first corpus (nearly equal durations), "
                        "4 version 3 with a rig a BVH hierarchy follows exactly")
    args = parser.parse_args(argv)
    path = build_corpus(args.out, args.num_motions, args.seed, args.workers, args.overwrite,
                        version=args.version)
    print(f"{args.num_motions} motions in {path}")


if __name__ == "__main__":
    main()
