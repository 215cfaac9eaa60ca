"""Where a bundle loses a caption's actions, stage by stage, on the built-in corpus.

    python tools/order_by_stage.py --model B --data data/synth \\
        --action-classifier models/action_classifier [--split test] [--repeats 2] [--seed 0]

`order_by_template.py` scores whole generations; this tool takes the stages apart on the
first caption of every motion of two or more actions, each read by the action classifier
as a sequence (right or wrong), by the caption's true number of actions (2, 3, 4-5, 3+):

- `tokenizer_layers`: the real motion through the tokenizer, decoded from its first L
  residual layers only (L = 1 .. q): how much of the actions the base tokens carry, and how
  much the residual layers add. The last entry is the whole reconstruction.
- then only on the captions whose whole reconstruction is read right (`kept`), so that
  what fails below is the transformers':
- `residual`: the real motion's base tokens, the residual layers drawn by the residual
  transformer (the bundle's residual guidance); `residual_layers`: one residual layer
  drawn at a time, every other layer real: which layers lose the actions.
- `fill`: the real tokens everywhere but one segment's, which the mask transformer draws
  (and the residual transformer inside it), every segment in turn: can the model make an
  action when the motion around it is given? Split by the segment's place (first, middle,
  last) and its share of the motion's frames (under 20 %, 20-40 %, 40 % and more).
- `generated`: every token drawn, as `order_by_template.py --segment-timing truth` draws
  them for a mask transformer with segment timing (the corpus' durations), as the bundle
  does for one without.

A segment's span is its true duration's share of the motion in whole tokens (the spans a
timing model is given). The last stdout line is the JSON object.
"""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from segmo.data.layout import read_motion
from segmo.errors import SegmoError
from segmo.evaluation.metrics import segment_bucket
from segmo.generation.generate import (
    fill_tokens,
    guidance_condition,
    residual_decode,
    resolve_precision,
    token_mask_from_lengths,
)
from segmo.models.pretrained import load_pretrained
from segmo.models.segment_timing import durations_to_spans
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.pipeline import SegMo

sys.path.insert(0, str(Path(__file__).resolve().parent))
from order_by_template import (  # noqa: E402
    corpus_arguments,
    multi_segment_rows,
    reconstruction_read_right,
    true_timing,
)

BATCH = 16
SHARES = ((0.0, 0.2, "<20%"), (0.2, 0.4, "20-40%"), (0.4, float("inf"), ">=40%"))


def buckets(num_actions: int) -> list[str]:
    """The buckets a caption of `num_actions` counts in: its own, and "3+" from three on."""
    return [segment_bucket(num_actions)] + (["3+"] if num_actions >= 3 else [])


def accuracy(hits: dict[str, list[bool]]) -> dict:
    """{bucket: reads right or wrong} → {bucket: {"sequence_accuracy", "reads"}}."""
    return {k: {"sequence_accuracy": float(np.mean(v)), "reads": len(v)} for k, v in sorted(hits.items())}


class Batch:
    """A chunk of rows as tensors: the real motions' tokens, their lengths and token mask,
    the text condition (the model's own segments where it finds one per true action, else
    the corpus'), and each segment's true span in tokens (b, a, 2)."""

    def __init__(self, model: SegMo, rows: list[dict], data: Path):
        self.rows = rows
        timing = true_timing(model, rows)
        self.texts = [r["text"] for r in rows]
        self.sentence, self.vectors, self.segment_mask, self.segments = model.text_condition(
            self.texts, timing["segments"])
        self.lengths = torch.tensor([r["frames"] for r in rows], device=model.device)
        n = int(self.lengths.max()) // FRAMES_PER_TOKEN
        self.token_mask = token_mask_from_lengths(self.lengths, model.mask.config.max_tokens)[:, :n]
        q = model.residual.config.num_quantizers if model.residual is not None else 1
        self.real = torch.full((len(rows), n, q), -1, dtype=torch.long, device=model.device)
        for k, row in enumerate(rows):
            tokens = model.encode_motion(read_motion(data, row["id"])[: row["frames"]])[0, :, :q]
            self.real[k, : tokens.shape[0]] = tokens
        durations = torch.zeros(self.segment_mask.shape)
        for k, d in enumerate(timing["durations"]):
            durations[k, : len(d)] = torch.tensor(d, dtype=torch.float32)
        self.durations = timing["durations"]
        self.spans = durations_to_spans(durations.to(model.device), self.segment_mask.bool(),
                                        self.token_mask.sum(1))
        position = torch.arange(n, device=model.device)
        self.inside = ((position >= self.spans[..., :1]) & (position < self.spans[..., 1:])
                       & self.token_mask[:, None])  # (b, a, n)

    def read(self, model: SegMo, classifier, tokens: torch.Tensor) -> list[bool]:
        out = model.decode(tokens, self.lengths, self.texts, self.segments)
        return [classifier.predict_sequence(out.features[k, : int(out.lengths[k])].float().cpu().numpy())
                == row["actions"] for k, row in enumerate(self.rows)]


def tokenizer_layers(model: SegMo, classifier, rows: list[dict], data: Path) -> tuple[dict, np.ndarray]:
    """Per bucket, the accuracy of the reconstruction from the first L layers (L = 1 .. q),
    and one bool per row: is the whole reconstruction read right?"""
    q = model.tokenizer.num_quantizers
    hits = np.array([reconstruction_read_right(model, classifier, row, data, list(range(1, q + 1)))
                     for row in rows], dtype=bool).reshape(len(rows), q)
    by: dict[str, list[int]] = defaultdict(list)
    for i, row in enumerate(rows):
        for bucket in buckets(row["num_actions"]):
            by[bucket].append(i)
    table = {k: {"sequence_accuracy": [float(hits[v, layer].mean()) for layer in range(q)], "motions": len(v)}
             for k, v in sorted(by.items())}
    return table, hits[:, -1]


