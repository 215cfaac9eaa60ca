"""Run the rule segmenter over the real KIT-ML captions and print what it does.

Usage: python tools/segment_kitml.py [--annotations PATH] [--samples 25] [--seed 0] [--multi]

Prints the histogram of segment counts over all captions, the time taken, and a seeded
random sample of outputs (``--multi``: sampled among captions that were split) to be
checked by eye.
"""

from __future__ import annotations

import argparse
import json
import random
import time
from collections import Counter
from pathlib import Path

from segmo.text.rules import RuleSegmenter

DEFAULT = Path(__file__).resolve().parents[1].parent / "shared" / "fixtures" / "kitml" / "annotations.json"


def load_captions(path: Path) -> list[str]:
    """All caption texts of a KIT-ML annotations file, in file order."""
    data = json.loads(path.read_text(encoding="utf-8"))
    return [a["text"] for entry in data.values() for a in entry["annotations"]]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--annotations", type=Path, default=DEFAULT)
    parser.add_argument("--samples", type=int, default=25)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--multi", action="store_true", help="sample only captions that were split")
    args = parser.parse_args(argv)
    if not args.annotations.is_file():
        raise SystemExit(f"segment_kitml: no annotations file at {args.annotations}")
    captions = load_captions(args.annotations)
    segmenter = RuleSegmenter()
    t0 = time.perf_counter()
    results = segmenter.segment(captions)
    elapsed = time.perf_counter() - t0
    histogram = Counter(len(r) for r in results)
    print(f"{len(captions)} captions ({len(set(captions))} distinct) in {elapsed:.2f} s")
    for count in sorted(histogram):
        print(f"  {count} segment(s): {histogram[count]:5d}  ({100 * histogram[count] / len(captions):.1f} %)")
    pool = [i for i, r in enumerate(results) if len(r) > 1] if args.multi else list(range(len(results)))
    rng = random.Random(args.seed)
    for i in sorted(rng.sample(pool, min(args.samples, len(pool)))):
        print(f"\n{captions[i]!r}")
        for s in results[i]:
            print(f"    - {s}")


if __name__ == "__main__":
    main()
