"""Motion segmenters (uniform, cpd, kmeans) over the token axis; see `segmenters`."""

from segmo.segmentation.segmenters import (
    CPDSegmenter,
    KMeansSegmenter,
    SegmenterName,
    Span,
    boundaries,
    get_motion_segmenter,
    pool_tokens,
    repair_boundaries,
    segment_batch,
    uniform,
    uniform_spans,
)

__all__ = [
    "CPDSegmenter",
    "KMeansSegmenter",
    "SegmenterName",
    "Span",
    "boundaries",
    "get_motion_segmenter",
    "pool_tokens",
    "repair_boundaries",
    "segment_batch",
    "uniform",
    "uniform_spans",
]
