"""Text side: offline text-segment extraction, text encoders and their feature cache.

Heavy dependencies (transformers) are imported only when an LLM backend or an encoder
is actually built.
"""

from segmo.text.cache import TextFeatureCache, update_cache
from segmo.text.encoders import TextEncoder, TextEncoding, get_text_encoder
from segmo.text.llm import (
    OpenAISegmenter,
    TransformersSegmenter,
    get_text_segmenter,
    load_prompt,
    parse_answer,
    validate_segments,
)
from segmo.text.rules import MAX_SEGMENTS, RuleSegmenter, TextSegmenter

__all__ = [
    "MAX_SEGMENTS",
    "OpenAISegmenter",
    "RuleSegmenter",
    "TextEncoder",
    "TextEncoding",
    "TextFeatureCache",
    "TextSegmenter",
    "TransformersSegmenter",
    "get_text_segmenter",
    "get_text_encoder",
    "load_prompt",
    "parse_answer",
    "update_cache",
    "validate_segments",
]
