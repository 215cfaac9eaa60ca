"""Where a SegMo bundle's motion tokens look: SinkRatio, prefix and sentence shares over
generation, and attention grounding on the built-in corpus' real motions, with plots.

    python tools/attention_report.py --model models/segmo --data data/synth --split test \\
        --out runs/attention [--motions 64] [--k 1] [--plots 6] [--seed 0]

For the first caption of each of the first --motions motions of the split (those with
ground truth, `DIR/segments/<id>.json`), with its ground-truth text segments:

- generation (`SegMo.generate` at the motion's length, seeded, recorded with
  `SegMo.record_attention`): `sink_ratio`, `prefix_share` and `sentence_share` of the mask
  transformer, by block and by decoding step (`segmo.evaluation.attention`);
- the real motion (`segmo.evaluation.attention.motion_attention`: one pass with all its
  tokens visible): `attention_grounding` against the true spans, by block, over the
  captions of at least 2 segments (one segment is always its own tokens' largest weight);
- the prefix mass by kind of key (sentence, segments, start word, other words:
  `kind_share`), by block, to find the sink of a model with word keys; for one that reads
  its words by gated cross-attention, each block's gate tanh(g) (0: closed);
- OUT/plots/<id>.png: each segment's attention over the real motion (last block), true
  spans shaded; for a model with word keys (`text_tokens: words`) a second panel with each
  content word's attention (`segmo.evaluation.attention.content_words`).

Writes OUT/attention.json and OUT/attention.md; the last stdout line is the JSON object.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from segmo.data.layout import first_captions, read_motion
from segmo.errors import SegmoError
from segmo.evaluation.attention import (
    attention_grounding,
    content_words,
    kind_share,
    motion_attention,
    plot_segment_attention,
    prefix_share,
    sentence_share,
    sink_ratio,
)
from segmo.files import json_text
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.pipeline import SegMo

BATCH = 16


def samples(data: Path, split: str, count: int, max_frames: int) -> list[dict]:
    out = []
    for motion_id, record, caption in first_captions(data, split):
        frames = min(record["num_frames"], max_frames) // FRAMES_PER_TOKEN * FRAMES_PER_TOKEN
        if frames < FRAMES_PER_TOKEN:
            continue
        spans = [(s["start"] // FRAMES_PER_TOKEN, -(-s["end"] // FRAMES_PER_TOKEN)) for s in caption["segments"]]
        out.append({"id": motion_id, "text": caption["text"], "frames": frames, "spans": spans,
                    "segments": [s["text"] for s in caption["segments"]]})
        if len(out) == count:
            break
    if not out:
        raise SegmoError(f"--data {data}: no {split} motion of at least {FRAMES_PER_TOKEN} frames")
    return out


def report(model: SegMo, data: Path, split: str, count: int, k: int, seed: int) -> tuple[dict, list]:
    chosen = samples(data, split, count, model.max_frames)
    generated, grounding_maps = [], []
    for start in range(0, len(chosen), BATCH):
        batch = chosen[start:start + BATCH]
        texts, segments = [s["text"] for s in batch], [s["segments"] for s in batch]
        # Word panels for words that are keys of the recorded attention (not cross-attention).
        pieces = model.word_texts(texts, segments) if model.has_word_keys else [[] for _ in texts]
        for sample, sample_pieces in zip(batch, pieces, strict=True):
            sample["words"] = content_words(sample_pieces)
        with model.record_attention() as recording:
            model.generate(texts, [s["frames"] for s in batch], segments=segments,
                           generator=torch.Generator().manual_seed(seed + start))
        generated += recording.of("mask")
        motions = [read_motion(data, s["id"])[:s["frames"]] for s in batch]
        maps = motion_attention(model, texts, segments, motions)
        grounding_maps.append((maps, [s["spans"] for s in batch], batch))
    counts: dict[int, list[int]] = {}
    for maps, spans, _ in grounding_maps:
        hits = attention_grounding(maps, spans, counts)
    result = {"motions": len(chosen), "split": split, "k": k, "seed": seed,
              "sink_ratio": sink_ratio(generated, k), "prefix_share": prefix_share(generated),
              "sentence_share": sentence_share(generated), "kind_share": kind_share(generated),
              "attention_grounding": hits}
    blocks = model.mask.trunk.blocks
    if hasattr(blocks[0], "cross"):  # words read by gated cross-attention: how open each gate is
        result["cross_gate"] = {b: float(torch.tanh(block.cross.gate).item()) for b, block in enumerate(blocks)}
    return result, grounding_maps


def plots(grounding_maps: list, out: Path, count: int, fps: float) -> list[str]:
    written = []
    for maps, spans, batch in grounding_maps:
        last = max(m.block for m in maps)
        m = next(m for m in maps if m.block == last)
        for row, sample in enumerate(batch):
            if len(written) == count:
                return written
            if len(sample["segments"]) < 2:
                continue
            path = plot_segment_attention(m, row, sample["segments"], out / "plots" / f"{sample['id']}.png",
                                          spans=spans[row], fps=fps, title=sample["text"],
                                          words=sample["words"])
            written.append(str(path))
    return written


def markdown(result: dict) -> str:
    lines = [f"Attention of the mask transformer, {result['motions']} {result['split']} motions "
             f"(SinkRatio top-{result['k']}).", "",
             "| block | SinkRatio | prefix share | sentence share | attention grounding |",
             "| ---: | ---: | ---: | ---: | ---: |"]
    for block in result["sink_ratio"]["by_block"]:
        lines.append(f"| {block} | {result['sink_ratio']['by_block'][block]:.3f} | "
                     f"{result['prefix_share']['by_block'][block]:.3f} | "
                     f"{result['sentence_share']['by_block'][block]:.3f} | "
                     f"{result['attention_grounding']['by_block'].get(block, float('nan')):.3f} |")
    lines.append(f"| all | {result['sink_ratio']['mean']:.3f} | {result['prefix_share']['mean']:.3f} | "
                 f"{result['sentence_share']['mean']:.3f} | {result['attention_grounding']['mean']:.3f} |")
    kinds = result["kind_share"]
    lines += ["", "Prefix mass by kind of key (the start word is the first word key, the start token):", "",
              "| block | " + " | ".join(kinds) + " |", "| ---: |" + " ---: |" * len(kinds)]
    for block in result["sink_ratio"]["by_block"]:
        lines.append(f"| {block} | " + " | ".join(f"{kinds[k]['by_block'][block]:.3f}" for k in kinds) + " |")
    if "cross_gate" in result:
        lines += ["", "Cross-attention gates, tanh(gate) by block: "
                  + ", ".join(f"{b}: {g:+.3f}" for b, g in result["cross_gate"].items())]
    lines += ["", "| decoding step | SinkRatio | prefix share | sentence share |", "| ---: | ---: | ---: | ---: |"]
    for step in result["sink_ratio"]["by_step"]:
        lines.append(f"| {step} | {result['sink_ratio']['by_step'][step]:.3f} | "
                     f"{result['prefix_share']['by_step'][step]:.3f} | "
                     f"{result['sentence_share']['by_step'][step]:.3f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", required=True, type=Path, help="a SegMo bundle (segmo bundle)")
    parser.add_argument("--data", required=True, type=Path, help="the built-in corpus' folder")
    parser.add_argument("--split", default="test")
    parser.add_argument("--out", required=True, type=Path)
    parser.add_argument("--motions", type=int, default=64)
    parser.add_argument("--k", type=int, default=1, help="SinkRatio's top-K")
    parser.add_argument("--plots", type=int, default=6)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    if args.motions < 1 or args.k < 1 or args.plots < 0:
        raise SystemExit("attention_report: --motions and --k must be ≥ 1, --plots ≥ 0")
    try:
        model = SegMo.from_pretrained(args.model)
        result, maps = report(model, args.data, args.split, args.motions, args.k, args.seed)
    except (SegmoError, FileNotFoundError) as error:
        print(f"attention_report: {error}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    result["plots"] = plots(maps, args.out, args.plots, model.fps)
    (args.out / "attention.json").write_text(json_text(result, indent=1) + "\n")
    (args.out / "attention.md").write_text(markdown(result))
    print(markdown(result))
    print(json_text(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
