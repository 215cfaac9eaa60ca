"""Model-side grounding and retrieval in SegMo's learned segment space (paper §4.4).

The query text and the motion both go through the mask transformer, UNMASKED and
conditioned on the text and its segments, fed as a set (without their order embeddings,
the mode `MaskTask.order_drop_prob` trains), so that a segment is located by content.
Text segments are the alignment head's `embed_text` of the segments' projected text
vectors; motion segments are its `embed_motion` (mean ‖ max pooling + MLP) over token
spans of the motion outputs. Cosine similarity compares them. Because the motion
features depend on the text prefix, every (text, motion) pair is its own forward pass;
pairs are batched.

    out = model.ground("a person walks forward, then waves", features)   # (t, 263) raw
    print(out)                       # best frame span per text segment
    plot_similarity_map(out)         # paper Fig. 5
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F

from segmo.data.layout import read_ground_truth, read_motion, read_split
from segmo.errors import SegmoError
from segmo.evaluation.grounding import best_span, grounding_metrics, sliding_windows
from segmo.generation.generate import UNIT_LENGTH
from segmo.models.alignment import AlignmentHead
from segmo.pipeline.outputs import GroundingOutput
from segmo.segmentation import segment_batch

if TYPE_CHECKING:
    from segmo.pipeline.segmo import SegMo

BATCH = 32  # pairs per forward pass in retrieval


def alignment_head(model: SegMo) -> AlignmentHead:
    head = model.mask.alignment
    if head is None:
        raise SegmoError("SegMo: this mask transformer was trained without segment alignment "
                         "(alignment: none), so it has no shared text/motion space; grounding, "
                         "retrieval and embed_pairs need a model trained with alignment")
    return head


def _as_tensor(motion: Any) -> torch.Tensor:
    return motion.float() if isinstance(motion, torch.Tensor) else torch.as_tensor(
        np.asarray(motion, dtype=np.float32))


def batch_motions(model: SegMo, motions: Any, lengths: Any = None, normalized: bool = False
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Motions → z-scored (b, t, d) padded with zeros, and frames (b,) (multiples of 4).

    motions: a list of (t_i, d) arrays/tensors, or a (b, t, d) tensor with `lengths` (b,)
    frames. Raw features are z-scored with the tokenizer's statistics unless `normalized`.
    Each motion is cut to a multiple of 4 frames (the tokenizer's unit).
    """
    if isinstance(motions, (torch.Tensor, np.ndarray)) and np.ndim(motions) == 3:
        x = _as_tensor(motions)
        frames = (torch.full((x.shape[0],), x.shape[1]) if lengths is None
                  else torch.as_tensor(lengths).long().reshape(-1).cpu())
        if len(frames) != x.shape[0]:
            raise SegmoError(f"embed_pairs: {len(frames)} lengths for {x.shape[0]} motions")
        motions = [x[i, : int(n)] for i, n in enumerate(frames)]
    elif lengths is not None:
        raise SegmoError("embed_pairs: lengths are only used with a (b, t, d) motion tensor")
    rows = []
    for motion in motions:
        if normalized:
            x = _as_tensor(motion)
            if x.ndim != 2 or x.shape[1] != model.tokenizer.config.feature_dim:
                raise SegmoError(f"embed_pairs: a motion must be (t, "
                                 f"{model.tokenizer.config.feature_dim}), got {tuple(x.shape)}")
            usable = x.shape[0] - x.shape[0] % UNIT_LENGTH
            if not UNIT_LENGTH <= usable <= model.max_frames:
                raise SegmoError(f"embed_pairs: a motion must have {UNIT_LENGTH}.."
                                 f"{model.max_frames + 3} frames, got {x.shape[0]}")
            rows.append(x[:usable].to(model.device))
        else:
            rows.append(model.normalize_motion(motion)[0][0])
    if not rows:
        raise SegmoError("embed_pairs: no motion given")
    frames = torch.tensor([len(r) for r in rows], device=model.device)
    z = torch.zeros(len(rows), int(frames.max()), rows[0].shape[1], device=model.device)
    for i, r in enumerate(rows):
        z[i, : len(r)] = r
    return z, frames


