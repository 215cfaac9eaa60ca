"""Temporal-grounding metrics (spec §9): R@1 at temporal IoU 0.3/0.5/0.7 and mean IoU.

A span is (start, end) with `end` exclusive, in any unit (frames, tokens, seconds), as an
array (..., 2). The model-side similarity map lives with the alignment model; here only
the generic window helpers and the metrics.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

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
