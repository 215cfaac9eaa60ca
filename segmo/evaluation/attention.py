"""Attention diagnostics over a recording (`segmo.models.attention_recorder`): how much of
the motion queries' attention reaches the text, whether it sinks into one key, and whether
each segment's key is attended where the segment happens.

Every figure averages over the recorded conditional rows, the heads and the valid motion
queries (padded motion positions are not queries of any sample); a map is one block of one
pass.

- ``sink_ratio``: MLA-Gen's SinkRatio (eq. 7) adapted to a short prefix. MLA-Gen sums the
  top-K cross-attention weights of each motion frame over ~20 text tokens; segmo's motion
  queries attend to a prefix of N = 2..6 valid keys (sentence and segments) beside the
  motion, where a uniform spread already puts K/N on the top K. Per query, with the prefix
  weights renormalised to sum to one (p), K' = min(K, N − 1) and s = the sum of the K'
  largest p:

      SinkRatio = (s − K'/N) / (1 − K'/N)

  0 when the prefix weights are uniform, 1 when they sit on K' keys alone; queries of a
  prefix of fewer than 2 valid keys are left out. K = 1 by default (the sink is one key).
- ``prefix_share``: the attention mass on the text prefix (the rest is on motion keys).
- ``sentence_share``: the sentence key's part of the prefix mass; ``kind_share`` the same
  for each kind of key (sentence, segments, start word, other words), to find the sink in
  a model with word keys.
- ``attention_grounding``: over motion tokens inside the ground-truth span of segment k,
  the share whose largest segment weight (head mean) is on segment k; captions of one
  segment are left out (their one segment always holds the largest weight).
"""

from __future__ import annotations

import textwrap
from collections import defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
import torch

from segmo.models.attention_recorder import AttentionMap
from segmo.pipeline.attention import key_profile, motion_attention, segment_profile
from segmo.text.vocabulary import tag_caption

__all__ = ["attention_grounding", "content_words", "key_profile", "motion_attention",
           "kind_share", "plot_segment_attention", "prefix_share", "segment_profile", "sentence_share",
           "sink_ratio", "sink_ratio_values"]

# Parts of speech that carry what a motion does (`segmo.text.vocabulary.tag_caption`);
# connectives ("then", "first") are tagged ADV but order the actions, so they are left out.
CONTENT_POS = {"VERB", "NOUN", "ADJ", "ADV", "NUM"}
CONNECTIVES = {"then", "first", "finally", "next", "later", "again", "also", "still"}


def _query_valid(m: AttentionMap) -> torch.Tensor:
    """(r, q) bool: the queries at valid motion positions."""
    p = m.prefix_length
    return m.key_valid[:, p:].gather(1, m.queries)


def _prefix(m: AttentionMap) -> torch.Tensor:
    """(r, heads, q, p) weights on the text keys (memory slots, where a model has them,
    are not text)."""
    return m.weights[..., :m.text_length]


def sink_ratio_values(m: AttentionMap, k: int = 1) -> torch.Tensor:
    """(r, heads, q) SinkRatio per query (NaN where it is undefined: see the module)."""
    if k < 1:
        raise ValueError(f"sink_ratio: k must be ≥ 1, got {k}")
    prefix = _prefix(m)
    valid = m.key_valid[:, :m.text_length]  # (r, p)
    n = valid.sum(1).to(prefix.dtype)[:, None, None]  # (r, 1, 1)
    mass = prefix.sum(-1, keepdim=True)
    p = torch.where(mass > 0, prefix / mass.clamp_min(1e-30), torch.zeros_like(prefix))
    top = torch.sort(p, dim=-1, descending=True).values.cumsum(-1)  # (r, h, q, p)
    kk = torch.clamp(n - 1, min=1, max=k).long()  # K' per row, (r, 1, 1)
    s = top.gather(-1, (kk[..., None] - 1).expand(*top.shape[:3], 1)).squeeze(-1)
    uniform = kk.to(prefix.dtype) / n  # (r, 1, 1), what a uniform spread puts on the top K'
    ratio = (s - uniform) / (1 - uniform).clamp_min(1e-12)
    defined = (n >= 2) & _query_valid(m)[:, None, :] & (mass.squeeze(-1) > 0)
    return torch.where(defined, ratio, torch.full_like(ratio, float("nan")))


