"""Text ↔ motion retrieval (paper §4.4) in SegMo's learned segment space
(`segmo.pipeline.space`).

A (text, motion) pair is scored by pairing the text's segments with as many spans of the
motion (uniform by default, or a motion segmenter's, `segmo.segmentation`) and taking
the mean cosine of the paired segments (`pair_scores`). The R@k protocols that measure
retrieval are `segmo.evaluation.retrieval`.

    model.retrieve_texts(features, ["a person walks", "a person jumps"], top_k=1)
    model.retrieve_motions("a person walks, then waves", [features_a, features_b])
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from segmo.errors import SegmoError
from segmo.generation.editing import token_span
from segmo.pipeline.inputs import check_span, check_texts
from segmo.pipeline.space import SegmentModel
from segmo.segmentation import segment_batch

BATCH = 32  # pairs per forward pass in retrieval


def embed_pairs(model: SegmentModel, texts: list[str], motions: Any, spans: Any, *,
                segments: list[list[str]] | None = None, lengths: Any = None,
                normalized: bool = False, region: tuple[int, int] | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Text i's segments paired with spans of motion i, in the learned space.

    texts (b); motions as `SegMo.embed_segments` takes them; spans: "uniform" / "cpd" /
    "kmeans" (segmo.segmentation, as many spans as each text has segments), or explicit
    token spans (b, a, 2) with (0, 0) for absent slots; region: (start, end) tokens that
    the generated spans must cover instead of the whole motion. → text (b, a, out_dim),
    motion (b, a, out_dim), mask (b, a) bool (slot i has a text segment and a non-empty
    span). Segments beyond the motion's token count sit out (masked), as in training.
    """
    space = model.embed_segments(texts, motions, segments=segments, lengths=lengths,
                                 normalized=normalized)
    segment_mask, n_valid = space.segment_mask, space.num_tokens
    b, a = segment_mask.shape
    if isinstance(spans, str):
        latents, start = space.latents, torch.zeros_like(n_valid)
        if region is not None:
            start = torch.full_like(n_valid, region[0])
            if bool((n_valid < region[1]).any()) or not 0 <= region[0] < region[1]:
                raise SegmoError(f"embed_pairs: region {region} tokens is outside a motion of "
                                 f"{n_valid.tolist()} tokens")
            latents, n_valid = latents[:, region[0]: region[1]], torch.full_like(
                n_valid, region[1] - region[0])
        num = torch.minimum(segment_mask.sum(1), n_valid)
        spans = segment_batch(None if spans == "uniform" else latents, num, n_valid, spans,
                              max_segments=a)
        present = spans[..., 1] > spans[..., 0]
        spans = torch.where(present[..., None], spans + start[:, None, None], spans)
    else:
        spans = explicit_spans(spans, b, a, n_valid.tolist())
    spans = spans.to(space.text.device)
    mask = segment_mask & (spans[..., 1] > spans[..., 0])
    return space.text, space.motion(spans), mask


def explicit_spans(spans: Any, b: int, a: int, num_tokens: list[int]) -> torch.Tensor:
    """`embed_pairs`' explicit token spans → (b, a, 2) long, or SegmoError naming the span
    that is not (0, 0) (an absent slot) or whole tokens with 0 ≤ start < end ≤ its motion's
    tokens (fractions were truncated, negative starts clamped and reversed spans dropped,
    without a word)."""
    try:
        shape = tuple(torch.as_tensor(spans).shape)
    except (TypeError, ValueError, RuntimeError):
        shape = None
    if shape != (b, a, 2):
        raise SegmoError(f"embed_pairs: explicit spans must be (b={b}, a={a}, 2) token spans, "
                         f"got {shape if shape is not None else repr(spans)[:80]}")
    rows = spans.tolist() if isinstance(spans, (torch.Tensor, np.ndarray)) else spans
    for i, row in enumerate(rows):
        for k, span in enumerate(row):
            if list(span) != [0, 0]:
                check_span(tuple(span), f"embed_pairs: spans[{i}][{k}]", num_tokens[i], "tokens")
    return torch.as_tensor(spans).long()


def pair_scores(text: torch.Tensor, motion: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(b,) mean cosine of each row's valid segment pairs: the retrieval score."""
    cosine = F.cosine_similarity(text, motion, dim=-1)
    weight = mask.to(cosine.dtype)
    return (cosine * weight).sum(-1) / weight.sum(-1).clamp(min=1.0)


def _top(scores: torch.Tensor, top_k: int) -> list[tuple[int, float]]:
    if isinstance(top_k, bool) or not isinstance(top_k, numbers.Integral) or top_k < 1:
        raise SegmoError(f"SegMo: top_k must be a whole number >= 1, got {top_k!r}")
    order = scores.argsort(descending=True, stable=True)[:top_k]
    return [(int(i), float(scores[i])) for i in order]


def retrieve_texts(model: SegmentModel, motion: Any, candidates: list[str],
                   span: tuple[int, int] | None = None, top_k: int = 5
                   ) -> list[tuple[str, float]]:
    """Rank candidate texts for a motion, or for frames [start, end) of it.

    Each candidate is split into its text segments and paired with as many uniform spans
    of the motion (or of the span); its score is the mean paired cosine.
    """
    if isinstance(candidates, str) or not isinstance(candidates, (list, tuple)):
        # a string would be ranked letter by letter
        raise SegmoError(f"retrieve_texts: candidates must be a list of texts, got "
                         f"{candidates!r:.80}")
    if not candidates:
        raise SegmoError("retrieve_texts: no candidate texts")
    check_texts(candidates, "candidate")
    region = None
    if span is not None:
        region = token_span(check_span(span, "retrieve_texts"))
    scores = []
    for i in range(0, len(candidates), BATCH):
        chunk = list(candidates[i: i + BATCH])
        pairs = embed_pairs(model, chunk, [motion] * len(chunk), "uniform", region=region)
        scores.append(pair_scores(*pairs).cpu())
    return [(candidates[i], s) for i, s in _top(torch.cat(scores), top_k)]


def retrieve_motions(model: SegmentModel, text: str, motions: list, top_k: int = 5
                     ) -> list[tuple[int, float]]:
    """Rank motions (raw features (t_i, d)) for a text → [(index, score)], best first."""
    if not isinstance(text, str):
        raise SegmoError(f"retrieve_motions: text must be a string, got {text!r:.80}")
    if not isinstance(motions, (list, tuple, np.ndarray, torch.Tensor)):
        # a generator or None has no length to batch by
        raise SegmoError(f"retrieve_motions: motions must be a list of (t, d) motions, got a "
                         f"{type(motions).__name__}")
    if len(motions) == 0:
        raise SegmoError("retrieve_motions: no motions")
    segments = model.segment_texts([text])
    scores = []
    for i in range(0, len(motions), BATCH):
        chunk = list(motions[i: i + BATCH])
        pairs = embed_pairs(model, [text] * len(chunk), chunk, "uniform",
                            segments=segments * len(chunk))
        scores.append(pair_scores(*pairs).cpu())
    return _top(torch.cat(scores), top_k)