def _forward(model: SegMo, z: torch.Tensor, frames: torch.Tensor, texts: list[str],
             segments: list[list[str]] | None):
    """One unmasked pass: → (mask transformer output, token lengths (b,), segment_mask,
    per-token tokenizer latents (b, n, c) for the cpd/kmeans segmenters)."""
    sentence, vectors, segment_mask, _ = model.text_condition(texts, segments)
    if len(texts) != z.shape[0]:
        raise SegmoError(f"embed_pairs: {len(texts)} texts for {z.shape[0]} motions")
    with torch.inference_mode():
        latents = model.tokenizer.encoder(z.transpose(1, 2)).transpose(1, 2)
        base = model.tokenizer.encode(z)[..., 0]
        n_valid = frames // UNIT_LENGTH
        token_mask = torch.arange(base.shape[1], device=z.device) < n_valid[:, None]
        # Segments as a set: the motion features must say where each segment is from what
        # the motion does, not from where the caption put it (`TextPrefix`).
        unordered = torch.ones(len(texts), dtype=torch.bool, device=z.device)
        out = model.mask(base, token_mask, sentence, vectors, segment_mask, unordered=unordered)
    return out, n_valid, segment_mask, latents


def embed_pairs(model: SegMo, texts: list[str], motions: Any, spans: Any = None, *,
                segments: list[list[str]] | None = None, lengths: Any = None,
                normalized: bool = False, region: tuple[int, int] | None = None
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Text i's segments paired with spans of motion i, in the learned space.

    texts (b); motions as in `batch_motions`; spans: None (the bundle's motion segmenter,
    "uniform" by default), "uniform" / "cpd" / "kmeans" (segmo.segmentation, as many
    spans as each text has segments), or explicit token spans (b, a, 2) with (0, 0) for
    absent slots; region: (start, end) tokens that the generated spans must cover instead
    of the whole motion. → text (b, a, out_dim), motion (b, a, out_dim), mask (b, a) bool
    (slot i has a text segment and a non-empty span). Segments beyond the motion's token
    count sit out (masked), as in training.
    """
    head = alignment_head(model)
    z, frames = batch_motions(model, motions, lengths, normalized)
    out, n_valid, segment_mask, latents = _forward(model, z, frames, list(texts), segments)
    b, a = segment_mask.shape
    if spans is None:
        spans = model.config.motion_segmenter
    if isinstance(spans, str):
        start = torch.zeros_like(n_valid)
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
        spans = torch.as_tensor(spans, device=z.device).long()
        if spans.shape != (b, a, 2):
            raise SegmoError(f"embed_pairs: explicit spans must be (b={b}, a={a}, 2) token "
                             f"spans, got {tuple(spans.shape)}")
        if bool((spans[..., 1] > n_valid[:, None]).any()):
            raise SegmoError("embed_pairs: a span ends past its motion's token count")
    spans = spans.to(z.device)
    with torch.inference_mode():
        text = head.embed_text(out.segment_features)
        motion = head.embed_motion(out.motion_features, spans)
    mask = segment_mask & (spans[..., 1] > spans[..., 0])
    return text, motion, mask


def pair_scores(text: torch.Tensor, motion: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(b,) mean cosine of each row's valid segment pairs: the retrieval score."""
    cosine = F.cosine_similarity(text, motion, dim=-1)
    weight = mask.to(cosine.dtype)
    return (cosine * weight).sum(-1) / weight.sum(-1).clamp(min=1.0)


def ground(model: SegMo, text: str, motion: Any, window: int | Sequence[int] = 5,
           stride: int = 1, segments: list[str] | None = None) -> GroundingOutput:
    """Similarity of each text segment with every sliding window of the motion.

    motion: raw features (t, d); window: size(s) in tokens (a list gives multi-scale
    windows); stride in tokens. The best window of each segment, ×4, is its frame span.
    """
    head = alignment_head(model)
    z, t = model.normalize_motion(motion)
    frames = torch.tensor([z.shape[1]], device=z.device)
    out, n_valid, _, _ = _forward(model, z, frames, [text],
                                  None if segments is None else [segments])
    used = model.segment_texts([text])[0] if segments is None else list(segments)
    windows = torch.from_numpy(sliding_windows(int(n_valid[0]), window, stride))
    with torch.inference_mode():
        similarity = head.similarity_map(out.motion_features, out.segment_features,
                                         windows.to(z.device))[0].float().cpu()
    best = best_span(similarity, windows) * UNIT_LENGTH
    return GroundingOutput(
        text=text, segments=used, windows=windows, similarity=similarity,
        best_spans_frames=[(int(s), int(min(e, t))) for s, e in best],
        best_scores=similarity.max(dim=-1).values.tolist(), num_frames=t)


def _top(scores: torch.Tensor, top_k: int) -> list[tuple[int, float]]:
    if isinstance(top_k, bool) or not isinstance(top_k, int) or top_k < 1:
        raise SegmoError(f"SegMo: top_k must be a whole number >= 1, got {top_k!r}")
    order = scores.argsort(descending=True, stable=True)[:top_k]
    return [(int(i), float(scores[i])) for i in order]


def retrieve_texts(model: SegMo, motion: Any, candidates: list[str],
                   span: tuple[int, int] | None = None, top_k: int = 5
                   ) -> list[tuple[str, float]]:
    """Rank candidate texts for a motion, or for frames [start, end) of it.

    Each candidate is split into its text segments and paired with as many uniform spans
    of the motion (or of the span); its score is the mean paired cosine.
    """
    if not candidates:
        raise SegmoError("retrieve_texts: no candidate texts")
    region = None
    if span is not None:
        start, end = int(span[0]), int(span[1])
        if not 0 <= start < end:
            raise SegmoError(f"retrieve_texts: span must satisfy 0 ≤ start < end, got {span}")
        region = (start // UNIT_LENGTH, math.ceil(end / UNIT_LENGTH))
    scores = []
    for i in range(0, len(candidates), BATCH):
        chunk = list(candidates[i: i + BATCH])
        pairs = embed_pairs(model, chunk, [motion] * len(chunk), "uniform", region=region)
        scores.append(pair_scores(*pairs).cpu())
    return [(candidates[i], s) for i, s in _top(torch.cat(scores), top_k)]


def retrieve_motions(model: SegMo, text: str, motions: list, top_k: int = 5
                     ) -> list[tuple[int, float]]:
    """Rank motions (raw features (t_i, d)) for a text → [(index, score)], best first."""
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
        frames = output.windows * UNIT_LENGTH
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


def grounding_accuracy(model: SegMo, data_root: str | Path, split: str = "test",
                       max_motions: int | None = 50, window: int | Sequence[int] | str = "auto",
                       stride: int = 1, threshold: float = 0.5) -> dict[str, float]:
    """Ground every multi-segment caption of the built-in corpus and score against the truth.

    For each motion of `split` (first `max_motions`) and each caption with ≥ 2 segments in
    `segments/<id>.json`, the caption is grounded with its ground-truth segment texts; the
    best span of each segment is compared with its true span. window "auto" = multi-scale
    windows of 0.5–2× the mean segment length (a/n known from the query). Returns the
    metrics of `grounding_metrics`, `rate` (fraction with IoU ≥ threshold), the number of
    segments, and the same metrics for the uniform split (a text-free baseline).
    """
    root = Path(data_root)
    pred, truth, uniform = [], [], []
    for mid in read_split(root, split)[:max_motions]:
        record = read_ground_truth(root, mid)
        features = read_motion(root, mid)
        if len(features) > model.max_frames + UNIT_LENGTH - 1:
            continue
        n = len(features) // UNIT_LENGTH
        for caption in record["captions"]:
            segs = caption["segments"]
            if not 2 <= len(segs) <= min(model.max_segments, n):
                continue
            size = window
            if window == "auto":
                mean = n / len(segs)
                size = sorted({max(1, min(n, round(mean * k))) for k in (0.5, 0.75, 1, 1.5, 2)})
            out = ground(model, caption["text"], features, size, stride,
                         segments=[s["text"] for s in segs])
            pred += out.best_spans_frames
            truth += [(s["start"], s["end"]) for s in segs]
            uniform += [(UNIT_LENGTH * s, UNIT_LENGTH * e) for s, e in segment_batch(
                None, torch.tensor([len(segs)]), torch.tensor([n]))[0].tolist()]
    if not pred:
        raise SegmoError(f"grounding_accuracy: no caption with ≥ 2 segments in {root} ({split})")
    metrics = grounding_metrics(pred, truth, thresholds=(0.3, threshold, 0.7))
    metrics["rate"] = metrics[f"R@1,IoU={threshold:g}"]
    metrics["segments"] = float(len(pred))
    for key, value in grounding_metrics(uniform, truth, thresholds=(threshold,)).items():
        metrics[f"uniform/{key}"] = value
    return metrics