def _mean(values: Iterable[torch.Tensor]) -> float:
    flat = torch.cat([v.flatten() for v in values]) if values else torch.zeros(0)
    flat = flat[~torch.isnan(flat)]
    return float(flat.mean()) if flat.numel() else float("nan")


def _grouped(maps: Sequence[AttentionMap], values) -> dict[str, dict[int, float]]:
    by_block, by_step = defaultdict(list), defaultdict(list)
    for m in maps:
        v = values(m)
        by_block[m.block].append(v)
        by_step[m.step].append(v)
    return {"by_block": {b: _mean(v) for b, v in sorted(by_block.items())},
            "by_step": {s: _mean(v) for s, v in sorted(by_step.items())},
            "mean": _mean([v for vs in by_block.values() for v in vs])}


def _masked(m: AttentionMap, values: torch.Tensor) -> torch.Tensor:
    """values (r, heads, q) with the invalid queries set to NaN."""
    keep = _query_valid(m)[:, None, :].expand_as(values)
    return torch.where(keep, values, torch.full_like(values, float("nan")))


def sink_ratio(maps: Sequence[AttentionMap], k: int = 1) -> dict[str, dict[int, float]]:
    """SinkRatio by block, by pass (decoding step) and overall."""
    return _grouped(maps, lambda m: sink_ratio_values(m, k))


def prefix_share(maps: Sequence[AttentionMap]) -> dict[str, dict[int, float]]:
    """The attention mass on the text prefix, by block, by pass and overall."""
    return _grouped(maps, lambda m: _masked(m, _prefix(m).sum(-1)))


def sentence_share(maps: Sequence[AttentionMap]) -> dict[str, dict[int, float]]:
    """The sentence key's part of the prefix mass, by block, by pass and overall."""
    return _grouped(maps, _kind_part("sentence"))


KEY_KINDS = ("sentence", "segments", "start word", "words")


def _kind(label: str) -> str:
    if label == "sentence":
        return "sentence"
    if label.startswith("segment "):
        return "segments"
    return "start word" if label == "word 0" else "words"


def _kind_part(kind: str):
    """map → (r, heads, q): the part of each query's prefix mass on the keys of `kind`."""
    def value(m: AttentionMap) -> torch.Tensor:
        prefix = _prefix(m)
        mass = prefix.sum(-1)
        chosen = [i for i, label in enumerate(m.key_labels[:m.text_length]) if _kind(label) == kind]
        part = prefix[..., chosen].sum(-1)
        return _masked(m, torch.where(mass > 0, part / mass.clamp_min(1e-30), torch.nan))
    return value


def kind_share(maps: Sequence[AttentionMap]) -> dict[str, dict[str, dict[int, float]]]:
    """The prefix mass by kind of key: the sentence, the segments together, the start word
    (the first word key: the start token, MLA-Gen's sink) and the other words together;
    each by block, by pass and overall, like `sentence_share` (whose figures the
    "sentence" entry repeats). Kinds a model has no key of are left out."""
    kinds = {kind for m in maps for kind in map(_kind, m.key_labels[:m.text_length])}
    return {kind: _grouped(maps, _kind_part(kind)) for kind in KEY_KINDS if kind in kinds}


