"""How much the built-in corpus' segment durations give away: the spread of durations
within a motion, and how well the text-free equal split grounds the segments.

For every motion of the split with ≥ 2 ground-truth segments (`DIR/segments/<id>.json`):
the ratio longest / shortest segment (frames). For every caption with ≥ 2 segments, as
`segmo.evaluation.grounding.grounding_accuracy` scores its uniform baseline: the motion's
tokens (frames // FRAMES_PER_TOKEN) split evenly into as many spans as the caption has
segments (`uniform_spans`), compared with the true spans (R@1 at IoU 0.3/0.5/0.7, mIoU).
Prints a Markdown table and a final JSON line.

    python tools/corpus_durations.py --data /tmp/c2000 --split test
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from segmo.cli import run
from segmo.data.layout import ground_truth_file, has_ground_truth, read_ground_truth, read_split
from segmo.errors import ArgumentParser, SegmoError
from segmo.evaluation.grounding import grounding_metrics
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.segmentation import uniform_spans

THRESHOLDS = (0.3, 0.5, 0.7)


def measure(data: Path, split: str) -> dict:
    ratios, pred, truth = [], [], []
    ids = read_split(data, split)
    for motion_id in ids:
        record = read_ground_truth(data, motion_id)  # spans checked: start < end, in the motion
        missing = [key for key in ("actions", "num_frames", "captions") if key not in record]
        if missing:
            raise SegmoError(f"{ground_truth_file(data, motion_id)}: no {missing[0]!r}; not a "
                             "ground-truth file of the built-in corpus")
        lengths = [a["end"] - a["start"] for a in record["actions"]]
        if len(lengths) >= 2:
            ratios.append(max(lengths) / min(lengths))
        n = record["num_frames"] // FRAMES_PER_TOKEN
        for caption in record["captions"]:
            segments = caption["segments"]
            if not 2 <= len(segments) <= n:
                continue
            pred += [(FRAMES_PER_TOKEN * s, FRAMES_PER_TOKEN * e) for s, e in uniform_spans(n, len(segments))]
            truth += [(s["start"], s["end"]) for s in segments]
    if not ratios:
        raise SegmoError(f"--data {data}: no {split} motion with ≥ 2 segments")
    r = np.asarray(ratios)
    return {"split": split, "motions": len(ids), "multi_segment_motions": len(ratios),
            "segments": len(truth),
            "ratio": {"median": float(np.median(r)), "p90": float(np.percentile(r, 90)), "max": float(r.max())},
            "uniform": grounding_metrics(pred, truth, thresholds=THRESHOLDS)}


def table(result: dict) -> str:
    r, u = result["ratio"], result["uniform"]
    return "\n".join([
        "| longest/shortest: median | p90 | max | uniform R@1 IoU0.3 | IoU0.5 | IoU0.7 | mIoU |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
        f"| {r['median']:.2f} | {r['p90']:.2f} | {r['max']:.2f} | {u['R@1,IoU=0.3']:.3f} | "
        f"{u['R@1,IoU=0.5']:.3f} | {u['R@1,IoU=0.7']:.3f} | {u['mIoU']:.3f} |"])


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(prog="corpus_durations.py", description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, type=Path, help="built-in corpus folder")
    parser.add_argument("--split", default="test")
    args = parser.parse_args(argv)
    if not has_ground_truth(args.data):
        parser.error(f"--data {args.data}: no segments/ folder (ground truth of the built-in corpus)")
    result = measure(args.data, args.split)
    print(f"{result['multi_segment_motions']} of {result['motions']} {args.split} motions with ≥ 2 "
          f"segments; {result['segments']} caption segments\n")
    print(table(result))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run("corpus_durations.py", main, sys.argv[1:])
