"""Evaluation: generation metrics, retrieval, grounding, action order, reports, `segmo evaluate`.

The T2M evaluator these metrics embed with is a model (`segmo.models.evaluator`; its
vocabulary `segmo.text.vocabulary`); `segmo.tasks.evaluator` trains our own.

- `metrics`: R-precision, MM-Dist, FID, Diversity, MultiModality, `evaluate_generation`.
- `retrieval`: TMR-style R@k / median rank; `grounding`: temporal IoU metrics and
  `grounding_accuracy` on the built-in corpus (grounding itself: `segmo.pipeline.grounding`);
- `action_order`: action-sequence recovery on the built-in corpus (imported on demand).
"""

from segmo.evaluation.grounding import grounding_accuracy, grounding_metrics, temporal_iou
from segmo.evaluation.metrics import (
    diversity,
    euclidean_distance_matrix,
    evaluate_generation,
    fid,
    frechet_distance,
    matching_score,
    mean_and_interval,
    multimodality,
    r_precision,
    t2m_embedders,
)
from segmo.evaluation.retrieval import batched_retrieval_metrics, retrieval_metrics

__all__ = [
    "batched_retrieval_metrics", "diversity", "euclidean_distance_matrix", "evaluate_generation",
    "fid", "frechet_distance", "grounding_accuracy", "grounding_metrics", "matching_score",
    "mean_and_interval", "multimodality", "r_precision", "retrieval_metrics", "t2m_embedders",
    "temporal_iou",
]
