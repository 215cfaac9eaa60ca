"""More training motions for a built-in corpus, its val and test splits unchanged: from a
bigger corpus of the same seed (--add), or cut from its own train motions (--segment-crops).

Motion i of `segmo synth` depends only on the seed, the corpus version and i, so a corpus
of more motions (same seed and version) holds the smaller one's motions and more. This
writes OUT = the corpus DATA (its motions, captions, ground truth, splits and statistics)
plus the train motions of the bigger corpus ADD beyond DATA's last motion; val and test
are DATA's, so a model trained on OUT is measured on exactly the motions and captions of
one trained on DATA. The statistics (Mean.npy, Std.npy) stay DATA's, as the tokenizer's
do. Files are hard links where the file system allows it (copies elsewhere); the
segmo writers replace files instead of changing them, so neither corpus can change the
other's. Text segments and features are not copied: run `segmo segment-texts` and
`segmo encode-texts` on OUT (they are keyed by caption and fast).

    segmo synth --out data/v8 --num-motions 8000 --seed 0
    python tools/grow_train.py --data data/v3 --add data/v8 --out data/v3x
    segmo segment-texts --data data/v3x --backend rule
    segmo encode-texts --data data/v3x --encoder minilm --segments rule

--segment-crops adds no new motion of the corpus' generator: each train motion of two or
more actions also gives every run of consecutive actions but the whole (a 4-action motion
gives 3 + 2 + 2 + 1 + 1 + 1 + 1 + 1 + 1 = 9 minus the ones too short) as a motion of its own,
its frames cut from the motion's features at the true action boundaries (the features are
root-relative, so a cut is a motion that starts at the origin), at least `MIN_FRAMES`
frames long, worded by the corpus' own captions of the trained templates
(`segmo.synth.captions.make_captions` on the actions and their parameters, seeded by the
crop's id). So a short action also lies at the end, at the start and alone in the data, and
2- and 3-action sequences come from every part of the longer motions, while every frame
stays one of the 1,600 train motions'. The crop of motion 000123's actions 1 and 2 (from 0)
is 000123_1_3.

    python tools/grow_train.py --data data/v3 --segment-crops --out data/v3c

The last line printed is JSON: the train motions of DATA, the ones added, and OUT. A bad
argument or corpus is one line on stderr (exit status 2), and leaves no OUT.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from segmo.cli import run
from segmo.data.layout import (
    SPLITS,
    STATISTICS,
    ground_truth_file,
    joints_file,
    motion_file,
    read_split,
    split_file,
)
from segmo.errors import ArgumentParser, SegmoError
from segmo.synth.captions import make_captions
from segmo.synth.corpus import write_motion
from segmo.synth.sequence import MIN_FRAMES, Segment
from segmo.text.captions import texts_file

# What one motion of a corpus is: its features, joints, captions and ground truth.
MOTION_FILES = (motion_file, joints_file, texts_file, ground_truth_file)


def corpus_info(root: Path, flag: str) -> dict:
    """corpus.json of `root`, or SegmoError naming the argument; checked here too: its
    three split files (otherwise a missing val.txt is found after the motions are linked)."""
    try:
        info = json.loads((root / "corpus.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SegmoError(f"{flag} {root}: no corpus.json (not a corpus of `segmo synth`)") from None
    except (OSError, ValueError) as error:
        raise SegmoError(f"{flag} {root}/corpus.json: unreadable ({error})") from None
    for split in SPLITS:
        if not split_file(root, split).is_file():
            raise SegmoError(f"{flag} {root}: no {split}.txt; a corpus of `segmo synth` has "
                             "train.txt, val.txt and test.txt")
    return info


def link_motion(source: Path, root: Path, mid: str) -> None:
    """Motion `mid`'s files of corpus `source` into `root`: hard links, or copies where the
    file system has none."""
    for path_of in MOTION_FILES:
        target = path_of(root, mid)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.link(path_of(source, mid), target)
        except OSError:  # another file system, or one without hard links
            shutil.copy2(path_of(source, mid), target)


def grow_train(data: Path, add: Path, out: Path) -> dict:
    """Write OUT (see the module docstring); returns the counts."""
    base, bigger = corpus_info(data, "--data"), corpus_info(add, "--add")
    for key in ("name", "version", "seed"):
        if base.get(key) != bigger.get(key):
            raise SegmoError(f"--add {add}: {key} {bigger.get(key)!r}, --data {data} has "
                             f"{base.get(key)!r}; both must be `segmo synth` corpora of the "
                             "same version and seed")
    first_new = int(base["num_motions"])
    if int(bigger["num_motions"]) <= first_new:
        raise SegmoError(f"--add {add}: {bigger['num_motions']} motions, no more than --data's "
                         f"{first_new}")
    if out.exists():
        raise SegmoError(f"--out {out}: exists; choose a new folder")
    train = read_split(data, "train")
    added = [i for i in read_split(add, "train") if int(i) >= first_new]
    probe = train[0]  # the same motion in both, byte for byte, or they are not one sequence
    if motion_file(data, probe).read_bytes() != motion_file(add, probe).read_bytes():
        raise SegmoError(f"--add {add}: motion {probe} differs from --data's; not the same corpus")

    def write_added(tmp: Path) -> list[str]:
        for mid in added:
            link_motion(add, tmp, mid)
        return added

    info = {"train_added": {"from": str(add), "num_motions": bigger["num_motions"],
                            "motions": len(added)}}
    return write_grown(data, out, write_added, info)


def segment_crops(data: Path, out: Path) -> dict:
    """Write OUT = DATA and the segment crops of its train motions (module docstring)."""
    corpus_info(data, "--data")
    if out.exists():
        raise SegmoError(f"--out {out}: exists; choose a new folder")

    def write_crops(tmp: Path) -> list[str]:
        added = []
        for mid in read_split(data, "train"):
            path = ground_truth_file(data, mid)
            try:
                actions = json.loads(path.read_text(encoding="utf-8"))["actions"]
                spans = [(int(a["start"]), int(a["end"])) for a in actions]
                features = np.load(motion_file(data, mid))
            except (OSError, ValueError, KeyError, TypeError) as error:
                raise SegmoError(f"--data {data}: motion {mid}: {error!r}") from None
            if any(not 0 <= s < e <= len(features) for s, e in spans):
                raise SegmoError(f"{path}: action spans {spans} do not lie in the motion's "
                                 f"{len(features)} frames")
            for first in range(len(actions)):
                for last in range(first + 1, len(actions) + 1):
                    if last - first == len(actions):
                        continue
                    start, end = spans[first][0], spans[last - 1][1]
                    if end - start < MIN_FRAMES:
                        continue
                    added.append(write_crop(tmp, f"{mid}_{first}_{last}",
                                            features[start:end], actions[first:last], start))
        return added

    return write_grown(data, out, write_crops, {"segment_crops": True})


def write_crop(root: Path, mid: str, features: np.ndarray, actions: list[dict], offset: int) -> str:
    """One crop as a corpus motion (`segmo.synth.corpus.write_motion`); → its id."""
    segments = [Segment(a["action"], a["params"],
                        (a["with"]["action"], a["with"]["params"]) if "with" in a else None,
                        a["start"] - offset, a["end"] - offset) for a in actions]
    captions = make_captions(segments, np.random.default_rng(list(mid.encode())), held_out=False)
    for path_of in MOTION_FILES:
        path_of(root, mid).parent.mkdir(parents=True, exist_ok=True)
    write_motion(root, mid, np.ascontiguousarray(features, dtype=np.float32), segments, captions)
    return mid


def write_grown(data: Path, out: Path, write_added: Callable[[Path], list[str]],
                info: dict) -> dict:
    """OUT = DATA's motions (linked), its statistics, val and test, and the train motions
    `write_added(folder)` writes; built in a temporary folder renamed at the end, so a
    failure leaves no OUT."""
    train = read_split(data, "train")
    tmp = out.parent / f"{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        for mid in (i for s in SPLITS for i in read_split(data, s)):
            link_motion(data, tmp, mid)
        added = write_added(tmp)
        for name in STATISTICS:
            shutil.copy2(data / name, tmp / name)
        for split in SPLITS:
            ids = train + added if split == "train" else read_split(data, split)
            split_file(tmp, split).write_text("".join(f"{i}\n" for i in ids))
        (tmp / "corpus.json").write_text(json.dumps(dict(corpus_info(data, "--data"), **info),
                                                    indent=1) + "\n")
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"train": len(train), "added": len(added), "out": str(out)}


def main(argv: list[str] | None = None) -> dict:
    """Write OUT, print a line and the JSON line; the counts are returned. SegmoError (or
    OSError) for a bad argument or corpus: no OUT is left then."""
    parser = ArgumentParser(prog="grow_train.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="the corpus to grow")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--add", type=Path, help="a bigger corpus of the same seed and version")
    source.add_argument("--segment-crops", action="store_true",
                        help="add the runs of consecutive actions of DATA's own train motions")
    parser.add_argument("--out", type=Path, required=True, help="a new folder")
    args = parser.parse_args(argv)
    result = (segment_crops(args.data, args.out) if args.segment_crops
              else grow_train(args.data, args.add, args.out))
    added = "segment crops" if args.segment_crops else f"of {args.add}"
    print(f"{result['train']} train motions of {args.data} + {result['added']} {added} "
          f"-> {args.out}")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run("grow_train.py", main, sys.argv[1:])