def attention_grounding(maps: Sequence[AttentionMap],
                        spans: Sequence[Sequence[tuple[int, int]]],
                        counts: dict[int, list[int]] | None = None) -> dict:
    """The share of motion tokens inside the ground-truth span of segment k whose largest
    segment weight (head mean) is on segment k, by block and overall. spans[i]: the token
    spans [start, end) of the segments of the maps' row i, in segment order. Rows of fewer
    than 2 segments are left out, as in `segmo.evaluation.grounding.grounding_accuracy`: with
    one segment key every token's largest weight is on it, a hit whatever the attention.
    `counts` (block → [hits, tokens]) adds to the counts of earlier batches and is updated."""
    counts = {} if counts is None else counts
    for m in maps:
        for row, row_spans in enumerate(spans):
            if row >= len(m.rows) or len(row_spans) < 2:
                continue
            profile = segment_profile(m, row)[:len(row_spans)]
            valid = m.key_valid[row, 1:1 + len(row_spans)].numpy()
            profile[~valid] = -np.inf
            tally = counts.setdefault(m.block, [0, 0])
            for k, (start, end) in enumerate(row_spans):
                for t in range(start, min(end, profile.shape[1])):
                    column = profile[:, t]
                    if np.isnan(column).any():
                        continue
                    tally[0] += int(np.argmax(column) == k)
                    tally[1] += 1
    hits = sum(h for h, _ in counts.values())
    total = sum(t for _, t in counts.values())
    return {"by_block": {b: h / t if t else float("nan") for b, (h, t) in sorted(counts.items())},
            "mean": hits / total if total else float("nan"),
            "tokens": total // max(len(counts), 1)}


def content_words(pieces: Sequence[str]) -> list[tuple[int, str]]:
    """The content words among a text's word keys (`SegMo.word_texts`: word pieces with the
    start and end tokens): (index of the word's first piece, the whole word) for verbs,
    nouns, adjectives, adverbs and numbers; special tokens, punctuation, function words
    and connectives are left out; "##" pieces join the word they continue."""
    words: list[tuple[int, str]] = []
    for i, piece in enumerate(pieces):
        if piece.startswith("##") and words and words[-1][0] >= 0:
            words[-1] = (words[-1][0], words[-1][1] + piece[2:])
        else:
            words.append((i, piece) if piece.isalnum() else (-1, piece))
    out = []
    for i, word in words:
        tags = tag_caption(word) if i >= 0 else []
        if len(tags) == 1 and tags[0][1] in CONTENT_POS and word.lower() not in CONNECTIVES:
            out.append((i, word))
    return out


def plot_segment_attention(m: AttentionMap, row: int, segments: Sequence[str], path: str | Path,
                           spans: Sequence[tuple[int, int]] | None = None, fps: float = 20.0,
                           frames_per_token: int = 4, title: str = "",
                           words: Sequence[tuple[int, str]] | None = None) -> Path:
    """A PNG of each segment's attention (head mean) over the motion's tokens, the x axis in
    seconds, the ground-truth spans (token units) shaded in the segment's colour; with
    `words` ((word key index, text), e.g. `content_words`, for a model with word keys) a
    second panel shows each of those words' attention over the same tokens."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    profile = segment_profile(m, row)[:len(segments)]
    seconds = (np.arange(profile.shape[1]) + 0.5) * frames_per_token / fps
    valid = m.key_valid[row, m.prefix_length:].numpy()
    panels = 2 if words else 1
    fig, axes = plt.subplots(panels, 1, figsize=(8, 3 * panels), sharex=True, squeeze=False)
    ax = axes[0, 0]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]

    def shade(ax) -> None:
        for k in range(min(len(segments), len(spans or []))):
            start, end = spans[k]
            ax.axvspan(start * frames_per_token / fps, end * frames_per_token / fps,
                       color=colours[k % len(colours)], alpha=0.12)

    for k, text in enumerate(segments):
        # Legend labels are read as mathtext: a caption's "$" is escaped (plain text).
        label = textwrap.shorten(f"{k + 1}: {text}", 48, placeholder="…").replace("$", r"\$")
        ax.plot(seconds[valid], profile[k][valid], color=colours[k % len(colours)], label=label)
    shade(ax)
    ax.set_ylabel("segment attention")
    # A long caption wraps instead of running off the figure.
    title = title or f"{m.stage} step {m.step}, block {m.block}"
    ax.set_title("\n".join(textwrap.fill(line, 100) for line in title.splitlines()), fontsize=9,
                 parse_math=False)
    ax.legend(fontsize=7, loc="best")
    if words:
        word_profile = key_profile(m, row, "word ")
        if len(word_profile) == 0:
            raise ValueError("plot_segment_attention: words given, but the recording has no word "
                             "keys (a model without words, or words read by cross-attention)")
        ax = axes[1, 0]
        styles = ["-", "--", ":", "-."]
        for j, (index, text) in enumerate(words):
            ax.plot(seconds[valid], word_profile[index][valid], label=text.replace("$", r"\$"),
                    color=colours[j % len(colours)], linestyle=styles[(j // len(colours)) % 4])
        shade(ax)
        ax.set_ylabel("word attention")
        ax.legend(fontsize=7, loc="best", ncol=2)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

