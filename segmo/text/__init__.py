"""Text side: offline text-segment extraction, text encoders and their feature cache.

Heavy dependencies are imported on use: torch with the encoders and their cache (so that
`segmo segment-texts` starts without it), transformers when an LLM backend or an encoder
is actually built.
"""

import importlib

# name -> the module that defines it, imported on first use
_EXPORTS = {
    "TextFeatureCache": "segmo.text.cache",
    "update_cache": "segmo.text.cache",
    "TextEncoder": "segmo.text.encoders",
    "TextEncoding": "segmo.text.encoders",
    "get_text_encoder": "segmo.text.encoders",
    "OpenAISegmenter": "segmo.text.llm",
    "TransformersSegmenter": "segmo.text.llm",
    "get_text_segmenter": "segmo.text.llm",
    "load_prompt": "segmo.text.llm",
    "parse_answer": "segmo.text.llm",
    "validate_segments": "segmo.text.llm",
    "MAX_SEGMENTS": "segmo.text.rules",
    "RuleSegmenter": "segmo.text.rules",
    "TextSegmenter": "segmo.text.rules",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'segmo.text' has no attribute {name!r}")


def __dir__() -> list[str]:  # completion in notebooks lists the lazy names too
    return sorted([*globals(), *__all__])
