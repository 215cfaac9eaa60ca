"""Pure `torch.nn` models (no Lightning): the tokenizer, the transformers and their heads,
the length estimator, the T2M evaluator and the action classifier.

Importing the package registers every model kind (`registry`), which
`pretrained.load_pretrained` dispatches on.
"""

import segmo.models.registry  # noqa: F401
