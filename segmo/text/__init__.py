"""Text side: offline text-segment extraction, text encoders and their feature cache."""

from segmo.text.rules import RuleSegmenter

__all__ = ["RuleSegmenter"]
