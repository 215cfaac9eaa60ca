"""The mask transformer: text + segments + masked base tokens → base-token logits (spec §4).

Besides the logits, the forward pass returns the trunk's output features at the motion
positions and the projected text vectors of the segments: the segment-alignment loss
(spec §5, `segmo.tasks.alignment_loss` through the head of `segmo.models.alignment`)
aggregates the former over motion segments and contrasts them with the latter.

Training helpers are plain functions so that the task owns the loop:

    inputs, target_mask = mask_tokens(indices, token_mask, model.config.codebook_size, generator)
    out = model(inputs, token_mask, sentence, segments, segment_mask, drop_condition)
    loss = masked_token_loss(out.logits, indices, target_mask)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from segmo.models.alignment import AlignmentConfig, AlignmentHead
from segmo.models.pretrained import Pretrained
from segmo.models.segment_timing import SegmentTiming, TimingHead, predicted_spans
from segmo.models.text_prefix import Condition, EncodedPrefix, PrefixKeys, TextPrefix
from segmo.models.transformer import Linear, TokenHead, TransformerConfig, Trunk, init_weights


def cosine_schedule(t: torch.Tensor | float) -> torch.Tensor | float:
    """Masking ratio γ(t) = cos(πt/2) for t ∈ [0, 1] (1 → everything masked)."""
    if isinstance(t, torch.Tensor):
        return torch.cos(t * (math.pi / 2))
    return math.cos(t * math.pi / 2)


@dataclass
class MaskTransformerConfig(TransformerConfig):
    # SegMo's segment-alignment head (spec §5); None = plain MoMask (no alignment).
    alignment: AlignmentConfig | None = None
    # MLA-Gen's sink mask (eq. 8): at decoding times t > sink_mask_t (t from 0, all masked,
    # to 1, done; in training the t of the mask ratio), motion queries may not attend to
    # the sentence key, the sink of the diagnostics. None = off; the paper's strong 0.2
    # and weak 0.6 are the values to measure.
    sink_mask_t: float | None = None
    # Segment timing (`segmo.models.segment_timing`): each motion position also carries the
    # number of the segment it belongs to, from spans given or predicted by a timing head.
    # False = the model without it.
    segment_timing: bool = False
    # With segment timing, each motion position also gets its own segment's projected text
    # vector (`SegmentTiming` with text), not only the segment's number. False = without.
    position_text: bool = False

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.alignment, dict):  # read back from config.json
            self.alignment = AlignmentConfig.from_dict(self.alignment)


@dataclass
class MaskTransformerOutput:
    """logits (b, n, codebook_size); motion_features (b, n, dim) trunk outputs at the motion
    positions (n → m when `forward_condition` is given positions); segment_features
    (b, a, dim) and sentence_features (b, dim) the projected text vectors
    (`Condition.content`): what each segment says, without its slot order, so that
    alignment cannot be met by order alone (`TextPrefix`)."""

    logits: torch.Tensor
    motion_features: torch.Tensor
    segment_features: torch.Tensor
    sentence_features: torch.Tensor


class MaskTransformer(nn.Module, Pretrained):
    """Bidirectional transformer over `[sentence, segments 1..A, base tokens]`.

    Token ids: codes 0..codebook_size-1, then `mask_id` = codebook_size, `pad_id` =
    codebook_size + 1. Positions where `token_mask` is False are replaced by `pad_id` and
    excluded from attention, so their input ids do not matter.
    """

    kind = "mask"
    config_class = MaskTransformerConfig

    def __init__(self, config: MaskTransformerConfig) -> None:
        super().__init__()
        self.config = config
        self.meta: dict = {}
        self.mask_id = config.codebook_size
        self.pad_id = config.codebook_size + 1
        self.token_embedding = nn.Embedding(config.codebook_size + 2, config.dim)
        self.prefix = TextPrefix(config.text_dim, config.dim, config.max_segments,
                                 config.text_tokens, config.max_words, config.word_attention,
                                 config.word_norm)
        self.trunk = Trunk(config.dim, config.depth, config.heads, config.ff_dim, config.dropout,
                           config.norm_first, config.max_tokens, config.memory_slots,
                           config.text_tokens == "words" and config.word_attention == "cross")
        self.head = TokenHead(config.dim)
        self.classifier = Linear(config.dim, config.codebook_size)
        self.apply(init_weights)
        # Built after init_weights so the head keeps its own initialisation; absent without
        # alignment so that no parameter goes without gradient (DDP rejects that).
        self.alignment = (AlignmentHead(config.dim, config.alignment)
                          if config.alignment is not None else None)
        if config.position_text and not config.segment_timing:
            raise ValueError("MaskTransformer: position_text needs segment_timing")
        # Absent without timing, so that such a model is exactly the one before it.
        if config.segment_timing:
            self.timing = SegmentTiming(config.dim, config.max_segments, config.position_text)
            self.timing_head = TimingHead(config.dim)
            self.timing.apply(init_weights)
            self.timing_head.apply(init_weights)

    def condition(self, sentence: torch.Tensor, segments: torch.Tensor,
                  segment_mask: torch.Tensor, drop_condition: torch.Tensor | None = None,
                  unordered: torch.Tensor | None = None, words: torch.Tensor | None = None,
                  word_mask: torch.Tensor | None = None,
                  keep_local: torch.Tensor | None = None, spans: torch.Tensor | None = None,
                  span_known: torch.Tensor | None = None,
                  hidden_segments: torch.Tensor | None = None) -> Condition:
        """Prefix tokens (b, 1 + a, dim) and their encoding by the trunk, which does not
        depend on the motion tokens: computed once per generation, reused at every step.
        `unordered` (b,) bool: rows whose segments enter without order; `words`
        (b, l, text_dim), `word_mask` (b, l): the caption's word features, used where
        `config.text_tokens` is "words" (`TextPrefix`); `spans` (b, a, 2) long token spans
        of the segments and `span_known` (b, a) bool (None = all): the segment timing of a
        model with it, kept as `Condition.token_segments` for the motion positions
        (`predict_spans`); a model without timing refuses spans; `hidden_segments` (b, a)
        bool: segment slots masked out of attention, their timing with them (`TextPrefix`)."""
        condition = self.prefix(sentence, segments, segment_mask, drop_condition, unordered,
                                words, word_mask, keep_local, hidden_segments)
        if spans is not None:
            if not hasattr(self, "timing"):
                raise ValueError("MaskTransformer: this model has no segment timing "
                                 "(segment_timing: false); give no spans")
            if tuple(spans.shape) != (*segment_mask.shape, 2):
                raise ValueError(f"MaskTransformer: spans must be (b, a, 2) = "
                                 f"{(*segment_mask.shape, 2)}, got {tuple(spans.shape)}")
            known = condition.mask[:, 1:1 + segment_mask.shape[1]]  # not in dropped rows
            if span_known is not None:
                known = known & span_known.bool()
            condition.token_segments = self.timing.token_segments(
                spans.long(), known, self.config.max_tokens)
        condition.encoded = self.trunk.encoded(condition)
        return condition

    def predict_spans(self, segments: torch.Tensor, segment_mask: torch.Tensor,
                      lengths: torch.Tensor) -> torch.Tensor:
        """The timing head's token spans: segments (b, a, text_dim) in execution order,
        segment_mask (b, a) bool, lengths (b,) motion tokens → (b, a, 2) long spans that
        tile each motion (`segmo.models.segment_timing.shares_to_spans`)."""
        if not hasattr(self, "timing_head"):
            raise ValueError("MaskTransformer: this model has no segment timing "
                             "(segment_timing: false)")
        mask = segment_mask.bool()
        content = self.prefix.project(segments.masked_fill(~mask[..., None], 0.0))
        return predicted_spans(self.timing_head, content, mask, lengths)

    def forward_condition(self, indices: torch.Tensor, token_mask: torch.Tensor,
                          condition: Condition, positions: torch.Tensor | None = None,
                          sink_rows: torch.Tensor | None = None) -> MaskTransformerOutput:
        """indices (b, n) long, token_mask (b, n) bool, condition from `condition()`;
        positions (b, m) long: where logits and motion features are wanted (None = all n
        positions; decoding asks for the positions it samples, `Trunk.forward_motion`);
        sink_rows (b,) bool: rows whose motion queries may not attend to the sentence key
        (the sink mask, `sink_mask_rows`)."""
        if indices.shape != token_mask.shape or indices.shape[0] != condition.tokens.shape[0]:
            raise ValueError(f"MaskTransformer: indices {tuple(indices.shape)}, token_mask "
                             f"{tuple(token_mask.shape)} and condition batch "
                             f"{condition.tokens.shape[0]} disagree")
        token_mask = token_mask.bool()
        indices = torch.where(token_mask, indices, self.pad_id)
        encoded = self.trunk.encoded(condition)
        if sink_rows is not None and bool(sink_rows.any()):
            encoded = without_sentence(encoded, sink_rows)
        tokens = self.token_embedding(indices)
        if condition.token_segments is not None:
            tokens = tokens + self.timing(condition.token_segments[:, :indices.shape[1]],
                                          condition.content[:, 1:])
        motion = self.trunk.forward_motion(tokens, token_mask, encoded, positions)
        return MaskTransformerOutput(
            logits=self.classifier(self.head(motion)),
            motion_features=motion,
            segment_features=condition.content[:, 1:],  # the segments (content has no words)
            sentence_features=condition.content[:, 0],
        )

    def forward(self, indices: torch.Tensor, token_mask: torch.Tensor, sentence: torch.Tensor,
                segments: torch.Tensor, segment_mask: torch.Tensor,
                drop_condition: torch.Tensor | None = None,
                unordered: torch.Tensor | None = None, words: torch.Tensor | None = None,
                word_mask: torch.Tensor | None = None,
                sink_rows: torch.Tensor | None = None,
                keep_local: torch.Tensor | None = None, spans: torch.Tensor | None = None,
                span_known: torch.Tensor | None = None,
                hidden_segments: torch.Tensor | None = None) -> MaskTransformerOutput:
        """indices (b, n) long with masked positions already replaced by `mask_id`;
        token_mask (b, n) bool; sentence (b, text_dim); segments (b, a, text_dim) in
        execution order; segment_mask (b, a) bool; drop_condition (b,) bool (classifier-free
        guidance); unordered (b,) bool (segments as a set, as grounding uses them);
        sink_rows (b,) bool: the sink mask's rows (`sink_mask_rows`); keep_local (b,) bool:
        dropped rows that keep their segments and words (`TextPrefix`); spans (b, a, 2) and
        span_known (b, a): the segment timing; hidden_segments (b, a) bool: segment slots
        masked out of attention (`condition`)."""
        condition = self.condition(sentence, segments, segment_mask, drop_condition, unordered,
                                   words, word_mask, keep_local, spans, span_known,
                                   hidden_segments)
        return self.forward_condition(indices, token_mask, condition, sink_rows=sink_rows)

    def sink_mask_rows(self, t: torch.Tensor) -> torch.Tensor | None:
        """t (b,) decoding times → (b,) bool rows the sink mask applies to (t >
        `config.sink_mask_t`), None when the model has no sink mask."""
        if self.config.sink_mask_t is None:
            return None
        return t > self.config.sink_mask_t


def without_sentence(encoded: EncodedPrefix, rows: torch.Tensor) -> EncodedPrefix:
    """The encoded prefix with the sentence key (slot 0) masked out of the motion queries'
    attention in `rows` (b,) bool (the sink mask); keys and values are shared."""
    blocks = []
    for block in encoded.blocks:
        mask = block.mask.clone()
        mask[:, 0] &= ~rows
        blocks.append(PrefixKeys(block.keys, block.values, mask, block.words))
    return EncodedPrefix(blocks=blocks, labels=encoded.labels, text_slots=encoded.text_slots)


def mask_ratio_time(target_mask: torch.Tensor, token_mask: torch.Tensor) -> torch.Tensor:
    """(b,) the decoding time t whose masking ratio γ(t) = cos(πt/2) is each row's share of
    masked tokens (`mask_tokens`): what the sink mask compares with its threshold."""
    ratio = target_mask.sum(1).float() / token_mask.sum(1).clamp(min=1).float()
    return torch.arccos(ratio.clamp(0.0, 1.0)) * (2.0 / math.pi)


def mask_tokens(indices: torch.Tensor, token_mask: torch.Tensor, codebook_size: int,
                generator: torch.Generator | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Corrupt base tokens for one training step (spec §4).

    Per sample, t ~ U(0, 1) and max(1, round(γ(t)·len)) valid tokens are chosen at random;
    of those, 10 % get a random code, 80 % become [MASK] (id codebook_size) and 10 % stay.
    Padded positions become [PAD] (id codebook_size + 1).

    indices (b, n) long codes, token_mask (b, n) bool →
    (inputs (b, n) long, target_mask (b, n) bool: the chosen positions, to be predicted).
    """
    token_mask = token_mask.bool()
    lengths = token_mask.sum(dim=1)
    if bool((lengths == 0).any()):
        raise ValueError("mask_tokens: every sample needs at least one valid token")
    b, n = indices.shape
    device = indices.device
    t = torch.rand(b, generator=generator, device=device)
    count = torch.round(cosine_schedule(t) * lengths).long().clamp(min=1)
    count = torch.minimum(count, lengths)
    # Rank valid positions in a random order; padded ones sort last and are never chosen.
    noise = torch.rand(b, n, generator=generator, device=device).masked_fill(~token_mask, 2.0)
    ranks = noise.argsort(dim=1).argsort(dim=1)
    target_mask = ranks < count[:, None]
    choice = torch.rand(b, n, generator=generator, device=device)
    random_codes = torch.randint(0, codebook_size, (b, n), generator=generator, device=device)
    inputs = torch.where(target_mask & (choice < 0.8), codebook_size, indices)
    inputs = torch.where(target_mask & (choice >= 0.8) & (choice < 0.9), random_codes, inputs)
    inputs = torch.where(token_mask, inputs, codebook_size + 1)
    return inputs, target_mask


