"""Editing a generated motion through its attention (SALAD §3.3 and its supplement, after
Prompt-to-Prompt), on segmo's masked decoding.

The source generation is run again from its text and its generator's state, with every
block's attention stored (`segmo.models.attention_control`); then the target text is
decoded from the same generator state while the attention is edited:

- "swap": one segment's (or word's) text replaced. For the first `inject_until` share of
  the mask transformer's decoding steps, the motion queries take the source's attention
  weights (to the prefix and to the motion), with the target's values; the target's own
  attention afterwards, and in the residual transformer.
- "add" / "refine": a segment added, or a segment's text refined (a modifier added): the
  keys with a counterpart in the source (the sentence, segments whose text is kept or
  refined, the motion) take the source's weights in those steps, the others (the new
  segment) the target's.
- "reweight": the attention to chosen keys (a segment or a word) multiplied by a factor
  c in every pass of both transformers, without renormalising (negative c suppresses).

An edit that changes nothing (the same text, `inject_until` anything, or c = 1) gives the
source's tokens bit for bit; `inject_until = 0` gives a plain generation from the target
text. Segments are matched between the texts by `segment_counterparts`.

    tokens = attention_edit_tokens(mask, residual, source, target, lengths, mode="swap",
                                   segment_map=[{1: 1, 2: 2}], generator_state=state)
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from typing import Literal

import torch

from segmo.generation.generate import (
    Precision,
    fill_tokens,
    generate_tokens,
    token_mask_from_lengths,
)
from segmo.generation.sampling import SamplingOptions
from segmo.models.attention_control import AttentionControl, Site, Stored
from segmo.models.mask_transformer import MaskTransformer
from segmo.models.residual_transformer import ResidualTransformer

EditMode = Literal["swap", "add", "refine", "reweight"]
EDIT_MODES: tuple[str, ...] = ("swap", "add", "refine", "reweight")
# The share of decoding steps that take the source's attention; SALAD's value for its
# diffusion steps, to be re-measured for masked decoding (README, "Editing by attention").
INJECT_UNTIL = 0.5


@dataclass
class TextSide:
    """What `generate_tokens` takes for one text: sentence (b, text_dim), segments
    (b, a, text_dim), segment_mask (b, a) bool, words (b, l, text_dim) and word_mask
    (b, l) for models with word keys, and durations (b, a) of the segments for a mask
    transformer with segment timing (None, or a row of 0: its timing head's)."""

    sentence: torch.Tensor
    segments: torch.Tensor
    segment_mask: torch.Tensor
    words: torch.Tensor | None = None
    word_mask: torch.Tensor | None = None
    durations: torch.Tensor | None = None


def segment_counterparts(source: list[str], target: list[str], mode: str) -> dict[int, int]:
    """{target segment k: its source segment} (1-based) for the keys that take the source's
    attention. "swap" with as many segments: each to the one in its place. Otherwise the
    segments an ordered match keeps (difflib), and, where one stretch of segments was
    replaced by as many, each to the one in its place (a refined or swapped text)."""
    if mode == "swap" and len(source) == len(target):
        return {k: k for k in range(1, len(target) + 1)}
    pairs: dict[int, int] = {}
    matcher = difflib.SequenceMatcher(a=source, b=target, autojunk=False)
    for tag, a0, a1, b0, b1 in matcher.get_opcodes():
        if tag == "equal" or (tag == "replace" and a1 - a0 == b1 - b0):
            pairs.update({b0 + i + 1: a0 + i + 1 for i in range(b1 - b0)})
    return pairs


def _key_index(labels: list[str], stored: Stored, segment_map: list[dict[int, int]],
               words: bool, device: torch.device) -> torch.Tensor:
    """(rows, keys) long: per conditional row, the source key each target key takes its
    weight from, −1 for none. Sentence to sentence, segment k to segment_map[row][k], word
    w to word w where `words`, motion i to motion i."""
    where = {label: i for i, label in enumerate(stored.labels)}
    rows = []
    for mapping in segment_map:
        index = []
        for label in labels:
            if label.startswith("segment "):
                source = mapping.get(int(label.split()[1]))
                index.append(-1 if source is None else where.get(f"segment {source}", -1))
            elif label.startswith("word "):
                index.append(where.get(label, -1) if words else -1)
            else:  # sentence, motion i
                index.append(where.get(label, -1))
        rows.append(index)
    return torch.tensor(rows, dtype=torch.long, device=device)


def inject(site: Site, weights: torch.Tensor, stored: Stored | None,
           key_index: torch.Tensor) -> torch.Tensor:
    """The target's weights (rows, heads, m, keys) with those of its conditional rows that
    have a source counterpart (key_index (c, keys), a stored query at the same motion
    position, a valid source key) replaced by the source's."""
    c = site.conditional
    if stored is None or c == 0:
        return weights
    target = weights[:c]
    heads, m = target.shape[1], target.shape[2]
    n = sum(label.startswith("motion ") for label in site.labels)
    device = weights.device
    asked = (torch.arange(m, device=device).expand(c, m) if site.queries is None
             else site.queries[:c])
    if stored.queries is None:
        query = asked
    else:  # the source computed its last block only at its own sampled positions
        table = torch.full((c, n), -1, dtype=torch.long, device=device)
        table.scatter_(1, stored.queries, torch.arange(stored.queries.shape[1], device=device)
                       .expand_as(stored.queries))
        query = table.gather(1, asked)
    keys = key_index.clamp(min=0)
    has_key = (key_index >= 0) & stored.key_valid.gather(1, keys)
    source = stored.weights.gather(2, query.clamp(min=0)[:, None, :, None].expand(
        c, heads, m, stored.weights.shape[3]))
    source = source.gather(3, keys[:, None, None, :].expand(c, heads, m, keys.shape[1]))
    take = (query >= 0)[:, None, :, None] & has_key[:, None, None, :]
    out = weights.clone()
    out[:c] = torch.where(take, source, target)
    return out


def attention_edit_tokens(
    mask_model: MaskTransformer,
    residual_model: ResidualTransformer | None,
    source: TextSide,
    target: TextSide,
    lengths: torch.Tensor,
    *,
    mode: EditMode = "swap",
    segment_map: list[dict[int, int]] | None = None,
    inject_until: float | None = None,
    reweight: list[dict[str, float]] | None = None,
    editable: torch.Tensor | None = None,
    source_tokens: torch.Tensor | None = None,
    options: SamplingOptions | None = None,
    generator_state: torch.Tensor,
    precision: Precision = "auto",
) -> tuple[torch.Tensor, AttentionControl]:
    """The target's tokens (b, n, q) decoded with the source's attention edited in, and the
    control holding the source's stored attention (for spans derived from it).

    source, target: the two texts' conditions (b rows each); lengths (b,) frames;
    segment_map: per row, {target segment: source segment} of the keys that take the
    source's weights (default: each segment to the one in its place); inject_until: the
    share of the mask transformer's steps that take them (default `INJECT_UNTIL`; "swap",
    "add" and "refine" only: "reweight" edits every pass); reweight: per row,
    {key label ("segment k", "word w"): factor} ("reweight" mode, which needs no source
    pass); editable (b, n) bool with source_tokens (b, n, q): decode only those positions,
    the others kept from source_tokens (an edit confined to a span; decoded without segment
    spans, as `edit_tokens` is, so the sides' durations are unused); generator_state: the
    state of the generator the source was drawn with (`torch.Generator.get_state()`), used
    for the source and for the target.
    """
    if mode not in EDIT_MODES:
        raise ValueError(f"attention edit: mode must be one of {', '.join(EDIT_MODES)}, "
                         f"got {mode!r}")
    if mode == "reweight" and inject_until is not None:  # it would be ignored without a word
        raise ValueError("attention edit: inject_until is for modes 'swap', 'add' and 'refine'; "
                         "'reweight' edits every pass")
    inject_until = INJECT_UNTIL if inject_until is None else inject_until
    if not 0.0 <= inject_until <= 1.0:
        raise ValueError(f"attention edit: inject_until must be in [0, 1], got {inject_until}")
    options = options or SamplingOptions()
    device = source.sentence.device
    b = source.sentence.shape[0]
    control = AttentionControl({"mask": mask_model, "residual": residual_model})

    def decode(side: TextSide) -> torch.Tensor:
        generator = torch.Generator(device=device).set_state(generator_state)
        if editable is None:
            return generate_tokens(mask_model, residual_model, side.sentence, side.segments,
                                   side.segment_mask, lengths, options=options,
                                   generator=generator, precision=precision, words=side.words,
                                   word_mask=side.word_mask, durations=side.durations)
        token_mask = token_mask_from_lengths(lengths, mask_model.config.max_tokens)
        return fill_tokens(mask_model, residual_model, source_tokens, editable & token_mask,
                           token_mask, side.sentence, side.segments, side.segment_mask, options,
                           generator, precision, side.words, side.word_mask)

    if mode == "reweight":
        factors = reweight or [{} for _ in range(b)]

        def edit(site: Site, weights: torch.Tensor, stored: Stored | None) -> torch.Tensor:
            scale = torch.ones(weights.shape[0], weights.shape[3], dtype=weights.dtype,
                               device=weights.device)
            for row, chosen in enumerate(factors[: site.conditional]):
                for label, factor in chosen.items():
                    if label in site.labels:
                        scale[row, site.labels.index(label)] = factor
            return weights * scale[:, None, None, :]

        with control.editing(edit):
            return decode(target), control

    with control.storing():
        decode(source)
    if segment_map is None:
        segment_map = [{k: k for k in range(1, target.segments.shape[1] + 1)} for _ in range(b)]
    until = round(inject_until * options.steps)
    index_cache: dict[tuple[int, int], torch.Tensor] = {}

    def edit(site: Site, weights: torch.Tensor, stored: Stored | None) -> torch.Tensor:
        if site.stage != "mask" or site.step >= until or stored is None:
            return weights
        key = (len(site.labels), site.block)
        if key not in index_cache:
            index_cache[key] = _key_index(site.labels, stored, segment_map[: site.conditional],
                                          words=mode == "swap", device=weights.device)
        return inject(site, weights, stored, index_cache[key])

    with control.editing(edit):
        return decode(target), control


def source_attention(mask_model: MaskTransformer, residual_model: ResidualTransformer | None,
                     source: TextSide, lengths: torch.Tensor, *, options: SamplingOptions,
                     generator_state: torch.Tensor, precision: Precision = "auto"
                     ) -> AttentionControl:
    """The source generation run again with its attention stored (for `attended_span`)."""
    control = AttentionControl({"mask": mask_model, "residual": residual_model})
    with control.storing():
        generate_tokens(mask_model, residual_model, source.sentence, source.segments,
                        source.segment_mask, lengths, options=options,
                        generator=torch.Generator(device=source.sentence.device)
                        .set_state(generator_state), precision=precision,
                        words=source.words, word_mask=source.word_mask,
                        durations=source.durations)
    return control


def attended_span(control: AttentionControl, row: int, segment: int, n: int) -> tuple[int, int]:
    """The tokens [start, end) the source's motion queries gave most of their segment
    attention to segment `segment` (1-based) at the last decoding step, averaged over blocks
    and heads (attention grounding); the whole motion when no token did."""
    last = max(step for stage, step, _ in control.stored if stage == "mask")
    blocks = [s for (stage, step, _), s in control.stored.items()
              if stage == "mask" and step == last and s.queries is None]
    segments = [i for i, label in enumerate(blocks[0].labels) if label.startswith("segment ")]
    mean = torch.stack([s.weights[row, :, :, segments].mean(dim=0) for s in blocks]).mean(dim=0)
    valid = blocks[0].key_valid[row, segments]
    winner = mean.masked_fill(~valid, -1.0).argmax(dim=1)[:n]
    hits = torch.nonzero(winner == segment - 1).flatten()
    if hits.numel() == 0:
        return 0, n
    return int(hits.min()), int(hits.max()) + 1
