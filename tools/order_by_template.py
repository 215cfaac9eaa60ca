"""Action order of generated motions by the template of their caption, on the built-in corpus.

    python tools/order_by_template.py --model B --data data/synth \\
        --action-classifier models/action_classifier [--split test] [--repeats 2] [--seed 0] \\
        [--word-text caption|segments] [--segment-timing predicted|none|truth] \\
        [--remasking confidence|segments] [--segment-guidance W] [--choice-temperature TAU] \\
        [--compose FRAMES] [--reconstruction]

`segmo evaluate` scores action order on each motion's first caption. The corpus words its
captions with ordering templates (`segmo.synth.captions.TEMPLATES`), two of them only in
val/test captions (`HELD_OUT_TEMPLATES`: "…, followed by …" and "before …", which names the
last action first). This tool generates the first caption of every motion of two or more
segments (at its length, `--repeats` seeds each), reads the action sequence with the
action classifier and reports the sequence accuracy per template, over the trained and the
held-out templates, over all, and by the caption's true number of actions (2, 3, 4-5, and
3+: `by_num_actions`; `segmo evaluate` buckets by the segments the model is given, which
the text extractor may miscount); the last stdout line is the JSON object. --word-text:
what a words model's word keys read (`SamplingOptions.word_text`; default: the bundle's).
--segment-timing, for a mask transformer trained with segment timing: the spans its timing
head predicts, none, or "truth": each segment's true duration from the corpus (the model's
own text segments where it finds as many as the caption has actions, else the corpus'
segment texts), the ceiling of what predicted timing can give. --remasking: which tokens
each decoding step masks again (`SamplingOptions.remasking`). --segment-guidance: the weight
of per-segment guidance (`SamplingOptions.segment_guidance`). --choice-temperature: MaskGIT's
randomised remasking (`SamplingOptions.choice_temperature`). --reconstruction also reads
each motion's tokenizer reconstruction (real motion → the bundle's tokenizer → decoded) and
splits the generated accuracy by it: `reconstruction` (the tokenizer's ceiling on the same
captions), `generated_where_reconstructed` and `generated_where_not` (the generator on the
captions whose reconstruction is read right, and on the others), each by number of actions.
Every bucket also counts its captions that no repeat got right (`never_right`).
"""

from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path
from typing import get_args

import numpy as np
import torch

from segmo.data.layout import first_captions, read_motion
from segmo.errors import SegmoError, non_negative_float, positive_int
from segmo.evaluation.metrics import segment_bucket
from segmo.files import json_text
from segmo.generation.sampling import Remasking, SegmentTiming, WordText
from segmo.models.action_classifier import collapse
from segmo.models.pretrained import load_pretrained
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.pipeline import SegMo
from segmo.pipeline.compose import COMPOSE_MIN_PART, valid_transition
from segmo.synth.captions import HELD_OUT_TEMPLATES

BATCH = 32


def multi_segment_rows(data: Path, split: str, max_frames: int) -> list[dict]:
    """The first caption of each motion of two or more segments: text, template, the
    collapsed true action sequence, frames (a whole number of tokens)."""
    rows = []
    for motion_id, record, caption in first_captions(data, split):
        frames = min(record["num_frames"], max_frames) // FRAMES_PER_TOKEN * FRAMES_PER_TOKEN
        if len(caption["segments"]) < 2 or frames < FRAMES_PER_TOKEN:
            continue
        rows.append({"id": motion_id, "text": caption["text"], "template": caption["template"], "frames": frames,
                     "actions": collapse([s["action"] for s in caption["segments"]]),
                     "num_actions": len(caption["segments"]),
                     "segments": [s["text"] for s in caption["segments"]],
                     "durations": [s["end"] - s["start"] for s in caption["segments"]]})
    if not rows:
        raise SegmoError(f"--data {data}: no {split} motion whose first caption has two or more segments")
    return rows


def true_timing(model: SegMo, chunk: list[dict]) -> dict:
    """`SegMo.generate`'s segments and durations for the corpus' true timing: the model's
    own segments where it finds one per true action, else the corpus' segment texts."""
    own = model.segment_texts([r["text"] for r in chunk])
    segments = [s if len(s) == len(r["durations"]) else r["segments"] for s, r in zip(own, chunk)]
    return {"segments": segments, "durations": [r["durations"] for r in chunk]}


def composed_parts(row: dict, segments: list[str], transition: int) -> list[tuple[str, int]]:
    """`SegMo.compose`'s parts for one row: each segment with its true share of the frames
    left beside the transitions, in whole tokens, at least `COMPOSE_MIN_PART` frames."""
    left = row["frames"] - (len(segments) - 1) * transition
    total = sum(row["durations"])
    return [(text, max(COMPOSE_MIN_PART, round(left * d / total / FRAMES_PER_TOKEN) * FRAMES_PER_TOKEN))
            for text, d in zip(segments, row["durations"])]


