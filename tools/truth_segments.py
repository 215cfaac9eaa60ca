"""The built-in corpus' ground-truth text segments as a segmentation source.

Writes ``DATA/text_segments/truth/<id>.txt`` (one line per caption, its ground-truth
segments joined by '#') through the same writer as `segmo segment-texts` (atomic files,
the manifest of caption hashes, the folder lock), from ``DATA/segments/<id>.json``. Train
and evaluate with it as with any other source, to see how the quality of the segmentation
moves alignment (the paper's Fig. 4 axis "segmentation source"):

    python tools/truth_segments.py --data data/synth
    segmo encode-texts --data data/synth --encoder minilm --segments truth
    segmo fit --config configs/mask/synthetic.yaml --data.root data/synth \\
        --data.text_segments truth ...

It also prints how often the rule extractor (``text_segments/rule``, when present) gives
exactly the ground-truth segments, and the last line is JSON.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from segmo.cli import run
from segmo.data.layout import has_ground_truth, read_ground_truth
from segmo.errors import ArgumentParser, SegmoError
from segmo.text.captions import read_caption_lines, texts_file
from segmo.text.extract import segment_folder


class TruthSegmenter:
    """Answers each caption of the corpus with its ground-truth segments (a caption text
    found with two different segmentations is an error: the corpus is inconsistent)."""

    name = "truth"

    def __init__(self, data: Path) -> None:
        self.table: dict[str, list[str]] = {}
        for path in sorted((data / "segments").glob("*.json")):
            for caption in read_ground_truth(data, path.stem)["captions"]:
                segments = [s["text"] for s in caption["segments"]]
                if self.table.setdefault(caption["text"], segments) != segments:
                    raise SegmoError(f"{path}: caption {caption['text']!r} has two ground truths")

    def segment(self, texts: list[str]) -> list[list[str]]:
        missing = [t for t in texts if t not in self.table]
        if missing:
            raise SegmoError(f"truth: {len(missing)} caption(s) without ground truth, first {missing[0]!r}")
        return [self.table[t] for t in texts]


def rule_agreement(data: Path, truth: TruthSegmenter) -> dict[str, float] | None:
    """Share of captions whose rule segments equal the ground truth, and whose number of
    segments does (None: no rule folder)."""
    rule = data / "text_segments" / "rule"
    if not rule.is_dir():
        return None
    same = same_count = total = 0
    for path in sorted(rule.glob("*.txt")):
        if not texts_file(data, path.stem).is_file():
            continue  # rule segments of a motion the folder no longer has
        captions = [line.caption for line in read_caption_lines(texts_file(data, path.stem))]
        answers = path.read_text(encoding="utf-8").splitlines()
        for caption, answer in zip(captions, answers, strict=False):
            if caption in truth.table:
                total += 1
                same += answer.split("#") == truth.table[caption]
                same_count += len(answer.split("#")) == len(truth.table[caption])
    return {"captions": float(total), "rule_equals_truth": same / max(total, 1),
            "rule_count_equals_truth": same_count / max(total, 1)}


def main(argv: list[str] | None = None) -> dict:
    p = ArgumentParser(prog="truth_segments.py", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, required=True, help="a built-in corpus folder")
    p.add_argument("--overwrite", action="store_true", help="redo every file")
    args = p.parse_args(argv)
    if not args.data.is_dir():
        p.error(f"--data {args.data}: no such folder")
    if not has_ground_truth(args.data):
        p.error(f"--data {args.data}: no segments/<id>.json (only the built-in corpus has ground truth)")
    truth = TruthSegmenter(args.data)
    summary = segment_folder(args.data, truth, "truth", overwrite=args.overwrite, progress=False)
    agreement = rule_agreement(args.data, truth)
    print(f"truth segments: {summary['captions']} captions of {summary['motions']} motions -> "
          f"{args.data / 'text_segments' / 'truth'} (processed {summary['processed_files']} files)")
    if agreement is not None:
        print(f"the rule extractor gives exactly the ground truth for "
              f"{100 * agreement['rule_equals_truth']:.1f}% of {int(agreement['captions'])} captions, "
              f"as many segments for {100 * agreement['rule_count_equals_truth']:.1f}%")
    result = {"summary": {k: summary[k] for k in ("motions", "captions", "processed_files")},
              "rule_agreement": agreement}
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run("truth_segments.py", main, sys.argv[1:])
