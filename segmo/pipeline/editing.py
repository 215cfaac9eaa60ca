"""Editing a motion (`SegMo.edit`, `SegMo.edit_text`): regenerate a span of it from a text
(temporal inpainting, `segmo.generation.editing`), or decode it again from its own
generator state while its attention is edited (SALAD's zero-shot edits,
`segmo.generation.attention_edit`). `SegMo`'s methods check and resolve the sampling
options and hand over here; what the edits do to tokens lives in `segmo.generation`.

    out = model.generate(["a man walks forward, then jumps"], 120, generator=g)
    model.edit(out, (40, 80), "a man spins")                  # frames 40-80 from a new text
    model.edit_text(out, "a man walks forward, then kicks")   # the jump swapped for a kick
"""

from __future__ import annotations

import numbers
from collections.abc import Mapping
from typing import Any, Protocol

import numpy as np
import torch

from segmo.errors import SegmoError
from segmo.generation.attention_edit import (
    EDIT_MODES,
    EditMode,
    TextSide,
    attended_span,
    attention_edit_tokens,
    segment_counterparts,
    source_attention,
)
from segmo.generation.editing import edit_tokens, token_span
from segmo.generation.generate import Precision
from segmo.generation.sampling import SamplingOptions
from segmo.models.mask_transformer import MaskTransformer
from segmo.models.residual_transformer import ResidualTransformer
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.motion.skeleton import SkeletonSpec
from segmo.pipeline.inputs import check_span
from segmo.pipeline.outputs import GenerationOutput


class EditingModel(Protocol):
    """What editing and composing ask of a model (`SegMo` is one)."""

    mask: MaskTransformer
    residual: ResidualTransformer | None
    skeleton: SkeletonSpec
    device: torch.device
    fps: float
    max_frames: int
    has_word_keys: bool

    def encode_motion(self, motion: Any) -> torch.Tensor: ...

    def text_condition(self, texts: list[str], segments: list[list[str]] | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[list[str]]]: ...

    def word_condition(self, texts: list[str], segments: list[list[str]] | None = None,
                       word_text: str | None = None
                       ) -> tuple[torch.Tensor | None, torch.Tensor | None]: ...

    def decode(self, tokens: torch.Tensor, lengths: torch.Tensor, texts: list[str],
               segments: list[list[str]], precision: Precision = "auto") -> GenerationOutput: ...

    def generate(self, texts: list[str], lengths: Any = None, *,
                 generator: torch.Generator | None = None, precision: Precision = "auto",
                 durations: list[list[float] | None] | None = None) -> GenerationOutput: ...


def edit(model: EditingModel, motion: GenerationOutput | Any, span: tuple[int, int], text: str, *,
         segments: list[str] | None, options: SamplingOptions,
         generator: torch.Generator | None, precision: Precision) -> GenerationOutput:
    """`SegMo.edit`: frames [start, end) of `motion` regenerated from `text`."""
    if isinstance(motion, GenerationOutput):
        tokens, lengths = motion.tokens.to(model.device), motion.lengths.to(model.device)
    else:
        tokens = model.encode_motion(motion)
        lengths = torch.tensor([tokens.shape[1] * FRAMES_PER_TOKEN], device=model.device)
    q = model.residual.config.num_quantizers if model.residual is not None else 1
    tokens = tokens[..., :q]
    if tokens.shape[1] > model.mask.config.max_tokens:  # a composition, say
        raise SegmoError(f"SegMo.edit: the motion has {tokens.shape[1] * FRAMES_PER_TOKEN} "
                         f"frames, more than the {model.max_frames} the model reads at once; "
                         "edit one part of a composition before composing")
    start, end = check_span(span, "SegMo.edit")
    if not 0 <= start < end <= int(lengths.min()):
        raise SegmoError(f"SegMo.edit: span must satisfy 0 ≤ start < end ≤ "
                         f"{int(lengths.min())} frames, got {(start, end)}")
    b = tokens.shape[0]
    texts = [text] * b
    sentence, vectors, segment_mask, used = model.text_condition(
        texts, None if segments is None else [segments] * b)
    words, word_mask = model.word_condition(texts, used, options.word_text)
    edited = edit_tokens(model.mask, model.residual, tokens, token_span((start, end)),
                         sentence, vectors, segment_mask, options=options,
                         generator=generator, precision=precision, words=words,
                         word_mask=word_mask)
    return model.decode(edited, lengths, texts, used, precision)


