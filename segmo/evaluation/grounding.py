"""Temporal-grounding metrics (spec §9): R@1 at temporal IoU 0.3/0.5/0.7 and mean IoU,
and `grounding_accuracy`, which grounds the built-in corpus's captions with a model and
scores them against the truth.

A span is (start, end) with `end` exclusive, in any unit (frames, tokens, seconds), as an
array (..., 2). Grounding itself (windows, similarity map, its picture) is
`segmo.pipeline.grounding`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from segmo.data.layout import read_ground_truth, read_motion, read_split
from segmo.errors import SegmoError
from segmo.models.tokenizer import FRAMES_PER_TOKEN
from segmo.segmentation import segment_batch

if TYPE_CHECKING:
    # For the annotation only: the metrics above need no model, and importing them should
    # not load the pipeline.
    from segmo.pipeline.segmo import SegMo

IOU_THRESHOLDS: tuple[float, ...] = (0.3, 0.5, 0.7)


def _spans(x: Any, name: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.shape[-1:] != (2,):
        raise ValueError(f"{name}: spans must have shape (..., 2), got {a.shape}")
    if (a[..., 1] < a[..., 0]).any():
        raise ValueError(f"{name}: a span has end < start")
    return a


def temporal_iou(span_a: Any, span_b: Any) -> np.ndarray:
    """IoU of spans (..., 2) and (..., 2), broadcast; 0 where both spans are empty."""
    a, b = _spans(span_a, "temporal_iou span_a"), _spans(span_b, "temporal_iou span_b")
    inter = np.clip(np.minimum(a[..., 1], b[..., 1]) - np.maximum(a[..., 0], b[..., 0]), 0, None)
    union = (a[..., 1] - a[..., 0]) + (b[..., 1] - b[..., 0]) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1), 0.0)


def grounding_metrics(pred_spans: Any, gt_spans: Any, thresholds: Sequence[float] = IOU_THRESHOLDS
                      ) -> dict[str, float]:
    """Top-1 predictions (n, 2) vs ground truth (n, 2) → {"R@1,IoU=0.3", ..., "mIoU"}."""
    pred, gt = _spans(pred_spans, "grounding_metrics pred"), _spans(gt_spans, "grounding_metrics gt")
    if pred.shape != gt.shape or pred.ndim != 2 or len(pred) == 0:
        raise ValueError(f"grounding_metrics: pred {pred.shape} and gt {gt.shape} must both be (n>0, 2)")
    iou = temporal_iou(pred, gt)
    out = {f"R@1,IoU={t:g}": float((iou >= t).mean()) for t in thresholds}
    out["mIoU"] = float(iou.mean())
    return out


def auto_windows(num_tokens: int, num_segments: int) -> list[int]:
    """Window sizes in tokens for grounding `num_segments` segments in `num_tokens` tokens
    when their lengths are unknown: 0.5–2× the mean segment length (multi-scale)."""
    mean = num_tokens / num_segments
    return sorted({max(1, min(num_tokens, round(mean * k))) for k in (0.5, 0.75, 1, 1.5, 2)})


def grounding_accuracy(model: SegMo, data_root: str | Path, split: str = "test",
                       max_motions: int | None = 50, search: str | None = None,
                       window: int | Sequence[int] | str | None = None, stride: int | None = None,
                       threshold: float = 0.5) -> dict[str, float]:
    """Ground every multi-segment caption of the built-in corpus and score against the truth.

    For each motion of `split` (first `max_motions`) and each caption with ≥ 2 segments in
    `segments/<id>.json`, the caption is grounded with its ground-truth segment texts
    (`SegMo.ground`: search "ordered" by default, or "spans", or "window" with `window`
    sizes, where "auto" = multi-scale windows of 0.5–2× the mean segment length,
    `auto_windows`, and `stride`, default 1); the chosen span of each segment is compared with its true span.
    Returns the metrics of `grounding_metrics`, `rate` (fraction with IoU ≥ threshold), the
    number of segments, and the same metrics for the uniform split (a text-free baseline).
    """
    root = Path(data_root)
    pred, truth, uniform = [], [], []
    for mid in read_split(root, split)[:max_motions]:
        record = read_ground_truth(root, mid)
        features = read_motion(root, mid)
        if len(features) > model.max_frames + FRAMES_PER_TOKEN - 1:
            continue
        n = len(features) // FRAMES_PER_TOKEN
        for caption in record["captions"]:
            segs = caption["segments"]
            # n // 2: the ordered search gives each segment at least 2 tokens (MIN_TOKENS)
            if not 2 <= len(segs) <= min(model.max_segments, n // 2):
                continue
            size = auto_windows(n, len(segs)) if window == "auto" else window
            out = model.ground(caption["text"], features, search=search, window=size,
                               stride=stride, segments=[s["text"] for s in segs])
            pred += out.best_spans_frames
            truth += [(s["start"], s["end"]) for s in segs]
            uniform += [(FRAMES_PER_TOKEN * s, FRAMES_PER_TOKEN * e) for s, e in segment_batch(
                None, torch.tensor([len(segs)]), torch.tensor([n]))[0].tolist()]
    if not pred:
        raise SegmoError(f"grounding_accuracy: no caption with ≥ 2 segments in {root} ({split})")
    metrics = grounding_metrics(pred, truth, thresholds=(0.3, threshold, 0.7))
    metrics["rate"] = metrics[f"R@1,IoU={threshold:g}"]
    metrics["segments"] = float(len(pred))
    for key, value in grounding_metrics(uniform, truth, thresholds=(threshold,)).items():
        metrics[f"uniform/{key}"] = value
    return metrics
