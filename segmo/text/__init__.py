"""Text side: offline text-segment extraction, text encoders and their feature cache.

Heavy dependencies (transformers) are imported only when an LLM backend or an encoder
is actually built.
"""

from segmo.text.llm import (
    OpenAISegmenter,
    TransformersSegmenter,
    get_segmenter,
    load_prompt,
    parse_answer,
    validate_segments,
)
from segmo.text.rules import MAX_SEGMENTS, RuleSegmenter, TextSegmenter

__all__ = [
    "MAX_SEGMENTS",
    "OpenAISegmenter",
    "RuleSegmenter",
    "TextSegmenter",
    "TransformersSegmenter",
    "get_segmenter",
    "load_prompt",
    "parse_answer",
    "validate_segments",
]