def edit_text(model: EditingModel, source: GenerationOutput, target_text: str | list[str] | None,
              mode: EditMode, *, target_segments: list[list[str]] | None,
              weights: dict[str | int, float] | None, inject_until: float,
              keep_outside: bool, precision: Precision) -> GenerationOutput:
    """`SegMo.edit_text`: `source` decoded again from its generator state, towards
    `target_text`, while its attention is edited as `mode` says."""
    if not isinstance(source, GenerationOutput) or source.generator_state is None \
            or source.sampling is None:
        raise SegmoError("SegMo.edit_text: source must be a GenerationOutput of "
                         "SegMo.generate (it records the generator state to replay)")
    if mode not in EDIT_MODES:
        raise SegmoError(f"SegMo.edit_text: mode must be one of {', '.join(EDIT_MODES)}, "
                         f"got {mode!r}")
    if isinstance(inject_until, bool) or not (isinstance(inject_until, numbers.Real)
                                              and 0.0 <= inject_until <= 1.0):
        raise SegmoError(f"SegMo.edit_text: inject_until must be in [0, 1], got "
                         f"{inject_until!r}")
    b = len(source)
    if target_text is not None and (not isinstance(target_text, (str, list, tuple)) or (
            not isinstance(target_text, str) and not all(isinstance(t, str) for t in target_text))):
        raise SegmoError(f"SegMo.edit_text: target_text must be a string or a list of strings, "
                         f"got {target_text!r:.80}")
    if weights and mode != "reweight":  # they would be ignored without a word
        raise SegmoError(f"SegMo.edit_text: weights are for mode 'reweight'; mode {mode!r} "
                         "takes none")
    if target_text is None:
        if mode != "reweight":
            raise SegmoError(f"SegMo.edit_text: mode {mode!r} needs a target_text")
        targets = list(source.texts)
    else:
        targets = [target_text] * b if isinstance(target_text, str) else list(target_text)
    if len(targets) != b:
        raise SegmoError(f"SegMo.edit_text: {len(targets)} target texts for {b} samples")
    if target_segments is None and target_text is None:
        target_segments = source.segments
    device = model.device
    lengths = source.lengths.to(device)
    sides = []
    for texts, segments in ((source.texts, source.segments), (targets, target_segments)):
        sentence, vectors, segment_mask, used = model.text_condition(list(texts), segments)
        words, word_mask = model.word_condition(list(texts), used, source.sampling.word_text)
        sides.append((TextSide(sentence, vectors, segment_mask, words, word_mask), used))
    (source_side, _), (target_side, used) = sides
    segment_map = [segment_counterparts(s, t, mode) for s, t in zip(source.segments, used)]
    reweight = None
    if mode == "reweight":
        if not weights:
            raise SegmoError("SegMo.edit_text: mode 'reweight' needs weights, e.g. "
                             "{1: 2.0} or {'jumps': 2.0}")
        reweight = [weight_labels(weights, segs, model.has_word_keys) for segs in used]
    editable = None
    if keep_outside:
        changed = [sorted({int(label.split()[1]) for label in row if label.startswith("segment ")})
                   for row in reweight] if reweight is not None else [
            [segment_map[i][k] for k, text in enumerate(used[i], 1)
             if k in segment_map[i] and source.segments[i][segment_map[i][k] - 1] != text]
            for i in range(b)]
        if not all(changed):
            raise SegmoError("SegMo.edit_text: keep_outside needs a changed segment with a "
                             "counterpart in the source (swap, refine, reweight of a segment)")
        control = source_attention(model.mask, model.residual, source_side, lengths,
                                   options=source.sampling, generator_state=source.generator_state,
                                   precision=precision)
        n = source.tokens.shape[1]
        editable = torch.zeros(b, n, dtype=torch.bool, device=device)
        for i, ks in enumerate(changed):
            spans = [attended_span(control, i, k, int(lengths[i]) // FRAMES_PER_TOKEN)
                     for k in ks]
            editable[i, min(a for a, _ in spans):max(e for _, e in spans)] = True
    tokens, _ = attention_edit_tokens(
        model.mask, model.residual, source_side, target_side, lengths, mode=mode,
        segment_map=segment_map, inject_until=float(inject_until), reweight=reweight,
        editable=editable, source_tokens=None if editable is None else source.tokens.to(device),
        options=source.sampling, generator_state=source.generator_state, precision=precision)
    return model.decode(tokens, lengths, targets, used, precision)


def weight_labels(weights: dict[str | int, float], segments: list[str],
                   words: bool) -> dict[str, float]:
    """`edit_text`'s weights → {key label: factor} for one caption's segments."""
    if not isinstance(weights, Mapping):
        raise SegmoError(f"SegMo.edit_text: weights must be a dict such as {{1: 2.0}} or "
                         f"{{'jumps': 2.0}}, got {type(weights).__name__}")
    labels: dict[str, float] = {}
    for key, factor in weights.items():
        # Attention weights are float32: a factor beyond its range would be inf.
        if isinstance(factor, bool) or not isinstance(factor, numbers.Real) \
                or not np.isfinite(factor) or abs(factor) > np.finfo(np.float32).max:
            raise SegmoError(f"SegMo.edit_text: weight of {key!r} must be a finite float32 "
                             f"number, got {factor!r}")
        if isinstance(key, numbers.Integral) and not isinstance(key, bool):
            label = f"segment {int(key)}"
        elif isinstance(key, str) and (key.startswith("segment ") or key.startswith("word ")):
            label = key
        elif isinstance(key, str) and key in segments:
            label = f"segment {segments.index(key) + 1}"
        elif isinstance(key, str) and any(c.isalnum() for c in key) \
                and len(found := [i for i, s in enumerate(segments) if key in s]) == 1:
            label = f"segment {found[0] + 1}"
        elif isinstance(key, str) and any(c.isalnum() for c in key) and found:
            raise SegmoError(f"SegMo.edit_text: weights key {key!r} is part of segments "
                             f"{[i + 1 for i in found]} of {segments!r}; give one's number or "
                             "whole text")
        else:
            raise SegmoError(f"SegMo.edit_text: weights key {key!r} names no segment of "
                             f"{segments!r} (give its number, its text, or 'segment k')")
        if label.startswith("word ") and not words:
            raise SegmoError(f"SegMo.edit_text: {label!r}: this model has no word keys "
                             "(text_tokens 'none', or words read by cross-attention)")
        if label.startswith("segment ") and not 1 <= int(label.split()[1]) <= len(segments):
            raise SegmoError(f"SegMo.edit_text: {label!r}: the caption has "
                             f"{len(segments)} segments")
        labels[label] = float(factor)
    return labels