def masked_token_loss(logits: torch.Tensor, targets: torch.Tensor,
                      target_mask: torch.Tensor,
                      weights: torch.Tensor | None = None) -> torch.Tensor:
    """Mean cross-entropy over the positions of `target_mask`, weighted by `weights`.

    logits (b, n, v), targets (b, n) long, target_mask (b, n) bool, weights (b, n) float or
    None (every position alike) → scalar. The residual task uses it too, with target_mask =
    token_mask (every valid token of layer j).
    """
    if weights is None:
        if not bool(target_mask.any()):
            raise ValueError("masked_token_loss: target_mask selects no position")
        return F.cross_entropy(logits[target_mask].float(), targets[target_mask])
    return weighted_mean(masked_token_losses(logits, targets, target_mask),
                         weights[target_mask].float())


def weighted_mean(losses: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """sum(losses · weights) / sum(weights), for per-position losses and their weights."""
    return (losses * weights).sum() / weights.sum().clamp(min=1e-8)


def masked_token_losses(logits: torch.Tensor, targets: torch.Tensor,
                        target_mask: torch.Tensor) -> torch.Tensor:
    """The cross-entropy at each position of `target_mask`, (m,) float32 in row-major order
    of its True positions (as `tensor[target_mask]` orders them)."""
    if not bool(target_mask.any()):
        raise ValueError("masked_token_loss: target_mask selects no position")
    return F.cross_entropy(logits[target_mask].float(), targets[target_mask], reduction="none")
