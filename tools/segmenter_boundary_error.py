"""Boundary error of the motion segmenters against the built-in corpus' ground truth.

For every caption with ≥ 2 ground-truth segments (`DIR/segments/<id>.json`), the
segmenters split the caption's motion range into as many token spans as it has
segments; each inner boundary's error is |predicted − true| in frames (token = 4
frames). Prints a Markdown table (mean, variance, std, median over all inner boundaries)
and a final JSON line. The paper (§4.3) argues the *variance* matters most.

Per-token features: `new_joint_vecs` z-scored with `Mean.npy`/`Std.npy`, average-pooled
over 4 frames; with `--tokenizer DIR`, the exported tokenizer's encoder outputs instead.

    python tools/segmenter_boundary_error.py --data /tmp/c2000 --split test
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from segmo.cli import run
from segmo.data.layout import (
    has_ground_truth,
    read_ground_truth,
    read_motion,
    read_split,
    stats_files,
)
from segmo.errors import ArgumentParser, SegmoError, positive_int
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.segmentation import boundaries, get_motion_segmenter, pool_tokens

METHODS = ("uniform", "cpd", "kmeans")


def load_encoder(directory: str):
    """Raw `(t, d)` features → `(t // 4, code_dim)` latents of an exported tokenizer.

    The tokenizer z-scores with its own statistics (buffers), not the corpus' ones.
    """
    from segmo.models.pretrained import load_pretrained

    model = load_pretrained(directory)
    if not hasattr(model, "encoder") or not hasattr(model, "normalize"):
        raise SegmoError(f"--tokenizer {directory}: not a tokenizer (no encoder/normalize)")

    @torch.no_grad()
    def encode(raw: np.ndarray) -> np.ndarray:
        x = model.normalize(torch.from_numpy(raw[: len(raw) // FRAMES_PER_TOKEN * FRAMES_PER_TOKEN]).float())
        return model.encoder(x.T[None])[0].T.numpy()  # Conv1d layout (b, d, t)

    return encode


def caption_cases(record: dict) -> list[tuple[int, int, list[int]]]:
    """(first frame, last frame, inner true boundaries) of each caption with ≥ 2 segments."""
    cases = []
    for caption in record["captions"]:
        segments = caption["segments"]
        if len(segments) < 2:
            continue
        start, end = segments[0]["start"], segments[-1]["end"]
        cases.append((start, end, [s["start"] for s in segments[1:]]))
    return cases


def measure(data: Path, split: str, max_motions: int | None, tokenizer: str | None) -> dict:
    ids = read_split(data, split)[:max_motions]
    mean, std = (np.load(path) for path in stats_files(data))  # any feature width
    if not (np.isfinite(mean).all() and np.isfinite(std).all() and (std > 0).all()):
        raise SegmoError(f"{stats_files(data)[1]}: the statistics must be finite, every std > 0")
    encode = load_encoder(tokenizer) if tokenizer else None
    errors: dict[str, list[int]] = {m: [] for m in METHODS}
    seconds = dict.fromkeys(METHODS, 0.0)
    calls = dict.fromkeys(METHODS, 0)
    cache: dict[tuple, list] = {}
    skipped = captions = 0
    for method in METHODS:  # keep one-off imports out of the timings
        get_motion_segmenter(method)(np.random.default_rng(0).normal(size=(12, 3)), 3)
    for motion_id in ids:
        record = read_ground_truth(data, motion_id)
        raw = read_motion(data, motion_id)
        for start, end, truth in caption_cases(record):
            window = raw[start:end]
            tokens = encode(window) if encode else pool_tokens((window - mean) / std)
            a = len(truth) + 1
            if a > tokens.shape[0]:
                skipped += 1
                continue
            captions += 1
            for method in METHODS:
                # Captions of one motion often share (range, a): segment once per key.
                key = (method, motion_id, start, end, a)
                if key not in cache:
                    began = time.perf_counter()
                    cache[key] = get_motion_segmenter(method)(tokens, a, seed=0)
                    seconds[method] += time.perf_counter() - began
                    calls[method] += 1
                spans = cache[key]
                predicted = [start + FRAMES_PER_TOKEN * b for b in boundaries(spans)]
                errors[method] += [abs(p - t) for p, t in zip(predicted, truth)]
    result = {"split": split, "motions": len(ids), "captions": captions, "skipped": skipped}
    for method in METHODS:
        e = np.asarray(errors[method], dtype=np.float64)
        result[method] = {
            "boundaries": int(e.size),
            "mean": float(e.mean()) if e.size else float("nan"),
            "var": float(e.var()) if e.size else float("nan"),
            "std": float(e.std()) if e.size else float("nan"),
            "median": float(np.median(e)) if e.size else float("nan"),
            "ms_per_call": 1000 * seconds[method] / max(calls[method], 1),
        }
    return result


def table(result: dict) -> str:
    lines = [
        "| segmenter | boundaries | mean (frames) | variance | std | median | ms/call |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for method in METHODS:
        r = result[method]
        lines.append(
            f"| {method} | {r['boundaries']} | {r['mean']:.2f} | {r['var']:.1f} | "
            f"{r['std']:.2f} | {r['median']:.1f} | {r['ms_per_call']:.2f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = ArgumentParser(prog="segmenter_boundary_error.py", description=__doc__.splitlines()[0])
    parser.add_argument("--data", required=True, type=Path, help="built-in corpus folder")
    parser.add_argument("--split", default="test")
    parser.add_argument("--max-motions", type=positive_int, default=None)
    parser.add_argument("--tokenizer", default=None, help="exported tokenizer directory")
    args = parser.parse_args(argv)
    if not has_ground_truth(args.data):
        parser.error(
            f"--data {args.data}: no segments/ folder (ground truth of the built-in corpus)"
        )
    result = measure(args.data, args.split, args.max_motions, args.tokenizer)
    print(
        f"{result['captions']} captions with ≥ 2 segments from {result['motions']} "
        f"{args.split} motions ({result['skipped']} skipped: more segments than tokens)\n"
    )
    print(table(result))
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    run("segmenter_boundary_error.py", main, sys.argv[1:])
