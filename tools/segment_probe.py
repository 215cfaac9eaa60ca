"""Segment-level top-1 of any mask transformer, with or without its own alignment head.

    python tools/segment_probe.py --mask models/mask --tokenizer models/rvq --data data/synth

A model trained with `alignment: none` has no segment-similarity matrix, so its segment
top-1 cannot be read off like that of a SegMo model. This tool fits a fresh alignment
head (the model's own design: mean ‖ max pooling + MLP, text MLP, in-sample loss) on the
FROZEN transformer's features of the train split, with uniform motion segments as in
training, then scores it on `--split` against the built-in corpus's ground-truth spans
(`MaskTask`'s `segment_top1`). A model with a head is scored with its own head too, so the
two columns compare like with like. Features come from unmasked inputs, as in validation
and grounding; `--unordered` feeds the segments as a set, as grounding does, so that a
model cannot score by copying the i-th segment into the i-th span. The last printed line
is JSON. A bad argument, model or data folder is one line on stderr (exit status 2).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import torch

from segmo.cli import run
from segmo.data import MotionDataModule
from segmo.errors import ArgumentParser, SegmoError, non_negative_int, positive_int
from segmo.models.alignment import AlignmentConfig, AlignmentHead
from segmo.models.mask_transformer import MaskTransformer
from segmo.segmentation import segment_batch
from segmo.tasks.alignment_loss import AlignmentLoss
from segmo.tasks.common import load_tokenizer, text_condition, token_lengths, token_mask
from segmo.tasks.mask import gt_token_spans, segment_top1


def features(mask: MaskTransformer, tokenizer, batch: dict, unordered: bool = False):
    """Unmasked pass → (motion features (b, n, dim), text features (b, a, dim),
    segment_mask (b, a), token lengths (b,)). `unordered`: the segments enter as a set
    (no order embeddings), as grounding feeds them."""
    sentence, segments, segment_mask = text_condition(batch)
    with torch.no_grad():
        base = tokenizer.encode(batch["motion"])[..., 0]
        valid = token_mask(batch["lengths"], base.shape[1])
        as_set = torch.full((base.shape[0],), unordered, dtype=torch.bool)
        out = mask(base, valid, sentence, segments, segment_mask, unordered=as_set)
    return out.motion_features, out.segment_features, segment_mask, token_lengths(batch["lengths"])


def fit_probe(mask: MaskTransformer, tokenizer, loader, steps: int, seed: int,
              unordered: bool = False) -> AlignmentHead:
    torch.manual_seed(seed)
    head = AlignmentHead(mask.config.dim, AlignmentConfig(out_dim=mask.config.dim))
    loss_fn = AlignmentLoss("in_sample")
    optimizer = torch.optim.AdamW(head.parameters(), lr=1e-3, weight_decay=1e-5)
    step = 0
    while step < steps:
        for batch in loader:
            h, text, segment_mask, lengths = features(mask, tokenizer, batch, unordered)
            num_segments = torch.minimum(segment_mask.sum(1), lengths)
            spans = segment_batch(None, num_segments, lengths, "uniform",
                                  max_segments=segment_mask.shape[1])
            loss = loss_fn(head, h, lengths, text, segment_mask, spans).losses["align"]
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            step += 1
            if step == steps:
                break
    return head.eval()


def score(mask: MaskTransformer, tokenizer, loader, heads: dict[str, AlignmentHead],
          unordered: bool = False) -> dict[str, float]:
    correct = dict.fromkeys(heads, 0)
    total = 0
    for batch in loader:
        if batch.get("spans") is None:
            raise SegmoError("the split has no ground-truth spans (the built-in corpus's "
                             "segments/<id>.json)")
        h, text, segment_mask, _ = features(mask, tokenizer, batch, unordered)
        gt, usable = gt_token_spans(batch["spans"], segment_mask.sum(1), batch["lengths"],
                                    segment_mask.shape[1])
        keep = segment_mask & usable[:, None] & (gt[..., 1] > gt[..., 0])
        total += int(keep.sum())
        with torch.no_grad():
            for name, head in heads.items():
                c, _ = segment_top1(head.embed_text(text), head.embed_motion(h, gt), keep)
                correct[name] += c
    return {name: correct[name] / max(total, 1) for name in heads} | {"segments": total}


def main(argv: list[str] | None = None) -> dict:
    """Fit the probe, score it, print the result and its JSON line; the result is returned.
    SegmoError (or OSError) for a bad argument, model or data folder."""
    parser = ArgumentParser(prog="segment_probe.py", description=__doc__.split("\n")[0])
    parser.add_argument("--mask", required=True, help="exported mask transformer directory")
    parser.add_argument("--tokenizer", required=True, help="exported RVQ-VAE directory")
    parser.add_argument("--data", required=True, type=Path, help="built-in corpus root (with text features)")
    parser.add_argument("--split", default="val", choices=("val", "test"))
    parser.add_argument("--text-segments", default="rule")
    parser.add_argument("--steps", type=positive_int, default=600, help="probe training steps")
    parser.add_argument("--batch-size", type=positive_int, default=32)
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--unordered", action="store_true",
                        help="feed the segments as a set, as grounding does: the score then "
                             "comes from what a segment says, not from its slot")
    args = parser.parse_args(argv)
    if not args.data.is_dir():
        parser.error(f"--data {args.data}: no such folder")

    mask = MaskTransformer.from_pretrained(args.mask).eval().requires_grad_(False)
    tokenizer = load_tokenizer(args.tokenizer)
    encoder = mask.meta.get("text_encoder") or "minilm"
    data = MotionDataModule(args.data, batch_size=args.batch_size, text_segments=args.text_segments,
                            text_features=encoder, max_segments=mask.config.max_segments,
                            seed=args.seed)
    data.setup(None)
    start = time.perf_counter()
    heads = {"probe": fit_probe(mask, tokenizer, data.train_dataloader(), args.steps, args.seed,
                                args.unordered)}
    if mask.alignment is not None:
        heads["own_head"] = mask.alignment.eval()
    loader = data.val_dataloader() if args.split == "val" else data.test_dataloader()
    result = score(mask, tokenizer, loader, heads, args.unordered)
    result |= {"split": args.split, "steps": args.steps, "unordered": args.unordered,
               "seconds": round(time.perf_counter() - start, 1)}
    print(", ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}"
                    for k, v in result.items()))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run("segment_probe.py", main, sys.argv[1:])
