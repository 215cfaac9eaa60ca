"""Temporal editing (spec §8): regenerate a span of a motion's tokens under new text.

Base tokens inside the span are re-masked and refilled by the masked decoding of
`segmo.generation.generate`, with everything outside visible as context; residual tokens
are drawn inside the span only, so every token outside it is kept exactly. The decoder is
convolutional, so frames near the span may still move a little (`edit_drift`).

    span = token_span((16, 48))                                  # frames → tokens (4, 12)
    edited = edit_tokens(mask_model, residual_model, indices, span, sentence, segments,
                         segment_mask, generator=torch.Generator().manual_seed(0))
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from segmo.errors import SegmoError
from segmo.generation.generate import Precision, check_models, fill_tokens
from segmo.generation.sampling import SamplingOptions
from segmo.models.mask_transformer import MaskTransformer
from segmo.models.residual_transformer import ResidualTransformer
from segmo.models.tokenizer import FRAMES_PER_TOKEN


def token_span(frames: tuple[int, int]) -> tuple[int, int]:
    """Frames [start, end) → the tokens [start // 4, ⌈end / 4⌉) that cover them."""
    start, end = frames
    return start // FRAMES_PER_TOKEN, math.ceil(end / FRAMES_PER_TOKEN)


def edit_tokens(
    mask_model: MaskTransformer,
    residual_model: ResidualTransformer | None,
    indices: torch.Tensor,
    span: tuple[int, int] | torch.Tensor,
    sentence: torch.Tensor,
    segments: torch.Tensor,
    segment_mask: torch.Tensor,
    *,
    options: SamplingOptions | None = None,
    generator: torch.Generator | None = None,
    precision: Precision = "auto",
    words: torch.Tensor | None = None,
    word_mask: torch.Tensor | None = None,
) -> torch.Tensor:
    """Regenerate the tokens of a span under new text conditioning (temporal inpainting).

    indices (b, n, q) long from `generate_tokens` (−1 marks padding in layer 0);
    span (start_token, end_token), end exclusive, or a (b, 2) long tensor of per-sample
    spans; new text (words and word_mask too), options, generator and precision as in
    `generate_tokens`. Base tokens
    inside the span are re-masked and refilled with everything outside visible as context;
    residual tokens are regenerated inside the span only. Every token outside the span is
    returned unchanged.
    """
    check_models(mask_model, residual_model)
    b, n, q = indices.shape
    if q > 1 and residual_model is None:
        raise ValueError(f"edit_tokens: indices have {q} layers; a residual_model is needed to "
                         "regenerate the residual tokens inside the span")
    if residual_model is not None and q != residual_model.config.num_quantizers:
        raise ValueError(f"edit_tokens: indices have {q} layers, the residual model has "
                         f"num_quantizers={residual_model.config.num_quantizers}")
    span = torch.as_tensor(span, device=indices.device).long().reshape(-1, 2).expand(b, 2)
    start, end = span[:, :1], span[:, 1:]
    if bool(((start < 0) | (end > n) | (start >= end)).any()):
        raise ValueError(f"edit_tokens: span must satisfy 0 ≤ start < end ≤ n={n}, "
                         f"got {span.tolist()}")
    token_mask = indices[..., 0] >= 0
    position = torch.arange(n, device=indices.device)
    editable = (position >= start) & (position < end) & token_mask
    return fill_tokens(mask_model, residual_model, indices, editable, token_mask, sentence,
                       segments, segment_mask, options or SamplingOptions(), generator, precision,
                       words, word_mask)


def edit_drift(original: Any, edited: Any, span: tuple[int, int]) -> dict[int, float]:
    """How much an edit changed the frames outside its span, by distance from the span.

    original, edited: (t, d) features; span: (start, end) frames, end exclusive →
    {distance in frames (1 = adjacent to the span): mean |edited − original|}.
    """
    a = torch.as_tensor(np.asarray(original, dtype=np.float32))
    b = torch.as_tensor(np.asarray(edited, dtype=np.float32))
    if a.shape != b.shape or a.ndim != 2:
        raise SegmoError(f"edit_drift: original {tuple(a.shape)} and edited {tuple(b.shape)} "
                         "must both be (t, d)")
    start, end = span
    change = (a - b).abs().mean(dim=1)
    frames = torch.arange(a.shape[0])
    distance = torch.where(frames < start, start - frames, frames - end + 1)
    outside = (frames < start) | (frames >= end)
    out: dict[int, float] = {}
    for d in sorted(set(distance[outside].tolist())):
        out[int(d)] = float(change[outside & (distance == d)].mean())
    return out
