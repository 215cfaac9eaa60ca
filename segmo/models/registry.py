"""Imports every model module so that `load_pretrained` knows every kind."""

import segmo.models.action_classifier  # noqa: F401
import segmo.models.evaluator  # noqa: F401
import segmo.models.length_estimator  # noqa: F401
import segmo.models.mask_transformer  # noqa: F401
import segmo.models.residual_transformer  # noqa: F401
import segmo.models.tokenizer  # noqa: F401
