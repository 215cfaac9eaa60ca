"""Temporal grounding (paper §4.4, Fig. 5): where each segment of a text happens in a
motion, in SegMo's learned segment space (`segmo.pipeline.space`).

Candidate token spans of the motion are embedded as motion spans and compared by cosine
with each text segment; the chosen span of each segment, ×4, is its frame span. Three
searches (`SEARCHES`):

- "ordered" (the default): the caption's segments happen in caption order, one after the
  other. The motion's valid tokens are cut into as many contiguous spans as there are
  segments, each of at least `min_tokens` tokens, maximising the summed similarity of
  segment k with span k (`ordered_spans`, a dynamic programme over the boundaries).
- "spans": each segment alone, its best span among every span [s, e) of at least
  `min_tokens` tokens (`all_spans`); spans of different segments may overlap.
- "window": the paper's sliding windows of a fixed size (`window`, 5 tokens in Fig. 5;
  a list gives multi-scale windows), stepping by `stride`; each segment's best window.

Two methods score the candidates (`METHODS`): "similarity" (the default, the paper's)
compares segment and span embeddings; "attention" reads where the mask transformer's
motion tokens look when it sees the whole motion (`segmo.pipeline.attention`): each
token's share of the last block's segment attention (head mean) that goes to segment k.
A candidate scores its mean share; "ordered" cuts the motion so that the summed share
of each token's segment is highest, "spans" takes each segment's longest-heaviest run
where it holds the majority (the span maximising the sum of share − 0.5), "window" the
window of the highest mean share.

The windows, the DP and the picture of the map live here too; how well grounding finds
the truth (temporal IoU, `grounding_accuracy`) is `segmo.evaluation.grounding`.

    out = model.ground("a person walks forward, then waves", features)   # (t, 263) raw
    print(out)                       # frame span per text segment
    plot_similarity_map(out)         # paper Fig. 5
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from segmo.errors import SegmoError
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.pipeline.attention import motion_attention, segment_profile
from segmo.pipeline.outputs import GroundingOutput
from segmo.pipeline.space import SegmentEmbeddings, SegmentModel

SEARCHES: tuple[str, ...] = ("ordered", "spans", "window")
METHODS: tuple[str, ...] = ("similarity", "attention")
PAPER_WINDOW = 5  # tokens, paper Fig. 5
MIN_TOKENS = 2  # shortest span of "spans"/"ordered": one token has no motion to speak of


def ground(model: SegmentModel, text: str, motion: Any, search: str | None = None,
           window: int | Sequence[int] | None = None, stride: int | None = None,
           min_tokens: int | None = None, segments: list[str] | None = None,
           method: str = "similarity") -> GroundingOutput:
    """Where each text segment of `text` happens in `motion` (raw features (t, d)).

    search: "ordered", "spans" or "window" (module docstring); None = "window" when a
    `window` is given (size(s) in tokens), else "ordered". stride: the step of "window"'s
    windows in tokens (default 1). min_tokens: the shortest span of "ordered" and "spans"
    (default `MIN_TOKENS`). An option the search does not use is refused, not ignored.
    method: "similarity" or "attention".
    """
    search = check_search(search, window, stride, min_tokens)
    stride = 1 if stride is None else stride
    min_tokens = MIN_TOKENS if min_tokens is None else min_tokens
    if method not in METHODS:
        raise SegmoError(f"ground: method={method!r}; choose from {', '.join(METHODS)}")
    if method == "attention":
        return attention_locate(model, text, motion, search, window, stride, min_tokens, segments)
    space = model.embed_segments([text], [motion],
                                 segments=None if segments is None else [segments])
    return locate(space, text, len(motion), search, window, stride, min_tokens)


def check_search(search: str | None, window: int | Sequence[int] | None, stride: int | None,
                 min_tokens: int | None) -> str:
    """The search `ground` runs, or SegmoError naming the bad argument (None: not given)."""
    if search is None:
        search = "ordered" if window is None else "window"
    if search not in SEARCHES:
        raise SegmoError(f"ground: search={search!r}; choose from {', '.join(SEARCHES)}")
    if window is not None and search != "window":
        raise SegmoError(f"ground: window={window!r} is for search='window', not {search!r}")
    if stride is not None and search != "window":  # it would be ignored without a word
        raise SegmoError(f"ground: stride={stride!r} is for search='window', not {search!r}")
    if min_tokens is not None and search == "window":
        raise SegmoError(f"ground: min_tokens={min_tokens!r} is for search 'ordered' or "
                         f"'spans', not 'window'")
    if isinstance(window, bool) or (isinstance(window, (list, tuple))
                                    and any(isinstance(w, bool) for w in window)):
        raise SegmoError(f"ground: window={window!r} must be a size >= 1 (tokens), not a bool")
    if window is not None and not isinstance(window, (int, np.integer, list, tuple)):
        raise SegmoError(f"ground: window={window!r} must be a size >= 1 (tokens) or a list of them")
    sizes = [] if window is None else [window] if isinstance(window, (int, np.integer)) else list(window)
    if search == "window" and window is not None and (
            not sizes or not all(isinstance(w, (int, np.integer)) and w >= 1 for w in sizes)):
        raise SegmoError(f"ground: window={window!r} must be a size >= 1 (tokens) or a list of them")
    if stride is not None and (not isinstance(stride, (int, np.integer)) or stride < 1):
        raise SegmoError(f"ground: stride={stride!r} must be a whole number >= 1 (tokens)")
    if min_tokens is not None and (not isinstance(min_tokens, (int, np.integer))
                                   or min_tokens < 1):
        raise SegmoError(f"ground: min_tokens={min_tokens!r} must be a whole number >= 1")
    return search


def locate(space: SegmentEmbeddings, text: str, num_frames: int, search: str,
           window: int | Sequence[int] | None = None, stride: int = 1,
           min_tokens: int = MIN_TOKENS) -> GroundingOutput:
    """`ground` on an embedded pair (the first of `space`): the candidate spans of `search`,
    their similarity with each segment, and the chosen span of each. num_frames: frames of
    the motion given (its pass used them cut to a multiple of 4)."""
    n = int(space.num_tokens[0])
    a = len(space.segments[0])
    spans = candidate_spans(n, search, window, stride, min_tokens)
    similarity = space.similarity(torch.from_numpy(spans))[0, :a].float().cpu()  # (a, k)
    if search == "ordered":
        if a * min_tokens > n:
            raise SegmoError(f"ground: {a} segments in order need {a * min_tokens} tokens of "
                             f"at least min_tokens={min_tokens}; the motion has {n}")
        chosen = ordered_spans(similarity, spans, n)
    else:
        chosen = best_span(similarity, spans)
    return _output(text, space.segments[0], spans, similarity, chosen, num_frames, search, "similarity")


def _output(text: str, segments: list[str], spans: np.ndarray, scores: torch.Tensor,
            chosen: np.ndarray, num_frames: int, search: str, method: str) -> GroundingOutput:
    """The `GroundingOutput` of the chosen spans (a, 2) among the candidates `spans` with
    their `scores` (a, k)."""
    index = {tuple(s): i for i, s in enumerate(spans.tolist())}
    best = [float(scores[k, index[tuple(s)]]) for k, s in enumerate(chosen.tolist())]
    frames = chosen * FRAMES_PER_TOKEN
    return GroundingOutput(
        text=text, segments=segments, windows=torch.from_numpy(spans), similarity=scores,
        best_spans_frames=[(int(s), int(min(e, num_frames))) for s, e in frames],
        best_scores=best, num_frames=num_frames, search=search, method=method)


def candidate_spans(n: int, search: str, window: int | Sequence[int] | None, stride: int,
                    min_tokens: int) -> np.ndarray:
    """The candidate token spans (k, 2) of `search` over n tokens; SegmoError when "spans"
    asks for spans longer than the motion ("ordered" checks its segments' total)."""
    if search == "window":
        return sliding_windows(n, PAPER_WINDOW if window is None else window, stride)
    if search == "spans" and min_tokens > n:  # it was cut to the whole motion without a word
        raise SegmoError(f"ground: spans of at least min_tokens={min_tokens} tokens; the motion "
                         f"has {n}")
    return all_spans(n, min(min_tokens, n))


def attention_locate(model: Any, text: str, motion: Any, search: str,
                     window: int | Sequence[int] | None = None, stride: int = 1,
                     min_tokens: int = MIN_TOKENS, segments: list[str] | None = None) -> GroundingOutput:
    """`ground` with method "attention" (module docstring)."""
    if segments is not None and (isinstance(segments, str) or not isinstance(segments, (list, tuple))):
        # a string would be read letter by letter, as the similarity method refuses
        raise SegmoError(f"ground: segments must be a list of texts, got {segments!r:.80}")
    segments = model.segment_texts([text])[0] if segments is None else list(segments)
    return locate_by_attention(text, segments, attention_shares(model, text, motion, segments),
                               len(motion), search, window, stride, min_tokens)


def attention_shares(model: Any, text: str, motion: Any, segments: list[str]) -> np.ndarray:
    """(a, n): the share of each motion token's attention (last block, over the text
    segments) that goes to each segment; one forward pass, which every search can reuse."""
    maps = motion_attention(model, [text], [segments], [motion])
    last = max(maps, key=lambda m: m.block)
    a, n = len(segments), len(motion) // FRAMES_PER_TOKEN
    profile = segment_profile(last, 0)[:a, :n].astype(np.float64)
    return profile / np.maximum(profile.sum(0, keepdims=True), 1e-30)


def locate_by_attention(text: str, segments: list[str], share: np.ndarray, num_frames: int,
                        search: str, window: int | Sequence[int] | None = None, stride: int = 1,
                        min_tokens: int = MIN_TOKENS) -> GroundingOutput:
    """The spans that `search` chooses from the attention shares (a, n) of `attention_shares`."""
    a, n = share.shape
    spans = candidate_spans(n, search, window, stride, min_tokens)
    cumulative = np.concatenate([np.zeros((a, 1)), share.cumsum(1)], axis=1)
    sums = cumulative[:, spans[:, 1]] - cumulative[:, spans[:, 0]]  # (a, k)
    lengths = (spans[:, 1] - spans[:, 0]).astype(np.float64)
    mean = sums / lengths
    if search == "ordered":
        if a * min_tokens > n:
            raise SegmoError(f"ground: {a} segments in order need {a * min_tokens} tokens of "
                             f"at least min_tokens={min_tokens}; the motion has {n}")
        chosen = ordered_spans(sums, spans, n)
    elif search == "spans":
        chosen = best_span(sums - 0.5 * lengths, spans)
    else:
        chosen = best_span(mean, spans)
    return _output(text, segments, spans, torch.from_numpy(mean).float(), chosen, num_frames,
                   search, "attention")


def sliding_windows(num_tokens: int, window: int | Sequence[int], stride: int | None = None) -> np.ndarray:
    """All spans (w, 2) of the given window size(s) stepping by `stride` (default window//2,
    at least 1) over [0, num_tokens); a window longer than the sequence becomes the whole
    sequence, and the last window of each size is aligned to the end so the tail is covered."""
    if num_tokens < 1:
        raise ValueError(f"sliding_windows: num_tokens={num_tokens} must be >= 1")
    sizes = [window] if isinstance(window, (int, np.integer)) else list(window)
    spans: list[tuple[int, int]] = []
    for w in sizes:
        if w < 1:
            raise ValueError(f"sliding_windows: window={w} must be >= 1")
        w = min(w, num_tokens)
        step = stride if stride is not None else max(1, w // 2)
        if step < 1:
            raise ValueError(f"sliding_windows: stride={stride} must be >= 1")
        starts = list(range(0, num_tokens - w + 1, step))
        if starts[-1] != num_tokens - w:
            starts.append(num_tokens - w)
        spans += [(s, s + w) for s in starts]
    return np.array(sorted(set(spans)), dtype=np.int64)


def all_spans(num_tokens: int, min_tokens: int = MIN_TOKENS) -> np.ndarray:
    """Every span [s, e) of at least `min_tokens` tokens in [0, num_tokens), sorted by
    start then end: (k, 2), k = (n − m + 1)(n − m + 2)/2 (1,176 for n = 49, m = 2)."""
    if not 1 <= min_tokens <= num_tokens:
        raise ValueError(f"all_spans: min_tokens={min_tokens} must be in 1..num_tokens={num_tokens}")
    return np.array([(s, e) for s in range(num_tokens)
                     for e in range(s + min_tokens, num_tokens + 1)], dtype=np.int64).reshape(-1, 2)


def best_span(similarity: Any, windows: Any) -> np.ndarray:
    """The window with the highest score: similarity (..., w), windows (w, 2) → (..., 2).
    Ties go to the first window."""
    s = similarity.detach().cpu().numpy() if isinstance(similarity, torch.Tensor) else np.asarray(similarity)
    win = np.asarray(windows)
    if s.shape[-1] != len(win):
        raise ValueError(f"best_span: {s.shape[-1]} scores for {len(win)} windows")
    return win[np.argmax(s, axis=-1)]


def ordered_spans(similarity: Any, spans: Any, num_tokens: int) -> np.ndarray:
    """Cut [0, num_tokens) into a contiguous spans in order, span k going to row k, with the
    highest summed score: similarity (a, k) of each row with the candidate `spans` (k, 2);
    a cut that needs a span not among the candidates is not allowed. → (a, 2).

    Dynamic programme over boundaries, O(a·n²): best[j][e] = the best sum of rows 0..j−1
    cutting [0, e); best[j+1][e] = max over s of best[j][s] + score[j][s, e]. Ties go to the
    earliest boundary.
    """
    s = similarity.detach().cpu().numpy() if isinstance(similarity, torch.Tensor) else np.asarray(similarity)
    cand = np.asarray(spans)
    a, n = s.shape[0], num_tokens
    if s.shape != (a, len(cand)):
        raise ValueError(f"ordered_spans: {s.shape[-1]} scores for {len(cand)} spans")
    score = np.full((a, n + 1, n + 1), -np.inf)  # score[j, start, end]
    score[:, cand[:, 0], cand[:, 1]] = s
    best = np.full((a + 1, n + 1), -np.inf)
    best[0, 0] = 0.0
    back = np.zeros((a + 1, n + 1), dtype=np.int64)
    for j in range(a):
        # total[start, end] = best[j][start] + score[j][start, end]
        total = best[j][:, None] + score[j]
        back[j + 1] = total.argmax(axis=0)
        best[j + 1] = total.max(axis=0)
    if not np.isfinite(best[a, n]):
        raise ValueError(f"ordered_spans: no cut of {n} tokens into {a} candidate spans")
    ends = [n]
    for j in range(a, 0, -1):
        ends.append(int(back[j, ends[-1]]))
    bounds = ends[::-1]
    return np.array([(bounds[j], bounds[j + 1]) for j in range(a)], dtype=np.int64)


def token_map(output: GroundingOutput) -> torch.Tensor:
    """(a, n) the best similarity of each segment over the candidate spans that contain each
    token: the map of "spans"/"ordered", whose candidates have every length."""
    n = int(output.windows[:, 1].max())
    index = torch.arange(n)
    inside = (index >= output.windows[:, :1]) & (index < output.windows[:, 1:])  # (k, n)
    masked = output.similarity[:, :, None].masked_fill(~inside[None], float("-inf"))
    return masked.amax(dim=1)


def plot_similarity_map(output: GroundingOutput, ax=None, title: str | None = None,
                        truth: Sequence[tuple[int, int]] | None = None, cmap: str = "viridis",
                        fps: float | None = None):
    """Paper Fig. 5, y = text segment, colour = similarity, x in seconds (`fps`: frames per
    second of the motion, default the output's; a token is 4 frames). "window": x = window start, the best window
    of each segment outlined in red, `truth` (one (start, end) frame span per segment)
    underlined in white over the windows lying inside the true span. "spans"/"ordered":
    x = token, colour = the best span containing that token (`token_map`), the chosen span
    outlined in red over its tokens, `truth` underlined over its tokens. Returns the
    matplotlib Axes."""
    # matplotlib on use: grounding and retrieval themselves do not plot.
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    if truth is not None and len(truth) != len(output.segments):
        raise SegmoError(f"plot_similarity_map: {len(truth)} true spans for "
                         f"{len(output.segments)} segments")
    by_token = output.search != "window"
    sim = (token_map(output) if by_token else output.similarity).numpy()
    if ax is None:
        _, ax = plt.subplots(figsize=(max(4.0, 0.12 * sim.shape[1] + 2),
                                      0.5 * len(output.segments) + 1.5))
    image = ax.imshow(sim, aspect="auto", cmap=cmap, interpolation="nearest")
    label = "cosine similarity" if output.method == "similarity" else "share of the segment attention"
    ax.figure.colorbar(image, ax=ax, label=label)
    for row, (start, end) in enumerate(output.best_spans_frames):
        if by_token:
            col, width = start // FRAMES_PER_TOKEN, -(-end // FRAMES_PER_TOKEN) - start // FRAMES_PER_TOKEN
        else:
            col, width = int(sim[row].argmax()), 1
        ax.add_patch(Rectangle((col - 0.5, row - 0.5), width, 1, fill=False, edgecolor="red",
                               linewidth=2))
    for row, (start, end) in enumerate(truth or []):
        if by_token:  # tokens that overlap the true frames
            first, last = start // FRAMES_PER_TOKEN, -(-end // FRAMES_PER_TOKEN) - 1
        else:  # windows inside the true frames
            frames = output.windows * FRAMES_PER_TOKEN
            inside = ((frames[:, 0] >= start) & (frames[:, 1] <= end)).nonzero()[:, 0]
            first, last = (int(inside.min()), int(inside.max())) if len(inside) else (1, 0)
        if first <= last:
            ax.hlines(row + 0.35, first - 0.5, last + 0.5, colors="white", linewidth=3)
    ax.set_yticks(range(len(output.segments)))
    # Captions are plain text: "$x^$" is no formula (matplotlib's mathtext fails on it).
    ax.set_yticklabels([s if len(s) <= 40 else s[:37] + "..." for s in output.segments],
                       parse_math=False)
    seconds = FRAMES_PER_TOKEN / (fps or output.fps)  # per token
    if by_token:
        labels = [f"{p * seconds:.1f}" for p in range(sim.shape[1])]
        xlabel = f"time (s) of the token; {output.search} search"
    else:
        sizes = (output.windows[:, 1] - output.windows[:, 0]).unique()
        starts = output.windows[:, 0].tolist()
        labels = ([f"{s * seconds:.1f}" for s in starts] if len(sizes) == 1
                  else [f"{s * seconds:.1f}+{(e - s) * seconds:.1f}" for s, e in output.windows.tolist()])
        xlabel = "window start (s)" if len(sizes) == 1 else "window start + length (s)"
    if truth:
        xlabel += "; white: true span"
    step = max(1, len(labels) // 12)
    ax.set_xticks(range(0, len(labels), step))
    ax.set_xticklabels(labels[::step])
    ax.set_xlabel(xlabel)
    ax.set_title(title if title is not None else output.text, fontsize=9, parse_math=False)
    return ax
