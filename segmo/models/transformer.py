"""The transformer trunk shared by the mask and residual transformers (spec §4, §6).

Bottom-up: the shared config, attention → block → trunk, plus the text-conditioning prefix. The trunk runs
over `[prefix tokens, motion tokens]`; motion tokens get sinusoidal positions, the prefix
slots get learned type embeddings and the segments a learned execution-order embedding.

The prefix is encoded on its own: prefix tokens attend to prefix tokens only, motion
tokens attend to both. So the prefix's keys and values depend on the text alone and are
computed once per generation, then reused at every decoding step (`Trunk.encode_prefix`).

Masks follow the package convention (`(b, n) bool`, True = valid) and are turned into an
attention mask only inside `attention`. Invalid keys (padded motion tokens, empty
segment slots, the whole text prefix of a sample whose condition is dropped) are excluded
from attention, so their content cannot influence any valid position.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from segmo.text.rules import MAX_SEGMENTS


@dataclass
class TransformerConfig:
    """What the mask and the residual transformer share: the token vocabulary, the text
    prefix (`text_dim`, `max_segments` slots A) and the trunk. Their configs extend it, so a
    config.json stays one flat object."""

    codebook_size: int = 512
    text_dim: int = 512
    # A: the most text segments a caption has, what the text segmenters produce at most.
    max_segments: int = MAX_SEGMENTS
    max_tokens: int = 49
    dim: int = 384
    depth: int = 8
    heads: int = 6
    ff_dim: int = 1024
    dropout: float = 0.2
    # MoMask uses PyTorch's default post-norm encoder layer; pre-norm trains more stably.
    norm_first: bool = False
    # Word-level conditioning (MLA-Gen): "words" adds the caption's per-word features of the
    # text encoder (start and end tokens included) as further prefix keys (`TextPrefix`);
    # "none" is the model without them. max_words: the most word keys (CLIP's 77 tokens).
    text_tokens: str = "none"
    max_words: int = 77
    # How motion tokens read the word keys: "prefix", as further keys of every block's
    # self-attention (one softmax with the sentence, segments and motion); "cross", a gated
    # cross-attention sub-layer over the words alone in every block (Flamingo's tanh gate,
    # 0 at initialisation). Measured against each other in the README; "prefix" by default.
    word_attention: str = "prefix"
    # How the word features are scaled before the shared projection: "none", as the text
    # encoder gives them; "unit", each word vector to unit length. MiniLM's per-token states
    # have a norm of about 6 against its unit-length sentence vectors, so without scaling
    # the word keys outweigh the sentence and segments (measured in the README).
    word_norm: str = "none"
    # MLA-Gen's memory slots (eq. 4): learned vectors every block's motion queries attend to,
    # independent of the text and present in conditional and unconditional rows alike
    # (`Trunk.encode_prefix`). 0 = the model without them.
    memory_slots: int = 0


TEXT_TOKENS: tuple[str, ...] = ("none", "words")
WORD_ATTENTION: tuple[str, ...] = ("prefix", "cross")
WORD_NORM: tuple[str, ...] = ("none", "unit")


def sinusoidal_positions(length: int, dim: int) -> torch.Tensor:
    """The fixed sin/cos table of "Attention is all you need": (length, dim) float32."""
    if dim % 2:
        raise ValueError(f"sinusoidal_positions: dim must be even, got {dim}")
    position = torch.arange(length, dtype=torch.float32)[:, None]
    frequency = torch.exp(torch.arange(0, dim, 2, dtype=torch.float32) * (-math.log(10000.0) / dim))
    table = torch.zeros(length, dim)
    table[:, 0::2] = torch.sin(position * frequency)
    table[:, 1::2] = torch.cos(position * frequency)
    return table


class Linear(nn.Linear):
    """`nn.Linear`, optionally followed by the exact (erf) GELU: the feed-forward's first
    layer and the token head fuse it, so that a CPU kernel can compute both in one call
    (`segmo.models.cpu_inference` swaps such a kernel in for CPU inference)."""

    def __init__(self, in_features: int, out_features: int, activation: str = "none") -> None:
        super().__init__(in_features, out_features)
        if activation not in ("none", "gelu"):
            raise ValueError(f"Linear: activation must be 'none' or 'gelu', got {activation!r}")
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = F.linear(x, self.weight, self.bias)
        return F.gelu(y) if self.activation == "gelu" else y


def attention(q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, key_valid: torch.Tensor,
              dropout: float = 0.0) -> torch.Tensor:
    """Scaled dot-product attention with a key mask.

    q (b, heads, l, head_dim), k and v (b, heads, m, head_dim), key_valid (b, m) bool keys
    that may be attended to (every row needs one) → (b, heads, l, head_dim).
    """
    mask = key_valid[:, None, None, :]  # True = take part; broadcast over heads and queries
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask, dropout_p=dropout)


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


class SelfAttention(nn.Module):
    """Multi-head self-attention with a key mask, optionally also over a prefix's keys."""

    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"SelfAttention: dim={dim} is not divisible by heads={heads}")
        self.heads = heads
        self.dropout = dropout
        self.qkv = Linear(dim, 3 * dim)
        self.out = Linear(dim, dim)
        # The attention function; `segmo.models.cpu_inference` swaps in a faster one.
        self.attend = attention

    def forward(self, x: torch.Tensor, valid: torch.Tensor, prefix: PrefixKeys | None = None,
                queries: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """x (b, l, dim), valid (b, l) bool keys of x that may be attended to; `prefix`:
        further keys in front of x's own; `queries` (b, m) long: the positions of x whose
        outputs are wanted (None = all) → (output (b, m, dim), x's (keys, values), each
        (b, heads, l, head_dim))."""
        b, length, dim = x.shape
        q, k, v = self.qkv(x).view(b, length, 3, self.heads, dim // self.heads).unbind(2)
        if queries is not None:
            q = _gather_positions(q, queries)
        q, k, v = (t.transpose(1, 2) for t in (q, k, v))  # (b, heads, l or m, head_dim)
        keys, values, key_valid = k, v, valid
        if prefix is not None:
            keys = torch.cat([prefix.keys.to(k.dtype), k], dim=2)
            values = torch.cat([prefix.values.to(v.dtype), v], dim=2)
            key_valid = torch.cat([prefix.mask, valid], dim=1)
        y = self.attend(q, keys, values, key_valid, self.dropout if self.training else 0.0)
        return self.out(y.transpose(1, 2).reshape(b, q.shape[2], dim)), (k, v)


class GatedCrossAttention(nn.Module):
    """Motion queries attending to the word tokens alone, added through a tanh gate that
    starts at 0 (Flamingo's gated cross-attention), so that training starts from the model
    without words. Rows without a valid word (a dropped condition) get nothing."""

    def __init__(self, dim: int, heads: int, dropout: float) -> None:
        super().__init__()
        self.heads = heads
        self.dropout = dropout
        self.query = Linear(dim, dim)
        self.key_value = Linear(dim, 2 * dim)
        self.out = Linear(dim, dim)
        self.gate = nn.Parameter(torch.zeros(1))

    def keys(self, words: torch.Tensor, word_mask: torch.Tensor
             ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """words (b, l, dim) word tokens, word_mask (b, l) bool → their keys and values
        (b, heads, l, head_dim) and mask: computed once per generation."""
        b, length, dim = words.shape
        k, v = self.key_value(words).view(b, length, 2, self.heads, dim // self.heads).unbind(2)
        return k.transpose(1, 2), v.transpose(1, 2), word_mask.bool()

    def forward(self, x: torch.Tensor, words: tuple[torch.Tensor, torch.Tensor, torch.Tensor]
                ) -> torch.Tensor:
        """x (b, m, dim) motion states, words from `keys` → the gated output (b, m, dim)."""
        b, m, dim = x.shape
        k, v, mask = words
        q = self.query(x).view(b, m, self.heads, dim // self.heads).transpose(1, 2)
        any_word = mask.any(dim=1)
        # A row without words attends to all its (zeroed) slots to stay finite, then is cut.
        y = attention(q, k.to(q.dtype), v.to(q.dtype), mask | ~any_word[:, None],
                      self.dropout if self.training else 0.0)
        y = self.out(y.transpose(1, 2).reshape(b, m, dim))
        return torch.tanh(self.gate).to(y.dtype) * y * any_word[:, None, None].to(y.dtype)


def _gather_positions(x: torch.Tensor, positions: torch.Tensor) -> torch.Tensor:
    """x (b, l, ...) at positions (b, m) long → (b, m, ...)."""
    index = positions.reshape(*positions.shape, *([1] * (x.dim() - 2)))
    return x.gather(1, index.expand(*positions.shape, *x.shape[2:]))


class Block(nn.Module):
    """Encoder block: attention + GELU feed-forward, pre-norm or post-norm."""

    def __init__(self, dim: int, heads: int, ff_dim: int, dropout: float, norm_first: bool,
                 cross_words: bool = False):
        super().__init__()
        self.norm_first = norm_first
        self.attention = SelfAttention(dim, heads, dropout)
        # word_attention "cross": a gated cross-attention sub-layer over the words after the
        # self-attention; absent otherwise, so that such a model is unchanged.
        if cross_words:
            self.cross = GatedCrossAttention(dim, heads, dropout)
            self.cross_norm = nn.LayerNorm(dim)
        self.norm1 = nn.LayerNorm(dim)
        self.norm2 = nn.LayerNorm(dim)
        self.ff = nn.Sequential(Linear(dim, ff_dim, activation="gelu"), nn.Dropout(dropout),
                                Linear(ff_dim, dim))
        self.drop = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, valid: torch.Tensor, prefix: PrefixKeys | None = None,
                queries: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
        """x (b, l, dim), valid (b, l) bool, prefix and queries (b, m) as in
        `SelfAttention` → (output (b, m, dim) at the queried positions (m = l without
        queries), this block's (keys, values) of all of x)."""
        residual = x if queries is None else _gather_positions(x, queries)
        words = prefix.words if prefix is not None and hasattr(self, "cross") else None
        if self.norm_first:
            y, kv = self.attention(self.norm1(x), valid, prefix, queries)
            x = residual + self.drop(y)
            if words is not None:
                x = x + self.drop(self.cross(self.cross_norm(x), words))
            return x + self.drop(self.ff(self.norm2(x))), kv
        y, kv = self.attention(x, valid, prefix, queries)
        x = self.norm1(residual + self.drop(y))
        if words is not None:
            x = self.cross_norm(x + self.drop(self.cross(x, words)))
        return self.norm2(x + self.drop(self.ff(x))), kv


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
    ) -> Condition:
        """sentence (b, text_dim), segments (b, a, text_dim) in execution order,
        segment_mask (b, a) bool, drop_condition (b,) bool or None, unordered (b,) bool or
        None: rows whose segments enter as a set, without order embeddings; words
        (b, l, text_dim) and word_mask (b, l) bool: the caption's word features (a model
        with word keys needs them, one without ignores them); keep_local (b,) bool: rows of
        `drop_condition` that keep their local condition (segments, words) and drop the
        sentence only (MLA-Gen's unconditional branch with local features) → Condition with
        p = 1 + a (+ l)."""
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


class Trunk(nn.Module):
    """Stack of encoder blocks over `[prefix, motion tokens]`.

    Prefix tokens attend to the prefix only; motion tokens attend to the prefix and to each
    other. Positions: sinusoidal on motion tokens (the prefix has type and order embeddings).
    """

    def __init__(self, dim: int, depth: int, heads: int, ff_dim: int, dropout: float,
                 norm_first: bool, max_tokens: int, memory_slots: int = 0,
                 cross_words: bool = False) -> None:
        super().__init__()
        if memory_slots < 0:
            raise ValueError(f"Trunk: memory_slots must be >= 0, got {memory_slots}")
        self.register_buffer("positions", sinusoidal_positions(max_tokens, dim), persistent=False)
        # Absent without slots, so that such a model is exactly the one without them.
        if memory_slots:
            self.memory = nn.Parameter(torch.randn(memory_slots, dim) * 0.02)
        self.drop = nn.Dropout(dropout)
        self.blocks = nn.ModuleList(
            Block(dim, heads, ff_dim, dropout, norm_first, cross_words) for _ in range(depth)
        )
        # Post-norm blocks already end in a LayerNorm; pre-norm needs a final one.
        self.norm = nn.LayerNorm(dim) if norm_first else nn.Identity()

    def encode_prefix(self, prefix: torch.Tensor, prefix_mask: torch.Tensor,
                      labels: list[str] | None = None, words: torch.Tensor | None = None,
                      word_mask: torch.Tensor | None = None) -> EncodedPrefix:
        """prefix (b, p, dim) tokens, prefix_mask (b, p) bool valid slots, labels the kind
        of each slot (kept for the attention recorder); words (b, l, dim) and word_mask
        (b, l): the word tokens of a model with cross-attention over them (`Condition`)
        → EncodedPrefix.

        A row without any valid slot (condition dropped) lets its slots attend to each
        other so that its keys and values stay finite; no motion token ever attends to them.
        """
        prefix_mask = prefix_mask.bool()
        among = prefix_mask | ~prefix_mask.any(dim=1, keepdim=True)
        x = self.drop(prefix)
        blocks = []
        cross = hasattr(self.blocks[0], "cross")
        if cross and (words is None or word_mask is None):
            raise ValueError("Trunk: this model reads words by cross-attention "
                             "(word_attention='cross'): give words and word_mask")
        for block in self.blocks:
            x, (keys, values) = block(x, among)
            word_keys = block.cross.keys(self.drop(words), word_mask) if cross else None
            blocks.append(PrefixKeys(keys, values, prefix_mask, word_keys))
        if not hasattr(self, "memory"):
            return EncodedPrefix(blocks=blocks, labels=labels)
        # Memory slots: encoded on their own (so they do not depend on the text), then
        # appended to every block's prefix keys, valid in every row.
        b, p = prefix_mask.shape
        slots = self.memory.shape[0]
        valid = prefix_mask.new_ones(1, slots)
        for i, (keys, values) in enumerate(self.memory_keys(prefix.dtype)):
            text = blocks[i]
            blocks[i] = PrefixKeys(
                torch.cat([text.keys, keys.expand(b, -1, -1, -1).to(text.keys.dtype)], dim=2),
                torch.cat([text.values, values.expand(b, -1, -1, -1).to(text.values.dtype)], dim=2),
                torch.cat([prefix_mask, valid.expand(b, slots)], dim=1), text.words)
        labels = [*(labels or prefix_labels(p - 1)), *(f"memory {k}" for k in range(slots))]
        return EncodedPrefix(blocks=blocks, labels=labels, text_slots=p)

    def memory_keys(self, dtype: torch.dtype) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Each block's keys and values of the memory slots, (1, heads, slots, head_dim)
        each, the slots run through the blocks on their own.

        They depend on the parameters alone, so inference (eval mode, no gradients) encodes
        them once and keeps them until a parameter, the precision or an attention or linear
        kernel changes: one generation encodes its prefix twice (mask and residual
        transformer), and for one motion this pass of 16 slots through every block cost
        ~4 % of the generation (`tools/bench_generate.py --versus memory16`)."""
        inference = not self.training and not torch.is_grad_enabled()
        key = None
        if inference:
            device = self.memory.device.type
            autocast = (torch.is_autocast_enabled(device)
                        and torch.get_autocast_dtype(device))
            key = (dtype, autocast,
                   tuple((q.data_ptr(), q._version) for q in self.parameters()),
                   tuple(block.attention.attend for block in self.blocks),
                   tuple(type(module) for module in self.modules()))
            cached = self.__dict__.get("_memory_cache")
            if cached is not None and cached[0] == key:
                return cached[1]
        m = self.drop(self.memory.to(dtype)[None])
        valid = torch.ones(1, m.shape[1], dtype=torch.bool, device=m.device)
        encoded = []
        for block in self.blocks:
            m, kv = block(m, valid)
            encoded.append(kv)
        # A plain attribute, not a buffer: never saved, moved or copied with the model.
        self.__dict__["_memory_cache"] = (key, encoded) if inference else None
        return encoded

    def encoded(self, condition: Condition) -> EncodedPrefix:
        """The condition's encoded prefix: the cached one from `condition()`, else a fresh one."""
        if condition.encoded is not None:
            return condition.encoded
        return self.encode_prefix(condition.tokens, condition.mask, condition.labels,
                                  condition.words, condition.word_mask)

    def forward_motion(self, tokens: torch.Tensor, token_mask: torch.Tensor,
                       prefix: EncodedPrefix, positions: torch.Tensor | None = None
                       ) -> torch.Tensor:
        """tokens (b, n, dim) embedded motion tokens, token_mask (b, n) bool, prefix from
        `encode_prefix`, positions (b, m) long: the motion positions whose hidden states
        are wanted (None = all) → hidden states (b, m, dim), m = n without positions.

        Every block but the last needs all positions (the next block's keys and values
        come from them); the last one computes its keys and values everywhere and the rest
        (attention output, feed-forward) only at `positions`. Decoding asks for the
        positions it samples: 38 % fewer than n on average over 10 steps of MoMask's
        cosine schedule."""
        n = tokens.shape[1]
        if n > self.positions.shape[0]:
            raise ValueError(f"Trunk: {n} motion tokens, the model has max_tokens="
                             f"{self.positions.shape[0]}")
        token_mask = token_mask.bool()
        if not bool(token_mask.any(dim=1).all()):
            raise ValueError("Trunk: every sample needs at least one valid motion token")
        x = self.drop(tokens + self.positions[:n].to(tokens.dtype))
        if positions is not None and (positions.dim() != 2 or positions.shape[0] != x.shape[0]):
            raise ValueError(f"Trunk: positions must be (b, m) = ({x.shape[0]}, m), "
                             f"got {tuple(positions.shape)}")
        last = len(self.blocks) - 1
        for depth, (block, keys) in enumerate(zip(self.blocks, prefix.blocks, strict=True)):
            x, _ = block(x, token_mask, keys, positions if depth == last else None)
        return self.norm(x)


class TokenHead(nn.Module):
    """MoMask's output process: dense → GELU → LayerNorm; the final projection is the
    caller's (a Linear for the mask transformer, tied embeddings for the residual one)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.dense = Linear(dim, dim, activation="gelu")
        self.norm = nn.LayerNorm(dim)

    def forward(self, h: torch.Tensor) -> torch.Tensor:
        """h (..., dim) → (..., dim)."""
        return self.norm(self.dense(h))


def init_weights(module: nn.Module) -> None:
    # MoMask/BERT initialisation: small normal weights, zero biases, unit LayerNorms.
    if isinstance(module, (nn.Linear, nn.Embedding)):
        nn.init.normal_(module.weight, mean=0.0, std=0.02)
        if isinstance(module, nn.Linear) and module.bias is not None:
            nn.init.zeros_(module.bias)
    elif isinstance(module, nn.LayerNorm):
        nn.init.ones_(module.weight)
        nn.init.zeros_(module.bias)