def order_by_template(model: SegMo, classifier, rows: list[dict], repeats: int, seed: int,
                      truth: bool = False, reconstructed: np.ndarray | None = None,
                      compose: int | None = None) -> dict:
    """Sequence accuracy of `repeats` generations of each row, by template, by number of
    actions and over the trained / held-out templates; with `reconstructed` (one bool per
    row, `reconstructions_read_right`) also split by whether the tokenizer keeps the actions.
    `compose`: each row generated segment by segment, transitions of that many frames."""
    hits = np.zeros((len(rows), repeats), dtype=bool)
    if compose is not None:
        segments = true_timing(model, rows)["segments"]
        for repeat in range(repeats):
            for i, row in enumerate(rows):
                out = model.compose(composed_parts(row, segments[i], compose), compose,
                                    generator=torch.Generator().manual_seed(seed + 1000 * repeat + i))
                features = out.features[0, : int(out.lengths[0])].float().cpu().numpy()
                hits[i, repeat] = classifier.predict_sequence(features) == row["actions"]
    else:
        for repeat in range(repeats):
            for start in range(0, len(rows), BATCH):
                chunk = rows[start:start + BATCH]
                out = model.generate([r["text"] for r in chunk], [r["frames"] for r in chunk],
                                     generator=torch.Generator().manual_seed(seed + 1000 * repeat + start),
                                     **(true_timing(model, chunk) if truth else {}))
                for k, row in enumerate(chunk):
                    features = out.features[k, : int(out.lengths[k])].float().cpu().numpy()
                    hits[start + k, repeat] = classifier.predict_sequence(features) == row["actions"]

    def entry(indices: list[int], of: np.ndarray = hits) -> dict:
        h = of[indices].reshape(len(indices), -1)
        return {"sequence_accuracy": float(h.mean()), "motions": len(indices),
                "never_right": int((~h.any(1)).sum())}

    def by_actions(indices: list[int], of: np.ndarray = hits) -> dict:
        buckets: dict[str, list[int]] = defaultdict(list)
        for i in indices:
            buckets[segment_bucket(rows[i]["num_actions"])].append(i)
            if rows[i]["num_actions"] >= 3:
                buckets["3+"].append(i)
        return {k: entry(v, of) for k, v in sorted(buckets.items())}

    templates: dict[str, list[int]] = defaultdict(list)
    for i, row in enumerate(rows):
        templates[row["template"]].append(i)
    groups = {"trained": [i for t, v in templates.items() if t not in HELD_OUT_TEMPLATES for i in v],
              "held_out": [i for t, v in templates.items() if t in HELD_OUT_TEMPLATES for i in v],
              "all": list(range(len(rows)))}
    result = {"by_template": {t: entry(v) for t, v in sorted(templates.items())},
              "by_num_actions": by_actions(groups["all"]),
              **{name: entry(v) for name, v in groups.items() if v}, "repeats": repeats}
    if reconstructed is not None:
        kept = [i for i in range(len(rows)) if reconstructed[i]]
        result["reconstruction"] = by_actions(groups["all"], of=reconstructed)
        result["generated_where_reconstructed"] = by_actions(kept)
        result["generated_where_not"] = by_actions([i for i in groups["all"] if not reconstructed[i]])
    return result


def reconstruction_read_right(model: SegMo, classifier, row: dict, data: Path,
                              layers: list[int] | None = None) -> list[bool]:
    """Is the tokenizer's reconstruction of the row's motion (cut to its frames) read as its
    true actions? One answer per entry of `layers`, the reconstruction decoded from the first
    L residual layers only; by default one answer, every layer."""
    tokens = model.encode_motion(read_motion(data, row["id"])[: row["frames"]])
    lengths = torch.tensor([tokens.shape[1] * FRAMES_PER_TOKEN], device=tokens.device)
    q = tokens.shape[-1]
    answers = []
    for kept in layers or [q]:
        out = model.decode(tokens.masked_fill(torch.arange(q, device=tokens.device) >= kept, -1),
                           lengths, [row["text"]], [[row["text"]]])
        answers.append(classifier.predict_sequence(out.features[0].float().cpu().numpy()) == row["actions"])
    return answers


def reconstructions_read_right(model: SegMo, classifier, rows: list[dict], data: Path) -> np.ndarray:
    """One bool per row: is the tokenizer's reconstruction of its motion (every layer) read as
    the row's true actions? The generator cannot beat this."""
    return np.array([reconstruction_read_right(model, classifier, row, data)[0] for row in rows], dtype=bool)


