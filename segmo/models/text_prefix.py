"""The text prefix: captions' vectors → the prefix slots the trunk runs before the motion.

`TextPrefix` projects the sentence, the ordered segments (and, with word keys, the words)
to prefix tokens with type and order embeddings; the result is a `Condition`, computed once
per generation. The trunk (`segmo.models.transformer.Trunk`) runs the prefix on its own into
an `EncodedPrefix`: per block, the `PrefixKeys` the motion tokens attend to. `prefix_labels`
names each slot ("sentence", "segment 1", …, "word 0", …), as attention recordings do.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

TEXT_TOKENS: tuple[str, ...] = ("none", "words")
WORD_ATTENTION: tuple[str, ...] = ("prefix", "cross")
WORD_NORM: tuple[str, ...] = ("none", "unit")


@dataclass
class PrefixKeys:
    """One block's keys and values of the encoded prefix, for the motion tokens to attend to.

    keys, values: (b, heads, p, head_dim); mask: (b, p) bool, True = may be attended to.
    """

    keys: torch.Tensor
    values: torch.Tensor
    mask: torch.Tensor
    # word_attention "cross": this block's keys and values of the word tokens, (b, heads,
    # l, head_dim) each, and their mask (b, l) bool; None for a model without it.
    words: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None

    def rows(self, index: torch.Tensor) -> PrefixKeys:
        """The keys of batch rows `index` (r,) long."""
        words = None if self.words is None else tuple(t[index] for t in self.words)
        return PrefixKeys(self.keys[index], self.values[index], self.mask[index], words)


def prefix_labels(num_segments: int, num_words: int = 0) -> list[str]:
    """The kind of each prefix slot, in order: "sentence", "segment 1".."segment A", then
    "word 0".."word L−1" where the model has word keys."""
    return ["sentence", *(f"segment {k}" for k in range(1, num_segments + 1)),
            *(f"word {w}" for w in range(num_words))]


@dataclass
class Condition:
    """Text conditioning as prefix tokens, computed once per generation.

    tokens:  (b, p, dim) prefix embeddings (p = 1 + A: sentence, segments 1..A; + L word
             slots in a model with word keys).
    mask:    (b, p) bool, True = the slot takes part in attention.
    content: (b, 1 + A, dim) the projected sentence and segment vectors alone, without type
             or order embeddings: what each slot says, the text side of segment alignment.
    encoded: the prefix run through the trunk (the models' `condition()` fill it, so that
             one encoding serves every pass of a generation); None = encode on each call.
    labels:  the kind of each of the p slots (`prefix_labels`).
    """

    tokens: torch.Tensor
    mask: torch.Tensor
    content: torch.Tensor
    encoded: EncodedPrefix | None = None
    labels: list[str] | None = None
    # word_attention "cross": the word tokens (b, l, dim) and their mask (b, l), read by the
    # blocks' cross-attention instead of entering the prefix; None otherwise.
    words: torch.Tensor | None = None
    word_mask: torch.Tensor | None = None
    # Segment timing (`segmo.models.segment_timing`): the segment each motion position
    # belongs to, (b, max_tokens) long, −1 where not known; None without timing.
    token_segments: torch.Tensor | None = None

    def rows(self, index: torch.Tensor) -> Condition:
        """The condition of batch rows `index` (r,) long, its encoding included."""
        encoded = None if self.encoded is None else EncodedPrefix(
            blocks=[k.rows(index) for k in self.encoded.blocks],
            labels=self.encoded.labels, text_slots=self.encoded.text_slots)
        words = None if self.words is None else self.words[index]
        word_mask = None if self.word_mask is None else self.word_mask[index]
        token_segments = None if self.token_segments is None else self.token_segments[index]
        return Condition(tokens=self.tokens[index], mask=self.mask[index],
                         content=self.content[index], encoded=encoded, labels=self.labels,
                         words=words, word_mask=word_mask, token_segments=token_segments)


class TextPrefix(nn.Module):
    """Projects pooled text vectors to prefix tokens: [sentence, segment 1..A].

    One projection is shared by the sentence and its segments (they come from the same
    frozen encoder); a learned type embedding tells the sentence from the segments, and a
    learned order embedding tells the trunk which segment comes first. The order has to
    come from the slots: pooled sentence vectors hardly encode it (MiniLM gives cosine
    0.985 between "a person walks forward, then waves" and "a person waves, then walks
    forward"), and without it the model cannot know which action to put where.

    Because the slots are ordered, the alignment loss must not compare motion segments with
    anything that carries the slot order (it would be met by slot i ↔ i-th span alone, and
    teach nothing about content): its text side is `Condition.content`, the projected
    vectors without type or order embeddings. Rows marked `unordered` get no order
    embedding: their segments enter as a set and a motion token must find its segment by
    what the segment says. Trained on a share of the samples (`MaskTask.order_drop_prob`),
    that mode is what grounding and retrieval use, so that they locate a segment by what the
    motion does rather than by where the caption put it. Dropping the condition
    (classifier-free guidance) masks the whole prefix out of attention, so the unconditional
    branch is a row of the same batch with no parameter of its own.

    With `text_tokens="words"` the caption's per-word features (start and end tokens
    included) follow as L further slots, through the same projection, with a word kind
    embedding and a learned word-position embedding; padded words are masked out of
    attention and dropped with the rest of the condition. A prefix without word keys
    ignores `words`. With `word_norm="unit"` each word vector is scaled to unit length
    before the projection (padded words stay 0).
    """

    def __init__(self, text_dim: int, dim: int, max_segments: int, text_tokens: str = "none",
                 max_words: int = 77, word_attention: str = "prefix",
                 word_norm: str = "none") -> None:
        super().__init__()
        if text_tokens not in TEXT_TOKENS:
            raise ValueError(f"TextPrefix: text_tokens must be one of {', '.join(TEXT_TOKENS)}, "
                             f"got {text_tokens!r}")
        if word_attention not in WORD_ATTENTION:
            raise ValueError(f"TextPrefix: word_attention must be one of "
                             f"{', '.join(WORD_ATTENTION)}, got {word_attention!r}")
        if word_norm not in WORD_NORM:
            raise ValueError(f"TextPrefix: word_norm must be one of {', '.join(WORD_NORM)}, "
                             f"got {word_norm!r}")
        self.word_attention = word_attention
        self.word_norm = word_norm
        self.max_segments = max_segments
        self.text_tokens = text_tokens
        self.max_words = max_words
        self.project = nn.Linear(text_dim, dim)
        self.types = nn.Parameter(torch.randn(2, dim) * 0.02)  # sentence, segment
        self.order = nn.Parameter(torch.randn(max_segments, dim) * 0.02)  # segment 1..A
        if text_tokens == "words":  # absent otherwise: a model without words is unchanged
            self.word_type = nn.Parameter(torch.randn(1, dim) * 0.02)
            self.word_position = nn.Parameter(torch.randn(max_words, dim) * 0.02)

    def forward(
        self,
        sentence: torch.Tensor,
        segments: torch.Tensor,
        segment_mask: torch.Tensor,
        drop_condition: torch.Tensor | None = None,
        unordered: torch.Tensor | None = None,
        words: torch.Tensor | None = None,
        word_mask: torch.Tensor | None = None,
        keep_local: torch.Tensor | None = None,
        hidden_segments: torch.Tensor | None = None,
    ) -> Condition:
        """sentence (b, text_dim), segments (b, a, text_dim) in execution order,
        segment_mask (b, a) bool, drop_condition (b,) bool or None, unordered (b,) bool or
        None: rows whose segments enter as a set, without order embeddings; words
        (b, l, text_dim) and word_mask (b, l) bool: the caption's word features (a model
        with word keys needs them, one without ignores them); keep_local (b,) bool: rows of
        `drop_condition` that keep their local condition (segments, words) and drop the
        sentence only (MLA-Gen's unconditional branch with local features); hidden_segments
        (b, a) bool: segment slots masked out of attention, each row keeping the rest of its
        text (segment dropout in training, per-segment guidance at generation); what they
        say stays in `Condition.content` → Condition with p = 1 + a (+ l)."""
        b, a = segment_mask.shape
        if sentence.dim() != 2 or segments.shape[:2] != (b, a) or sentence.shape[0] != b:
            raise ValueError(
                "TextPrefix: expected sentence (b, text_dim), segments (b, a, text_dim), "
                f"segment_mask (b, a); got {tuple(sentence.shape)}, {tuple(segments.shape)}, "
                f"{tuple(segment_mask.shape)}"
            )
        if a > self.max_segments:
            raise ValueError(f"TextPrefix: {a} segment slots given, the model has {self.max_segments}")
        segment_mask = segment_mask.bool()
        valid = torch.cat([segment_mask.new_ones(b, 1), segment_mask], dim=1)
        # Masked keys get zero attention weight, but 0 · NaN is NaN: zero what an empty slot
        # holds (NaN padding included) so that it cannot leak.
        text = torch.cat([sentence[:, None], segments], dim=1)  # (b, 1 + a, text_dim)
        content = self.project(text.masked_fill(~valid[..., None], 0.0))
        order = self.order[:a].expand(b, a, -1)
        if unordered is not None:
            order = order * ~unordered.bool()[:, None, None]
        slots = torch.cat([self.types[:1].expand(b, 1, -1), self.types[1:] + order], dim=1)
        dropped = None
        if drop_condition is not None:
            dropped = drop_condition.bool()[:, None].expand(b, 1 + a)
            if keep_local is not None:  # those rows drop the sentence slot only
                dropped = dropped & (~keep_local.bool()[:, None]
                                     | (torch.arange(1 + a, device=dropped.device) == 0))
            valid = valid & ~dropped
        if hidden_segments is not None:
            if tuple(hidden_segments.shape) != (b, a):
                raise ValueError(f"TextPrefix: hidden_segments must be (b, a) = {(b, a)}, got "
                                 f"{tuple(hidden_segments.shape)}")
            valid = valid & ~F.pad(hidden_segments.bool(), (1, 0))
        tokens = (content + slots).masked_fill(~valid[..., None], 0.0)
        if self.text_tokens == "none":
            return Condition(tokens=tokens, mask=valid, content=content, labels=prefix_labels(a))
        if words is None or word_mask is None:
            raise ValueError("TextPrefix: this model conditions on words (text_tokens='words'): "
                             "give words and word_mask")
        l = word_mask.shape[1]  # noqa: E741
        if words.shape[:2] != (b, l) or word_mask.shape[0] != b or words.dim() != 3:
            raise ValueError(f"TextPrefix: expected words (b, l, text_dim) and word_mask (b, l) "
                             f"for b={b}; got {tuple(words.shape)}, {tuple(word_mask.shape)}")
        if l > self.max_words:
            raise ValueError(f"TextPrefix: {l} word slots given, the model has max_words={self.max_words}")
        word_valid = word_mask.bool()
        words = words.masked_fill(~word_valid[..., None], 0.0).to(sentence.dtype)
        if self.word_norm == "unit":  # a padded word (all 0) stays 0
            words = F.normalize(words, dim=-1)
        word_content = self.project(words)
        if drop_condition is not None:
            drop_words = drop_condition.bool()
            if keep_local is not None:
                drop_words = drop_words & ~keep_local.bool()
            word_valid = word_valid & ~drop_words[:, None]
        word_tokens = (word_content + self.word_type + self.word_position[:l]).masked_fill(
            ~word_valid[..., None], 0.0)
        if self.word_attention == "cross":  # read by the blocks' cross-attention
            return Condition(tokens=tokens, mask=valid, content=content, labels=prefix_labels(a),
                             words=word_tokens, word_mask=word_valid)
        return Condition(tokens=torch.cat([tokens, word_tokens], dim=1),
                         mask=torch.cat([valid, word_valid], dim=1), content=content,
                         labels=prefix_labels(a, l))


@dataclass
class EncodedPrefix:
    """A prefix run through the trunk on its own (`Trunk.encode_prefix`): per block, the
    keys and values the motion tokens attend to. Depends on the text alone, so one encoding
    serves every decoding step of a generation."""

    blocks: list[PrefixKeys]
    labels: list[str] | None = None  # the kind of each prefix slot (`prefix_labels`)
    # The text slots come first; memory slots (labelled "memory s") may follow.
    text_slots: int | None = None

    def conditional_rows(self) -> torch.Tensor:
        """(b,) bool: the rows whose text takes part (not a dropped condition)."""
        mask = self.blocks[0].mask
        return mask[:, : self.text_slots if self.text_slots is not None else mask.shape[1]].any(1)
