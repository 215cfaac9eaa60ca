"""Temporal grounding (paper §4.4, Fig. 5): where each segment of a text happens in a
motion, in SegMo's learned segment space (`segmo.pipeline.space`).

Every sliding window of the motion's tokens is embedded as a motion span and compared by
cosine with each text segment; a segment's best window, ×4, is its frame span. The
windows and the picture of the map live here too; how well grounding finds the truth
(temporal IoU, `grounding_accuracy`) is `segmo.evaluation.grounding`.

    out = model.ground("a person walks forward, then waves", features)   # (t, 263) raw
    print(out)                       # best frame span per text segment
    plot_similarity_map(out)         # paper Fig. 5
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from segmo.errors import SegmoError
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.pipeline.outputs import GroundingOutput
from segmo.pipeline.space import SegmentModel


def ground(model: SegmentModel, text: str, motion: Any, window: int | Sequence[int] = 5,
           stride: int = 1, segments: list[str] | None = None) -> GroundingOutput:
    """Similarity of each text segment with every sliding window of the motion.

    motion: raw features (t, d); window: size(s) in tokens (a list gives multi-scale
    windows); stride in tokens. The best window of each segment, ×4, is its frame span.
    """
    space = model.embed_segments([text], [motion],
                                 segments=None if segments is None else [segments])
    t = len(motion)  # frames given; the pass used them cut to a multiple of 4
    windows = torch.from_numpy(sliding_windows(int(space.num_tokens[0]), window, stride))
    similarity = space.similarity(windows)[0].float().cpu()
    best = best_span(similarity, windows) * FRAMES_PER_TOKEN
    return GroundingOutput(
        text=text, segments=space.segments[0], windows=windows, similarity=similarity,
        best_spans_frames=[(int(s), int(min(e, t))) for s, e in best],
        best_scores=similarity.max(dim=-1).values.tolist(), num_frames=t)


def sliding_windows(num_tokens: int, window: int | Sequence[int], stride: int | None = None) -> np.ndarray:
    """All spans (w, 2) of the given window size(s) stepping by `stride` (default window//2,
    at least 1) over [0, num_tokens); a window longer than the sequence becomes the whole
    sequence, and the last window of each size is aligned to the end so the tail is covered."""
    if num_tokens < 1:
        raise ValueError(f"sliding_windows: num_tokens={num_tokens} must be >= 1")
    sizes = [window] if isinstance(window, int) else list(window)
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


def best_span(similarity: Any, windows: Any) -> np.ndarray:
    """The window with the highest score: similarity (..., w), windows (w, 2) → (..., 2).
    Ties go to the first window."""
    s = similarity.detach().cpu().numpy() if isinstance(similarity, torch.Tensor) else np.asarray(similarity)
    win = np.asarray(windows)
    if s.shape[-1] != len(win):
        raise ValueError(f"best_span: {s.shape[-1]} scores for {len(win)} windows")
    return win[np.argmax(s, axis=-1)]


def plot_similarity_map(output: GroundingOutput, ax=None, title: str | None = None,
                        truth: Sequence[tuple[int, int]] | None = None, cmap: str = "viridis"):
    """Paper Fig. 5: x = window start (tokens), y = text segment, colour = similarity; the
    best window of each segment is outlined in red. `truth` (one (start, end) frame span
    per segment) underlines in white the windows lying inside the true span. Returns the
    matplotlib Axes."""
    # matplotlib on use: grounding and retrieval themselves do not plot.
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    if ax is None:
        _, ax = plt.subplots(figsize=(max(4.0, 0.12 * output.similarity.shape[1] + 2),
                                      0.5 * len(output.segments) + 1.5))
    sim = output.similarity.numpy()
    starts = output.windows[:, 0].tolist()
    image = ax.imshow(sim, aspect="auto", cmap=cmap, interpolation="nearest")
    ax.figure.colorbar(image, ax=ax, label="cosine similarity")
    best = sim.argmax(axis=1)
    for row, col in enumerate(best):
        ax.add_patch(Rectangle((col - 0.5, row - 0.5), 1, 1, fill=False, edgecolor="red",
                               linewidth=2))
    if truth is not None:
        if len(truth) != len(output.segments):
            raise SegmoError(f"plot_similarity_map: {len(truth)} true spans for "
                             f"{len(output.segments)} segments")
        frames = output.windows * FRAMES_PER_TOKEN
        for row, (start, end) in enumerate(truth):
            inside = ((frames[:, 0] >= start) & (frames[:, 1] <= end)).nonzero()[:, 0]
            if len(inside):
                ax.hlines(row + 0.35, int(inside.min()) - 0.5, int(inside.max()) + 0.5,
                          colors="white", linewidth=3)
    ax.set_yticks(range(len(output.segments)))
    ax.set_yticklabels([s if len(s) <= 40 else s[:37] + "..." for s in output.segments])
    step = max(1, len(starts) // 12)
    ax.set_xticks(range(0, len(starts), step))
    sizes = (output.windows[:, 1] - output.windows[:, 0]).unique()
    labels = ([str(s) for s in starts] if len(sizes) == 1
              else [f"{s}+{e - s}" for s, e in output.windows.tolist()])
    ax.set_xticklabels(labels[::step])
    ax.set_xlabel("window start (tokens)" if len(sizes) == 1 else "window start+size (tokens)")
    ax.set_title(title if title is not None else output.text, fontsize=9)
    return ax