def draw(model: SegMo, b: Batch, editable: torch.Tensor, seed: int) -> torch.Tensor:
    """b's real tokens with the `editable` ones drawn anew by the bundle's sampling options;
    a mask transformer with segment timing is given the true spans."""
    generator = torch.Generator(device=model.device).manual_seed(seed)
    return fill_tokens(model.mask, model.residual, b.real, editable, b.token_mask, b.sentence, b.vectors,
                       b.segment_mask, model.sampling, generator, "auto",
                       spans=b.spans if model.mask.config.segment_timing else None)


def redraw_residual(model: SegMo, b: Batch, seed: int, layers: list[int] | None = None) -> torch.Tensor:
    """b's real base tokens, the residual `layers` (None = all) drawn by the residual
    transformer, the others real."""
    generator = torch.Generator(device=model.device).manual_seed(seed)
    precision, _ = resolve_precision("auto", model.device)
    with torch.inference_mode(), torch.autocast(model.device.type, dtype=torch.bfloat16,
                                                enabled=precision == "bf16"):
        condition = guidance_condition(model.residual, b.sentence, b.vectors, b.segment_mask)
        return residual_decode(model.residual, b.real, b.token_mask, b.token_mask, condition,
                               model.sampling, generator, layers)


def order_by_stage(model: SegMo, classifier, rows: list[dict], data: Path, repeats: int, seed: int) -> dict:
    """The `residual`, `residual_layers`, `fill` and `generated` readings of the module
    docstring over `rows` (the captions the tokenizer keeps), `repeats` draws each."""
    residual: dict[str, list[bool]] = defaultdict(list)
    residual_layers: dict[int, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    generated: dict[str, list[bool]] = defaultdict(list)
    fill: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    for module in model.modules():
        module.eval()
    for start in range(0, len(rows), BATCH):
        b = Batch(model, rows[start:start + BATCH], data)
        for repeat in range(repeats):
            salt = seed + 1000 * repeat + start
            for k, right in enumerate(b.read(model, classifier, draw(model, b, b.token_mask, salt))):
                for bucket in buckets(b.rows[k]["num_actions"]):
                    generated[bucket].append(right)
            if model.residual is not None:
                for k, right in enumerate(b.read(model, classifier, redraw_residual(model, b, salt))):
                    for bucket in buckets(b.rows[k]["num_actions"]):
                        residual[bucket].append(right)
                for layer in range(1, model.residual.config.num_quantizers):
                    redrawn = redraw_residual(model, b, salt + layer, [layer])
                    for k, right in enumerate(b.read(model, classifier, redrawn)):
                        for bucket in buckets(b.rows[k]["num_actions"]):
                            residual_layers[layer][bucket].append(right)
            for j in range(b.inside.shape[1]):
                editable = b.inside[:, j]
                if not bool(editable.any()):
                    continue
                for k, right in enumerate(b.read(model, classifier, draw(model, b, editable, salt + 1 + j))):
                    n = len(b.durations[k])
                    if j >= n or not bool(editable[k].any()):
                        continue
                    place = "first" if j == 0 else "last" if j == n - 1 else "middle"
                    share = b.durations[k][j] / sum(b.durations[k])
                    size = next(name for low, high, name in SHARES if low <= share < high)
                    for bucket in buckets(b.rows[k]["num_actions"]):
                        for key in ("all", place, size):
                            fill[bucket][key].append(right)
    return {"residual": accuracy(residual),
            "residual_layers": {str(k): accuracy(v) for k, v in sorted(residual_layers.items())},
            "generated": accuracy(generated),
            "fill": {k: accuracy(v) for k, v in sorted(fill.items())}}


def main(argv: list[str] | None = None) -> int:
    parser = corpus_arguments(__doc__.split("\n\n")[0])
    args = parser.parse_args(argv)
    try:
        model = SegMo.from_pretrained(args.model)
        classifier = load_pretrained(args.action_classifier).eval()
        rows = multi_segment_rows(args.data, args.split, model.max_frames)
        layers, kept = tokenizer_layers(model, classifier, rows, args.data)
        if not kept.any():
            raise SegmoError(f"--data {args.data}: no {args.split} caption's reconstruction is read "
                             "right by the action classifier; nothing is left to take apart")
    except (SegmoError, FileNotFoundError, OSError) as error:
        print(f"order_by_stage: {error}", file=sys.stderr)
        return 2
    with torch.inference_mode():
        result = {"tokenizer_layers": layers, "kept": int(kept.sum()), "repeats": args.repeats,
                  **order_by_stage(model, classifier, [r for r, k in zip(rows, kept) if k], args.data,
                                   args.repeats, args.seed)}
    for bucket, value in layers.items():
        print(f"tokenizer, first 1..q layers, {bucket} actions ({value['motions']}): "
              + " ".join(f"{a:.3f}" for a in value["sequence_accuracy"]))
    for name in ("residual", "generated"):
        for bucket, value in result[name].items():
            print(f"{name} {bucket} actions: {value['sequence_accuracy']:.3f} ({value['reads']} reads)")
    for layer, value in result["residual_layers"].items():
        print(f"residual layer {layer} alone: " + ", ".join(
            f"{bucket} actions {v['sequence_accuracy']:.3f}" for bucket, v in value.items()))
    for bucket, value in result["fill"].items():
        print(f"fill one segment, {bucket} actions: "
              + ", ".join(f"{k} {v['sequence_accuracy']:.3f} ({v['reads']})" for k, v in value.items()))
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
