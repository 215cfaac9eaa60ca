"""More training motions for a built-in corpus, its val and test splits unchanged.

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

The last line printed is JSON: the train motions of DATA, the ones added, and OUT.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

from segmo.data.layout import (
    SPLITS,
    STATISTICS,
    ground_truth_file,
    joints_file,
    motion_file,
    read_split,
    split_file,
)
from segmo.errors import SegmoError
from segmo.text.captions import texts_file

# What one motion of a corpus is: its features, joints, captions and ground truth.
MOTION_FILES = (motion_file, joints_file, texts_file, ground_truth_file)


def corpus_info(root: Path, flag: str) -> dict:
    """corpus.json of `root`, or SegmoError naming the argument."""
    try:
        return json.loads((root / "corpus.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SegmoError(f"{flag} {root}: no corpus.json (not a corpus of `segmo synth`)") from None
    except (OSError, ValueError) as error:
        raise SegmoError(f"{flag} {root}/corpus.json: unreadable ({error})") from None


def link(source: Path, target: Path) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system, or one without hard links
        shutil.copy2(source, target)


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
    tmp = out.parent / f"{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        for source, ids in ((data, [i for s in SPLITS for i in read_split(data, s)]), (add, added)):
            for mid in ids:
                for path_of in MOTION_FILES:
                    target = path_of(tmp, mid)
                    target.parent.mkdir(parents=True, exist_ok=True)
                    link(path_of(source, mid), target)
        for name in STATISTICS:
            shutil.copy2(data / name, tmp / name)
        for split in SPLITS:
            ids = train + added if split == "train" else read_split(data, split)
            split_file(tmp, split).write_text("".join(f"{i}\n" for i in ids))
        info = dict(base, train_added={"from": str(add), "num_motions": bigger["num_motions"],
                                       "motions": len(added)})
        (tmp / "corpus.json").write_text(json.dumps(info, indent=1) + "\n")
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"train": len(train), "added": len(added), "out": str(out)}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="the corpus to grow")
    parser.add_argument("--add", type=Path, required=True,
                        help="a bigger corpus of the same seed and version")
    parser.add_argument("--out", type=Path, required=True, help="a new folder")
    args = parser.parse_args(argv)
    try:
        result = grow_train(args.data, args.add, args.out)
    except SegmoError as error:
        sys.exit(f"grow_train: {error}")
    print(f"{result['train']} train motions of {args.data} + {result['added']} of {args.add} "
          f"-> {args.out}")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
