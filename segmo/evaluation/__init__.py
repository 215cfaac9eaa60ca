"""Evaluation: the T2M evaluator, generation metrics, retrieval, grounding, action order.

- `evaluator.T2MEvaluator`: text/motion embeddings (kind "evaluator"); `from_official`
  loads the released checkpoint + GloVe files, `segmo.tasks.evaluator` trains our own.
- `metrics`: R-precision, MM-Dist, FID, Diversity, MultiModality, `evaluate_generation`.
- `retrieval`: TMR-style R@k / median rank; `grounding`: temporal IoU metrics;
- `action_order`: action-sequence recovery on the built-in corpus (imported on demand).
"""

from segmo.evaluation.evaluator import EvaluatorConfig, EvaluatorOutput, T2MEvaluator
from segmo.evaluation.grounding import best_span, grounding_metrics, sliding_windows, temporal_iou
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
from segmo.evaluation.words import POS_CATEGORIES, Vocabulary, tag_caption

__all__ = [
    "POS_CATEGORIES", "EvaluatorConfig", "EvaluatorOutput", "T2MEvaluator", "Vocabulary",
    "batched_retrieval_metrics", "best_span", "diversity", "euclidean_distance_matrix",
    "evaluate_generation", "fid", "frechet_distance", "grounding_metrics", "matching_score",
    "mean_and_interval", "multimodality", "r_precision", "retrieval_metrics", "sliding_windows",
    "t2m_embedders", "tag_caption", "temporal_iou",
]