def corpus_arguments(description: str) -> argparse.ArgumentParser:
    """The arguments every action-order tool of the built-in corpus takes: the bundle, the
    corpus, the action classifier, the split, the draws per caption and the first seed."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--model", required=True, type=Path, help="a SegMo bundle (segmo bundle)")
    parser.add_argument("--data", required=True, type=Path, help="the built-in corpus' folder")
    parser.add_argument("--action-classifier", required=True, type=Path)
    parser.add_argument("--split", default="test")
    parser.add_argument("--repeats", type=positive_int, default=2, help="draws per caption (seeds)")
    parser.add_argument("--seed", type=int, default=0)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = corpus_arguments(__doc__.split("\n\n")[0])
    parser.add_argument("--word-text", choices=get_args(WordText), default=None,
                        help="what a words model's word keys read (default: the bundle's)")
    parser.add_argument("--segment-timing", choices=(*get_args(SegmentTiming), "truth"),
                        default=None, help="what a mask transformer with segment timing is "
                        "given (default: the bundle's); truth: the corpus' durations")
    parser.add_argument("--remasking", choices=get_args(Remasking), default=None,
                        help="which tokens each decoding step masks again: the least confident "
                        "of the motion or of each segment (default: the bundle's)")
    parser.add_argument("--segment-guidance", type=non_negative_float, default=None,
                        metavar="W", help="per-segment guidance weight, 0 = off (default: the "
                        "bundle's)")
    parser.add_argument("--choice-temperature", type=non_negative_float, default=None,
                        metavar="TAU", help="MaskGIT choice temperature of the remasking, 0 = "
                        "off (default: the bundle's)")
    parser.add_argument("--compose", type=int, default=None, metavar="FRAMES",
                        help="generate each caption segment by segment (SegMo.compose), "
                        "parts at their true shares, transitions of FRAMES frames")
    parser.add_argument("--reconstruction", action="store_true", help="also read the tokenizer's "
                        "reconstructions and split the generated accuracy by them")
    args = parser.parse_args(argv)
    if args.compose is not None and not valid_transition(args.compose):
        parser.error(f"--compose must be a multiple of {FRAMES_PER_TOKEN} frames ≥ {FRAMES_PER_TOKEN}, "
                     f"got {args.compose}")
    if args.compose is not None and args.segment_timing is not None:
        parser.error("--compose generates each segment alone: give no --segment-timing")
    try:
        model = SegMo.from_pretrained(args.model)
        if args.word_text is not None:
            model.config.word_text = args.word_text
        if args.remasking is not None:
            model.config.remasking = args.remasking
        if args.segment_guidance is not None:
            model.config.segment_guidance = args.segment_guidance
        if args.choice_temperature is not None:
            model.config.choice_temperature = args.choice_temperature
        if args.segment_timing in get_args(SegmentTiming):
            model.config.segment_timing = args.segment_timing
        sampling = model.sampling  # the options given, checked here: one line if they clash
        if args.segment_timing == "truth" and not model.mask.config.segment_timing:
            raise SegmoError(f"--segment-timing truth: {args.model}'s mask transformer has no "
                             "segment timing")
        classifier = load_pretrained(args.action_classifier).eval()
        rows = multi_segment_rows(args.data, args.split, model.max_frames)
        # a motion file the corpus lacks fails here, in one line, before any generation
        reconstructed = (reconstructions_read_right(model, classifier, rows, args.data)
                         if args.reconstruction else None)
    except (SegmoError, FileNotFoundError, OSError) as error:
        print(f"order_by_template: {error}", file=sys.stderr)
        return 2
    result = order_by_template(model, classifier, rows, args.repeats, args.seed,
                               truth=args.segment_timing == "truth", reconstructed=reconstructed,
                               compose=args.compose)
    for template, value in result["by_template"].items():
        print(f"{template:>12}: {value['sequence_accuracy']:.3f} ({value['motions']} motions)")
    for bucket, value in result["by_num_actions"].items():
        print(f"{bucket + ' actions':>12}: {value['sequence_accuracy']:.3f} ({value['motions']} motions, "
              f"{value['never_right']} never right)")
    for name in ("reconstruction", "generated_where_reconstructed", "generated_where_not"):
        for bucket, value in result.get(name, {}).items():
            print(f"{name} {bucket} actions: {value['sequence_accuracy']:.3f} ({value['motions']} motions)")
    timing = args.segment_timing or sampling.segment_timing
    print(json_text({**result, "word_text": sampling.word_text, "segment_timing": timing,
                      "remasking": sampling.remasking,
                      "segment_guidance": sampling.segment_guidance,
                      "choice_temperature": sampling.choice_temperature, "compose": args.compose}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
